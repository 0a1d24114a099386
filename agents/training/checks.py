"""Checks of single configuration values: each check returns the value (normalised, e.g. ``1e5``
to ``100000`` for an integer) or raises :class:`Bad` with what was expected and the likely
mistake; :class:`Section` groups the checks of one configuration section.
:mod:`agents.training.schema` says which key gets which check."""
from __future__ import annotations

import inspect
import math
from typing import Any, Mapping, Sequence


class Bad(Exception):
    """A value failed its check: what was expected, and the likely mistake."""

    def __init__(self, expected: str, hint: str = ""):
        super().__init__(expected)
        self.expected, self.hint = expected, hint


def is_real(v: Any) -> bool:
    try:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    except OverflowError:  # an integer beyond any float
        return False


def type_hint(v: Any, what: str = "number") -> str:
    """The likely mistake behind ``v`` where a ``what`` was expected."""
    if isinstance(v, bool):
        return f"true/false is not a {what}"
    if v is None:
        return "the entry is empty (null)"
    if isinstance(v, str):
        try:
            float(v)
        except ValueError:
            return f"it is text, not a {what}"
        return (f"YAML 1.1 reads {v} as text: in a YAML file write a decimal point and a signed "
                f"exponent (1.0e-4, 1.0e+6) or the plain number; --set reads it as a number")
    if isinstance(v, float) and not math.isfinite(v):
        return "not a finite number"
    if isinstance(v, (list, dict)):
        return f"a {type(v).__name__}, not a single {what}"
    return ""


def _bounds(lo: float | None, hi: float | None, lo_open: bool = False,
            hi_open: bool = False, integer: bool = False) -> str:
    if integer and lo is not None and hi is not None:
        return f" from {lo:,} to {hi:,}"
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi:g}"
    return ""


def integer(lo: int | None = None, hi: int | None = None):
    expected = "an integer" + _bounds(lo, hi, integer=True)

    def check(v: Any) -> int:
        if isinstance(v, float) and v.is_integer():  # 1e5 from --set: a whole number
            v = int(v)
        if not isinstance(v, int) or isinstance(v, bool):
            raise Bad(expected, type_hint(v, "integer")
                      or (f"{v!r} is not a whole number" if is_real(v) else ""))
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise Bad(expected)
        return v
    return check


def number(lo: float | None = None, hi: float | None = None, lo_open: bool = False,
           hi_open: bool = False):
    expected = "a finite number" + _bounds(lo, hi, lo_open, hi_open)

    def check(v: Any) -> float:
        if not is_real(v):
            raise Bad(expected, type_hint(v))
        if lo is not None and (v < lo or (lo_open and v == lo)) or hi is not None and (
                v > hi or (hi_open and v == hi)):
            raise Bad(expected)
        return v
    return check


def boolean(v: Any) -> bool:
    if not isinstance(v, bool):
        raise Bad("true or false", "text: write true or false without quotes"
                  if isinstance(v, str) else "")
    return v


def choice(options: Sequence[str]):
    def check(v: Any) -> str:
        if not isinstance(v, str) or v not in options:
            from pneugym.params import did_you_mean

            raise Bad(f"one of {list(options)}", did_you_mean(v, options).strip(" ()"))
        return v
    return check


def optional(spec):
    def check(v: Any) -> Any:
        return None if v is None else spec(v)
    return check


def list_of(spec, lo: int = 1, hi: int = 1000, what: str = "values"):
    def check(v: Any) -> list:
        if not isinstance(v, list) or not lo <= len(v) <= hi:
            raise Bad(f"a list of {lo} to {hi} {what}", type_hint(v, "list")
                      if not isinstance(v, list) else f"it has {len(v)}")
        out = []
        for i, x in enumerate(v):
            try:
                out.append(spec(x))
            except Bad as bad:
                raise Bad(f"a list of {what}; item {i} ({x!r}) is not {bad.expected}",
                          bad.hint) from None
        return out
    return check


def mapping(v: Any) -> Any:
    if v is not None and not isinstance(v, Mapping):
        raise Bad("a section (key: value entries) or null")
    return v


def anything(v: Any) -> Any:
    return v


def text(v: Any) -> str:
    if not isinstance(v, str) or not v.strip():
        raise Bad("a non-empty path (text)")
    return v


def by_default(default: Any):
    """A check from a keyword's default value (for keywords without a check of their own)."""
    if isinstance(default, bool):
        return boolean
    if isinstance(default, int):
        return integer()
    if isinstance(default, float):
        return number()
    return anything


class Section:
    """A configuration section: its keys and their checks (a check, or a nested section), the
    keys it must have, keys that are refused with a reason, and what its keys are."""

    def __init__(self, fields: Mapping[str, Any], what: str, required: Sequence[str] = (),
                 refused: Mapping[str, str] | None = None, nullable: bool = False):
        self.fields, self.what, self.required = dict(fields), what, tuple(required)
        self.refused, self.nullable = dict(refused or {}), nullable


def signature_section(cls, what: str, refused: Mapping[str, str], skip: Sequence[str] = (),
                      specs: Mapping[str, Any] | None = None) -> Section:
    """A section of the keyword arguments of ``cls`` (minus ``refused`` and ``skip``), each
    checked by ``specs`` or by its default's type."""
    fields = {}
    for name, p in inspect.signature(cls.__init__).parameters.items():
        if name == "self" or name in refused or name in skip or p.kind in (
                p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        fields[name] = (specs or {}).get(name) or by_default(p.default)
    return Section(fields, what, refused=refused)

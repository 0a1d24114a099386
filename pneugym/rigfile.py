"""Rig files: a :class:`~pneugym.params.RigParams` as JSON or YAML, read strictly.

A rig file (``.json``, ``.yaml`` or ``.yml``) holds a rig's hardware and operating point in SI
units, pressures absolute unless a name says ``gauge``. It has one of two forms:

- the **parameter form**: :meth:`RigParams.to_dict` (``supply_pressure_gauge_pa``,
  ``load_mass_kg`` and the groups ``gas``, ``cylinder``, ``line``, ``valve``, ``friction``,
  ``effects``, ``solver``). :func:`save` writes it with ``format: pneugym-rig/1``; the discrepancy
  workflow writes it as ``updated_model.json``;
- the **measurement form**: the ``rig`` section of a measured run (``MEASUREMENT_FORMAT.md``)
  with ``supply_pressure_gauge_pa``, ``load_mass_kg``, ``ambient_pressure_pa`` and
  ``ambient_temperature_k`` beside it; a whole ``pneugym-measurement/1`` JSON loads too.

Either may be partial: what the file does not give keeps ``base`` (default: the thesis rig).
Reading is strict: an unknown key (with the nearest known one), a duplicated key, NaN or
infinity, text or a boolean where a number belongs, an implausible value (a unit slip such as a
bore in mm given as m), two forms mixed, or a file over 1 MB are refused with a
:class:`RigFileError` naming the file and the key.

>>> rig = RigParams.load("my_rig.yaml")                  # doctest: +SKIP
>>> rig.save("my_rig.json")                              # doctest: +SKIP
>>> print(describe_difference(RigParams(), rig))         # doctest: +SKIP
line.length_m 0.725 -> 2.5

``python -m pneugym.rigfile FILE [FILE2]`` (``pneugym rig``) checks a file and shows the rig.
"""
from __future__ import annotations

import argparse
import json
import math
import numbers
import os
import re
import sys
from collections import Counter
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .data import FORMAT as MEASUREMENT_FORMAT
from .data import PLAUSIBLE, TEXT_KEYS
from .data import TOP_KEYS as MEASUREMENT_TOP_KEYS
from .data import _near_miss
from .outputs import atomic_write_text, check_output_file
from .params import (
    MEASUREMENT_FRICTION_KEYS, MEASUREMENT_RIG_KEYS, MEASUREMENT_TOP_FIELDS, RigParams, did_you_mean,
)

#: ``format`` of the files :func:`save` writes.
FORMAT = "pneugym-rig/1"
#: File extensions of rig files (matched case-insensitively).
SUFFIXES = (".json", ".yaml", ".yml")
#: Largest rig file read [bytes]: a rig file is a few kB.
MAX_BYTES = 1_000_000

_THESIS = RigParams()
#: group name -> its dataclass (``cylinder`` -> CylinderParams, ...)
GROUPS: dict[str, type] = {f.name: type(getattr(_THESIS, f.name)) for f in fields(_THESIS)
                           if is_dataclass(getattr(_THESIS, f.name))}
_TOP = tuple(f.name for f in fields(RigParams))
#: top-level keys of the measurement form
_MEASUREMENT_TOP = (*MEASUREMENT_TOP_FIELDS, "ambient_pressure_pa", "ambient_temperature_k",
                    "rig")
#: top-level keys only the measurement form has
_MEASUREMENT_ONLY = ("rig", "ambient_pressure_pa", "ambient_temperature_k")
#: (group, field) -> key of the measurement form
_MEASUREMENT_NAME = {
    **{v: f"rig.{k}" for k, v in MEASUREMENT_RIG_KEYS.items()},
    **{v: f"rig.friction.{k}" for k, v in MEASUREMENT_FRICTION_KEYS.items()},
    ("gas", "ambient_pressure_pa"): "ambient_pressure_pa",
    ("gas", "ambient_temperature_k"): "ambient_temperature_k",
}
_YAML_HEADER = ("# pneugym rig file: SI units (m, m², m³, kg, s, N, K), pressures in Pa absolute\n"
                "# unless a name says gauge. Check it: python -m pneugym.rigfile FILE\n")


class RigFileError(ValueError):
    """A rig file (or a mapping given as a rig) that is not a valid rig; the message names the
    file (or what was given), the key, what is wrong and the likely mistake."""


# ------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------
def load(path: str | os.PathLike, base: RigParams | None = None) -> RigParams:
    """The rig in ``path`` (``.json``, ``.yaml`` or ``.yml``, any case), in the parameter or the
    measurement form; what the file does not give keeps ``base`` (default: the thesis rig).
    Raises :class:`RigFileError` (a ``ValueError``) naming the file."""
    p = _rig_path(path)
    text = _read_text(p)
    doc = _parse_json(text, p) if p.suffix.lower() == ".json" else _parse_yaml(text, p)
    return _build(doc, base, str(p))


def as_rig(value: Any, what: str = "rig", base: RigParams | None = None) -> RigParams:
    """A :class:`RigParams` from what a user gives as a rig: a RigParams (returned as is), a
    mapping in either form of a rig file (refusals name ``what``), the path of a rig file
    (:func:`load`), or ``None`` (``base``, default the thesis rig)."""
    if isinstance(value, RigParams):
        return value
    if value is None:
        return _base(base)
    if isinstance(value, Mapping):
        return _build(value, base, what)
    if isinstance(value, (str, os.PathLike)):
        return load(value, base)
    raise RigFileError(f"{what} = {value!r:.80} is not a rig: give a RigParams, a mapping of its "
                       f"fields (RigParams.to_dict(), or a measured run's 'rig' form) or the "
                       f"path of a rig file ({', '.join(SUFFIXES)})")


def _rig_path(path: Any) -> Path:
    """``path`` as a Path with a rig file's extension."""
    if not isinstance(path, (str, os.PathLike)) or str(path).strip() == "":
        raise RigFileError(f"rig file path {path!r} is empty or not a path: give a "
                           f"{', '.join(SUFFIXES)} file")
    p = Path(path)
    if p.suffix.lower() not in SUFFIXES:
        hint = " (a measured run's rig is in its .json)" if p.suffix.lower() == ".csv" else ""
        raise RigFileError(f"{p}: a rig file must end in .json, .yaml or .yml (any case), not "
                           f"{p.suffix or 'no extension'!r}{hint}")
    return p


def _read_text(p: Path) -> str:
    """The UTF-8 text of ``p``, refused when missing, not a file, over :data:`MAX_BYTES` or empty."""
    try:
        if not p.is_file():
            raise RigFileError(f"{p}: {'is a folder' if p.is_dir() else 'file not found'}: give "
                               f"the path of a rig file")
        if p.stat().st_size > MAX_BYTES:
            raise _too_big(p, p.stat().st_size)
        with open(p, "rb") as fh:
            raw = fh.read(MAX_BYTES + 1)
    except OSError as exc:
        raise RigFileError(f"{p}: cannot be read: {exc.strerror or exc}") from None
    if len(raw) > MAX_BYTES:
        raise _too_big(p, len(raw))
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise RigFileError(f"{p}: not UTF-8 text ({exc.reason} at byte {exc.start}): is it a "
                           f"rig file?") from None
    if not text.strip():
        raise RigFileError(f"{p}: the file is empty; a rig file holds keys such as "
                           f"'cylinder: {{bore_m: 0.125}}'")
    return text


def _too_big(p: Path, size: int) -> RigFileError:
    return RigFileError(f"{p}: {size / 1e6:.1f} MB is too large for a rig file (at most "
                        f"{MAX_BYTES / 1e6:g} MB; one is a few kB): is it the right file?")


class _Object(dict):
    """A JSON object in which a key appears more than once (``repeated``: those keys)."""

    repeated: list[str]


def _json_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``object_pairs_hook`` that remembers repeated keys (``json`` keeps the last silently)."""
    counts = Counter(k for k, _ in pairs)
    if len(counts) == len(pairs):
        return dict(pairs)
    obj = _Object(pairs)
    obj.repeated = [k for k, n in counts.items() if n > 1]
    return obj


def _parse_json(text: str, p: Path) -> Any:
    try:  # NaN and Infinity are read as floats, then refused with their key by _check_tree
        return json.loads(text, object_pairs_hook=_json_object, parse_constant=float)
    except json.JSONDecodeError as exc:
        raise RigFileError(f"{p}: not valid JSON: {exc}") from None
    except RecursionError:
        raise RigFileError(f"{p}: not valid JSON: nested too deeply") from None


def _parse_yaml(text: str, p: Path) -> Any:
    import yaml

    try:
        _check_yaml_nodes(yaml.compose(text, Loader=yaml.SafeLoader), p)
        return yaml.safe_load(text)
    except yaml.constructor.ConstructorError as exc:
        raise RigFileError(f"{p}: plain YAML only: tags such as !!python/... are refused: "
                           f"{' '.join(str(exc).split())}") from None
    except yaml.YAMLError as exc:
        raise RigFileError(f"{p}: not valid YAML: {' '.join(str(exc).split())}") from None
    except RecursionError:
        raise RigFileError(f"{p}: not valid YAML: nested too deeply") from None


def _check_yaml_nodes(root: Any, p: Path) -> None:
    """Refuse repeated keys (YAML keeps the last silently) and aliases (``*name``: a rig file
    writes its values out; an alias bomb would expand to gigabytes)."""
    import yaml

    seen: set[int] = set()
    stack: list[tuple[str, Any]] = [("", root)]
    while stack:
        where, node = stack.pop()
        if node is None:
            continue
        if id(node) in seen:
            raise RigFileError(f"{p}: line {node.start_mark.line + 1}: anchors and aliases "
                               f"(&name, *name) are not supported in a rig file: write the "
                               f"values out")
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            lines: dict[str, int] = {}
            for key, value in node.value:
                name = _join(where, key.value) if isinstance(key, yaml.ScalarNode) else where
                if isinstance(key, yaml.ScalarNode) and key.value in lines:
                    raise RigFileError(
                        f"{p}: key {name!r} appears twice (line {lines[key.value]}, then line "
                        f"{key.start_mark.line + 1}); YAML keeps the last one silently, so "
                        f"which is meant is unclear: remove one")
                if isinstance(key, yaml.ScalarNode):
                    lines[key.value] = key.start_mark.line + 1
                stack.append((name, value))
        elif isinstance(node, yaml.SequenceNode):
            stack += [(f"{where}[{i}]", v) for i, v in enumerate(node.value)]
        elif (isinstance(node, yaml.ScalarNode) and node.style is None
              and yaml11_int(node.value) is not None):
            raise RigFileError(f"{p}: line {node.start_mark.line + 1}: {where} = {node.value}: "
                               f"YAML 1.1 reads a leading 0 as octal, 0x as hex and 1:05 as "
                               f"base 60 ({node.value} would be read as "
                               f"{yaml11_int(node.value)}); write the number in decimal")


#: plain integers YAML 1.1 reads in another base: 010 (octal), 0o10, 0x10, 0b10, 1:05 (60)
_YAML11_INT = re.compile(r"[-+]?(0[0-9_]+|0[oxbOXB][0-9a-fA-F_]+|[0-9][0-9_]*(:[0-5]?[0-9])+)")


def yaml11_int(text: str) -> int | None:
    """The integer YAML 1.1 reads a plain scalar ``text`` as, when it is one written in another
    base than ten (``010`` is 8, ``0x10`` 16, ``1:05`` 65); else None."""
    import yaml

    if not _YAML11_INT.fullmatch(text):
        return None
    v = yaml.safe_load(text)
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def _join(where: str, key: Any) -> str:
    return f"{where}.{key}" if where else str(key)


def _real(v: Any) -> bool:
    """A real number that is not a boolean."""
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _check_tree(doc: Mapping[str, Any], where: str) -> None:
    """Every key is text and given once; every number is finite."""
    seen: set[int] = set()
    stack: list[tuple[str, Any]] = [("", doc)]
    while stack:
        path, o = stack.pop()
        if isinstance(o, (Mapping, list, tuple)):
            if id(o) in seen:
                continue
            seen.add(id(o))
        if isinstance(o, Mapping):
            if getattr(o, "repeated", None):
                raise RigFileError(f"{where}: key {_join(path, o.repeated[0])!r} appears more "
                                   f"than once; a JSON reader keeps only the last one silently, "
                                   f"so which is meant is unclear: remove the duplicate")
            for k, v in o.items():
                if not isinstance(k, str):
                    why = " (YAML reads yes/no/on/off as booleans: quote it)" if isinstance(k, bool) else ""
                    raise RigFileError(f"{where}: key {k!r} in "
                                       f"{repr(path) if path else 'the top level'} is not text{why}")
                stack.append((_join(path, k), v))
        elif isinstance(o, (list, tuple)):
            stack += [(f"{path}[{i}]", v) for i, v in enumerate(o)]
        elif _real(o) and not _finite(o):
            raise RigFileError(f"{where}: key {path!r} = {o!r:.40} is not a finite number "
                               f"(NaN, infinity and numbers beyond 1e308 are refused)")


def _finite(v: numbers.Real) -> bool:
    try:
        return math.isfinite(float(v))
    except OverflowError:  # an integer beyond float range
        return False


def _base(base: Any) -> RigParams:
    if base is None:
        return RigParams()
    if not isinstance(base, RigParams):
        raise TypeError(f"base = {base!r:.80} must be a RigParams or None")
    return base


def _build(doc: Any, base: RigParams | None, where: str) -> RigParams:
    """The rig a parsed document describes, over ``base``."""
    if not isinstance(doc, Mapping):
        got = "nothing (an empty file, or only comments)" if doc is None else \
            f"{doc!r:.40} ({type(doc).__name__})"
        raise RigFileError(f"{where}: the top level must be a mapping of keys such as "
                           f"'cylinder: {{bore_m: 0.125}}'; got {got}")
    _check_tree(doc, where)
    base = _base(base)
    if _form(doc, where) == "measurement":
        return _from_measurement(doc, base, where)
    return _from_params(doc, base, where)


def _form(doc: Mapping[str, Any], where: str) -> str:
    """``"params"`` or ``"measurement"``; an unknown ``format`` or both forms mixed are refused."""
    fmt = doc.get("format")
    if "format" in doc and fmt not in (FORMAT, MEASUREMENT_FORMAT):
        raise RigFileError(f"{where}: key 'format' = {fmt!r:.60} is not a rig file's: expected "
                           f"{FORMAT!r}, a measured run's {MEASUREMENT_FORMAT!r}, or no 'format'")
    meas = [k for k in _MEASUREMENT_ONLY if k in doc]
    meas += [f"format: {fmt}"] if fmt == MEASUREMENT_FORMAT else []
    params = [k for k in GROUPS if k in doc] + ([f"format: {fmt}"] if fmt == FORMAT else [])
    if meas and params:
        raise RigFileError(
            f"{where}: mixes the two forms of a rig file: {', '.join(map(repr, meas))} of the "
            f"measurement form (rig: {{bore_m: ...}}, ambient_* at the top) and "
            f"{', '.join(map(repr, params))} of the parameter form (cylinder: {{bore_m: ...}}, "
            f"gas: {{ambient_pressure_pa: ...}}); use one form")
    return "measurement" if meas else "params"


def _unknown(where: str, key: str, known: Sequence[str], hint: str = "") -> RigFileError:
    name = key.rsplit(".", 1)[-1]
    return RigFileError(f"{where}: key {key!r} is unknown{did_you_mean(name, known) or hint}; "
                        f"known here: {', '.join(known)}")


def _is_text(cls: type, name: str) -> bool:
    return any(f.name == name and f.type == "str" for f in fields(cls))


def _number(where: str, key: str, v: Any) -> None:
    """Refuse a number written as text with what to write (YAML 1.1 reads ``1e-4`` as text);
    other non-numbers are refused by the dataclasses."""
    if not isinstance(v, str):
        return
    try:
        f = float(v)
    except ValueError:
        return
    fix = repr(f).replace("e", ".0e") if "e" in repr(f) and "." not in repr(f) else repr(f)
    yaml11 = ("; YAML 1.1 reads a number without a dot or without the exponent's sign, "
              f"such as {v}, as text") if re.fullmatch(r"\s*[-+]?[\d.]+[eE][-+]?\d+\s*", v) else ""
    raise RigFileError(f"{where}: key {key!r} = {v!r} is text, not a number: write {fix} "
                       f"(without quotes){yaml11}")


def _from_params(doc: Mapping[str, Any], base: RigParams, where: str) -> RigParams:
    """The parameter form: :meth:`RigParams.to_dict`'s keys, possibly partial."""
    kw: dict[str, Any] = {}
    for key, value in doc.items():
        if key == "format":
            continue
        if key not in _TOP:
            homes = [f"{g}.{key}" for g, cls in GROUPS.items() if key in _names(cls)]
            hint = f" (it belongs in a group: {' or '.join(homes)})" if homes else ""
            raise _unknown(where, key, ("format", *_TOP), hint)
        if key in GROUPS:
            kw[key] = _group(doc[key], key, where)
        else:
            _number(where, key, value)
            kw[key] = value
    rig = _make(where, lambda: base.with_(**kw), lambda group, name: _join(group, name))
    _plausible(kw, where)  # then the measurement form's plausible ranges (unit slips)
    return rig


def _plausible(doc: Mapping[str, Any], where: str) -> None:
    """Refuse a parameter-form value outside the measurement form's plausible range."""
    for key, value in doc.items():
        items = [("", value)] if key not in GROUPS else \
            value.items() if isinstance(value, Mapping) else ()  # (a group object: checked)
        for name, v in items:
            spec = PLAUSIBLE.get(_MEASUREMENT_NAME.get((key, name), key if not name else ""))
            if spec is not None and _real(v) and not spec.ok(float(v)):
                raise RigFileError(f"{where}: key {_join(key, name) if name else key!r} = "
                                   f"{v!r}: {spec.problem(float(v))}")


def _names(cls: type) -> list[str]:
    return [f.name for f in fields(cls)]


def _group(value: Any, name: str, where: str) -> Any:
    """A group's changes with its keys checked; anything but a mapping (an instance of the
    group's dataclass, or a wrong value) is left to :meth:`RigParams.with_`."""
    if not isinstance(value, Mapping):
        return value
    cls = GROUPS[name]
    for k, v in value.items():
        if k not in _names(cls):
            raise _unknown(where, f"{name}.{k}", _names(cls))
        if not _is_text(cls, k):
            _number(where, f"{name}.{k}", v)
    return dict(value)


def _from_measurement(doc: Mapping[str, Any], base: RigParams, where: str) -> RigParams:
    """The measurement form (a measured run's ``rig`` section and top-level keys), read with
    :meth:`RigParams.from_measurement` and the plausible ranges of :data:`pneugym.data.PLAUSIBLE`."""
    _measurement_top(doc, where)
    rig = _section(doc.get("rig"), "rig", [*MEASUREMENT_RIG_KEYS, "friction"], where)
    friction = _section(rig.get("friction"), "rig.friction", list(MEASUREMENT_FRICTION_KEYS), where)
    leaves = [(k, v) for k, v in doc.items() if k in _MEASUREMENT_TOP and k != "rig"]
    leaves += [(f"rig.{k}", v) for k, v in rig.items() if k != "friction"]
    leaves += [(f"rig.friction.{k}", v) for k, v in friction.items()]
    for key, value in leaves:
        if key in TEXT_KEYS:
            if value not in TEXT_KEYS[key]:
                raise RigFileError(f"{where}: key {key!r} = {value!r:.60}; expected one of "
                                   f"{list(TEXT_KEYS[key])}")
            continue
        _number(where, key, value)
        spec = PLAUSIBLE.get(key)
        if spec is not None and _real(value) and not spec.ok(float(value)):
            raise RigFileError(f"{where}: key {key!r} = {value!r}: {spec.problem(float(value))}")
    meta = {k: doc[k] for k in _MEASUREMENT_TOP if k in doc}
    return _make(where, lambda: RigParams.from_measurement(meta, base),
                 lambda group, name: _MEASUREMENT_NAME.get((group, name), _join(group, name)))


def _measurement_top(doc: Mapping[str, Any], where: str) -> None:
    """Refuse unknown top-level keys of the measurement form. A measured run's JSON (``format:
    pneugym-measurement/1``) keeps its own rule: its other keys are not the rig's, and keys the
    format does not know are ignored unless they look like a misspelt known one."""
    declared = doc.get("format") == MEASUREMENT_FORMAT
    known = MEASUREMENT_TOP_KEYS if declared else ("format", *_MEASUREMENT_TOP)
    for key in doc:
        if key in known or (declared and not _near_miss(key, MEASUREMENT_TOP_KEYS)):
            continue
        hint = f" (in the measurement form it belongs in 'rig': rig.{key})" \
            if key in MEASUREMENT_RIG_KEYS or key == "friction" else ""
        raise _unknown(where, key, known, hint)


def _section(value: Any, name: str, known: Sequence[str], where: str) -> Mapping[str, Any]:
    """An optional mapping of known keys (``None``: empty)."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise RigFileError(f"{where}: key {name!r} = {value!r:.60} must be a mapping of "
                           f"{', '.join(known)}")
    for k in value:
        if k not in known:
            raise _unknown(where, f"{name}.{k}", known)
    return value


_CLASS_GROUP = {cls.__name__: name for name, cls in GROUPS.items()}


def _make(where: str, build: Callable[[], RigParams], key_name: Callable[[str, str], str]) -> RigParams:
    """``build()``; a refusal by the dataclasses (``CylinderParams.bore_m = ...``) is re-raised
    naming ``where`` and the document's key (``key_name(group, field)``, group ``""`` for a
    top-level field)."""
    try:
        return build()
    except (ValueError, TypeError) as exc:
        m = re.match(r"(\w+Params)\.(\w+)", str(exc))
        key = ""
        if m and (m.group(1) == "RigParams" or m.group(1) in _CLASS_GROUP):
            key = f"key {key_name(_CLASS_GROUP.get(m.group(1), ''), m.group(2))!r}: "
        raise RigFileError(f"{where}: {key}{exc}") from None


# ------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------
def save(rig: RigParams, path: str | os.PathLike) -> Path:
    """Write ``rig`` to ``path`` (``.json``, ``.yaml`` or ``.yml``) as
    ``{"format": "pneugym-rig/1", **rig.to_dict()}``, atomically (a reader sees the old file or
    the new one); :func:`load` gives back an equal rig. Refuses a folder, another extension or
    a rig :func:`load` would refuse (a value outside the plausible ranges)."""
    if not isinstance(rig, RigParams):
        raise TypeError(f"save needs a RigParams, got {type(rig).__name__}")
    p = _rig_path(path)
    check_output_file(p, "rig file")
    doc = {"format": FORMAT, **_plain(rig.to_dict())}
    _plausible(doc, f"cannot save {p}")
    if p.suffix.lower() == ".json":
        text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
    else:
        import yaml

        text = _YAML_HEADER + yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)
    return atomic_write_text(p, text)


def _plain(o: Any) -> Any:
    """Tuples as lists, recursively (what JSON and YAML hold)."""
    if isinstance(o, dict):
        return {k: _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    return o


# ------------------------------------------------------------------------------------------
# comparing
# ------------------------------------------------------------------------------------------
def rig_fields(rig: RigParams) -> dict[str, Any]:
    """Every field of ``rig`` by its dotted name (``"cylinder.bore_m"``, ``"load_mass_kg"``), in
    the order of :meth:`RigParams.to_dict`."""
    out: dict[str, Any] = {}
    for f in fields(rig):
        v = getattr(rig, f.name)
        if is_dataclass(v):
            out.update({f"{f.name}.{g.name}": getattr(v, g.name) for g in fields(v)})
        else:
            out[f.name] = v
    return out


def _same(x: Any, y: Any, rel_tol: float) -> bool:
    if isinstance(x, tuple) and isinstance(y, tuple):
        return len(x) == len(y) and all(_same(a, b, rel_tol) for a, b in zip(x, y))
    if _real(x) and _real(y):
        return math.isclose(x, y, rel_tol=rel_tol, abs_tol=0.0)
    return x == y


def rig_difference(a: RigParams, b: RigParams, rel_tol: float = 1e-9) -> dict[str, tuple[Any, Any]]:
    """The fields whose values differ between ``a`` and ``b`` (numbers by more than ``rel_tol``,
    relative), as ``{dotted name: (a's value, b's value)}`` in field order; empty when equal."""
    fa, fb = rig_fields(a), rig_fields(b)
    return {k: (fa[k], fb[k]) for k in fa if not _same(fa[k], fb[k], rel_tol)}


def _show(v: Any, digits: int) -> str:
    """``v`` with ``digits`` significant digits: positional from 1e-3 to 1e6, else scientific."""
    if not _real(v) or isinstance(v, numbers.Integral):
        return str(list(map(list, v))) if isinstance(v, tuple) else str(v)
    if v == 0 or 1e-3 <= abs(v) < 1e6:
        return np.format_float_positional(v, precision=digits, unique=False, fractional=False,
                                          trim="-")
    return np.format_float_scientific(v, precision=digits - 1, unique=False, exp_digits=2)


def _change(x: Any, y: Any) -> str:
    """``"x -> y"`` with the fewest digits (from 3) that tell the two values apart."""
    for digits in range(3, 18):
        sx, sy = _show(x, digits), _show(y, digits)
        if sx != sy:
            break
    return f"{sx} -> {sy}"


def describe_difference(a: RigParams, b: RigParams, limit: int = 6, largest_first: bool = False) -> str:
    """One line naming how ``b`` differs from ``a``, at most ``limit`` fields:
    ``"cylinder.dead_volume_m3 2.44e-04 -> 1.00e-04, line.length_m 0.725 -> 2.5 (+3 more)"``;
    ``""`` when they are equal. Fields in field order, or with ``largest_first`` by relative
    change (a change from or to zero, or of a text, counts as the largest)."""
    diff = rig_difference(a, b)
    if largest_first:
        diff = dict(sorted(diff.items(), key=lambda kv: -_relative_change(*kv[1])))
    parts = [f"{k} {_change(x, y)}" for k, (x, y) in list(diff.items())[:max(limit, 0)]]
    more = f" (+{len(diff) - len(parts)} more)" if len(diff) > len(parts) else ""
    return ", ".join(parts) + more


def _relative_change(x: Any, y: Any) -> float:
    """``|y - x| / max(|x|, |y|)`` for two numbers, 1 otherwise (texts, tuples, None)."""
    if not (_real(x) and _real(y)):
        return 1.0
    big = max(abs(float(x)), abs(float(y)))
    return abs(float(y) - float(x)) / big if big > 0 else 0.0


# ------------------------------------------------------------------------------------------
# the command
# ------------------------------------------------------------------------------------------
_UNITS = (("_n_s_per_m", "N s/m"), ("_j_per_kg_k", "J/(kg K)"), ("_pa_s", "Pa s"),
          ("_m_s", "m/s"), ("_m2", "m²"), ("_m3", "m³"), ("_gauge_pa", "Pa gauge"),
          ("_pa", "Pa absolute"), ("_kg", "kg"), ("_m", "m"), ("_s", "s"), ("_n", "N"), ("_k", "K"))


def _unit(key: str) -> str:
    if key.endswith("tee_volumes"):
        return "(position m, volume m³) pairs"
    return next((u for suffix, u in _UNITS if key.endswith(suffix)), "")


def _yaml_value(v: Any) -> str:
    """``v`` as a YAML 1.1 scalar or flow list that reads back exactly."""
    if v is None:
        return "null"
    if isinstance(v, tuple):
        return "[" + ", ".join(_yaml_value(x) for x in v) + "]"
    if isinstance(v, float):
        s = repr(v)
        return s.replace("e", ".0e") if "e" in s and "." not in s else s
    return str(v)


def format_rig(rig: RigParams, ref: RigParams | None = None, ref_name: str = "the thesis rig") -> str:
    """``rig`` as YAML (a valid rig file) with each value's unit in a comment, and ``ref``'s
    value beside each field that differs from it."""
    diff = rig_difference(ref, rig) if ref is not None else {}
    rows: list[tuple[str, str]] = [(f"format: {FORMAT}", "")]
    group = ""
    for key, v in rig_fields(rig).items():
        g, _, name = key.rpartition(".")
        if g and g != group:
            rows.append((f"{g}:", ""))
        group = g
        note = [_unit(key)] + ([f"{ref_name}: {_yaml_value(diff[key][0])}"] if key in diff else [])
        rows.append((f"{'  ' if g else ''}{name}: {_yaml_value(v)}", "; ".join(n for n in note if n)))
    width = max(len(r) for r, _ in rows) + 2
    return "\n".join(f"{r:<{width}}# {c}" if c else r for r, c in rows)


def main(argv: Sequence[str] | None = None) -> int:
    """``pneugym rig FILE [FILE2]``: check a rig file, print the rig (YAML, units in comments)
    and how it differs from the thesis rig (or from FILE2). Exit 0, or 2 on a bad file."""
    ap = argparse.ArgumentParser(
        description="Check a rig file (.json, .yaml, .yml) and show the rig it describes, with "
                    "units, and how it differs from the thesis rig (or from FILE2). What the file "
                    "does not give is the thesis rig's.",
        epilog="examples:\n  pneugym rig my_rig.yaml\n"
               "  pneugym rig --preset iso15552-50 --stroke-mm 300 --out my_rig.yaml\n"
               "  python -m pneugym.rigfile report/updated_model.json my_rig.yaml\n"
               "  python -m pneugym.rigfile runs/conventional.json   # a measured run's rig",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("file", metavar="FILE", nargs="?", default=None,
                    help="the rig file to check (or --preset)")
    ap.add_argument("other", metavar="FILE2", nargs="?", default=None,
                    help="compare with this rig file instead of the thesis rig")
    ap.add_argument("--preset", default=None,
                    help="start from a standard cylinder instead of a file: a named preset "
                         "(iso15552-50, ...) or a bore in mm (8-320); see pneugym.presets")
    ap.add_argument("--stroke-mm", type=float, default=200.0, help="the preset's stroke [mm]")
    ap.add_argument("--supply-bar", type=float, default=6.0, help="the preset's supply [bar gauge]")
    ap.add_argument("--load-kg", type=float, default=0.0, help="the preset's payload [kg]")
    ap.add_argument("--out", default=None, help="write the rig to this file (.yaml or .json)")
    a = ap.parse_args(argv)
    if (a.file is None) == (a.preset is None):
        ap.error("give a rig FILE or --preset, one of the two")
    try:
        if a.preset is not None:
            from .presets import cylinder_rig, preset

            kw = dict(supply_bar=a.supply_bar, load_kg=a.load_kg)
            rig = (cylinder_rig(float(a.preset), a.stroke_mm, **kw)
                   if a.preset.replace(".", "", 1).isdigit()
                   else preset(a.preset, a.stroke_mm, **kw))
            source = f"preset {a.preset}, stroke {a.stroke_mm:g} mm"
        else:
            rig, source = load(a.file), a.file
        ref = load(a.other) if a.other else RigParams()
        if a.out:
            rig.save(a.out)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    ref_name = a.other or "the thesis rig"
    print(f"# {source}: a valid rig" + (f", written to {a.out}" if a.out else ""))
    print(format_rig(rig, ref, ref_name))
    n = len(rig_difference(ref, rig))
    ad, ae = rig.drive_piston_area_m2, rig.exhaust_piston_area_m2
    faces = (f"piston area {ad:.4g} m²" if ad == ae
             else f"piston faces {ad:.4g} m² driving, {ae:.4g} m² exhausting")
    along = f", {rig.load_force_n:+.4g} N of constant load along the motion" \
        if rig.load_force_n else ""
    print(f"# derived: {faces}, moving mass {rig.moving_mass_kg:g} kg, valve delay "
          f"{rig.valve_delay_s:g} s at this supply{along}")
    if n:
        print(f"# differs from {ref_name} in {n} of {len(rig_fields(rig))} fields: "
              f"{describe_difference(ref, rig)}")
    else:
        print(f"# the same rig as {ref_name}")
    stuck = rig.cannot_move()
    if stuck:
        print(f"# warning: {stuck}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

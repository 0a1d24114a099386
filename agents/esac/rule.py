"""The parameters of ESAC's cut-off rule: their defaults (:data:`RULE_DEFAULTS`), ranges and
meanings (:data:`RULE_PARAMETERS`) and their check (:func:`check_rule`), shared by the
controller, the model file's metadata and train.py's configuration.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

RULE_DEFAULTS = {"margin": 0.05, "max_time_increase": 0.2, "max_stick": 0.5,
                 "tolerance_m": 0.002, "lookahead": 0, "w_time": 0.3, "w_stick": 0.5,
                 "w_stall": 2.0, "hysteresis": 0.0}
#: every rule parameter: (lowest, highest, what it is); ``lookahead`` is a flag (0 or 1),
#: ``time_demand_s`` (optional, None: use ``max_time_increase``) must be > 0
RULE_PARAMETERS = {
    "margin": (0.0, 1.0, "the accepted predicted risk of an incomplete stroke, a probability "
                         "in [0, 1]"),
    "max_time_increase": (0.0, math.inf, "the time demand, a predicted stroke-time increase "
                                         ">= 0 (0.1: +10 %)"),
    "max_stick": (0.0, 1.0, "the accepted stick-slip risk, a probability in [0, 1]"),
    "tolerance_m": (0.0, math.inf, "how close to the stroke end the predicted final position "
                                   "must be, metres >= 0"),
    "lookahead": (0, 1, "0 (cut as soon as rules 1-3 hold) or 1 (and only once waiting no "
                        "longer pays)"),
    "w_time": (0.0, math.inf, "the objective's weight of the time increase, >= 0"),
    "w_stick": (0.0, math.inf, "the objective's weight of a stick-slip event, >= 0"),
    "w_stall": (0.0, math.inf, "the objective's weight of a stall, >= 0"),
    "hysteresis": (0.0, math.inf, "how much better a later cut must predict, >= 0"),
    "time_demand_s": (0.0, math.inf, "an absolute time demand, seconds > 0 (or none)"),
}


def _rule_number(name: str, v: Any) -> Any:
    """``v`` for rule parameter ``name`` if valid (``lookahead`` as an int), else raises
    ValueError without a location (see :func:`check_rule`)."""
    lo, hi, what = RULE_PARAMETERS[name]
    try:
        ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) \
            and math.isfinite(float(v)) and lo <= float(v) <= hi
    except OverflowError:  # an integer beyond any float
        ok = False
    if name == "lookahead":
        ok = (isinstance(v, (bool, np.bool_)) or ok) and float(v) in (0.0, 1.0)
        if ok:
            return int(v)
    elif name == "time_demand_s":
        ok = ok and float(v) > 0
    if not ok:
        raise ValueError(f"{v!r}: expected {what}")
    return v


def check_rule(params: Mapping[str, Any], where: str, per_row: bool = False) -> dict[str, Any]:
    """ESAC rule parameters (a model's saved rule, an override, a config's grid), checked: known
    names (:data:`RULE_PARAMETERS`, with the nearest for a typo), each a finite number in its
    range (``lookahead`` 0 or 1, ``time_demand_s`` > 0 or None). With ``per_row`` a parameter
    may be an array with one value per observation row. Returns them (``lookahead`` as ints);
    raises ValueError naming ``where`` and the parameter."""
    from pneugym.params import did_you_mean

    if not isinstance(params, Mapping):
        raise ValueError(f"{where} is {params!r}; expected an object of rule parameters "
                         f"({', '.join(RULE_PARAMETERS)})")
    out: dict[str, Any] = {}
    for name, v in params.items():
        if name not in RULE_PARAMETERS:
            raise ValueError(f"{where}: {name!r} is not an ESAC rule parameter"
                             f"{did_you_mean(name, RULE_PARAMETERS)}; they are "
                             f"{', '.join(RULE_PARAMETERS)}")
        if name == "time_demand_s" and v is None:
            out[name] = None
            continue
        try:
            if per_row and isinstance(v, (list, tuple, np.ndarray)) and np.ndim(v) == 1:
                vals = [_rule_number(name, x) for x in np.asarray(v).tolist()]
                out[name] = np.asarray(vals, dtype=np.int64 if name == "lookahead" else float)
            else:
                out[name] = _rule_number(name, v.item() if isinstance(v, np.ndarray)
                                         and v.ndim == 0 else v)
        except ValueError as exc:
            raise ValueError(f"{where}: {name} = {exc}") from None
    return out


"""ESAC model files (``model.pt``): :func:`save`, :func:`load` and :func:`is_esac_file`. A file
holds the weights and the metadata (JSON: layout, architecture, tuned rule, provenance); both are
checked (sizes, bounds, the rule) before a network is built from them.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping

from .model import (CLASS_HEADS, MAX_MEMBERS, REG_HEADS, ESACPredictor, _torch, is_ensemble,
                    make_net)
from .rule import check_rule

FORMAT = "pneugym-esac-1"


def save(path: str | Path, net, meta: Mapping[str, Any]) -> None:
    """Write the weights and ``meta`` (JSON-able: layout, architecture, rule, provenance) in one
    file, atomically; an ensemble's number of networks is recorded as ``members``."""
    torch = _torch()
    meta = {**meta, "members": len(net.members)} if is_ensemble(net) else dict(meta)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    torch.save({"format": FORMAT, "state_dict": net.state_dict(),
                "meta": json.dumps(dict(meta), allow_nan=False)}, tmp)
    os.replace(tmp, path)


def is_esac_file(path: str | Path) -> bool:
    """True if ``path`` looks like a saved ESAC model (a torch file, not an SB3 zip)."""
    import zipfile

    p = Path(path)
    if not p.is_file():
        return False
    if p.suffix == ".pt":
        return True
    if not zipfile.is_zipfile(p):
        return False
    with zipfile.ZipFile(p) as z:
        return "data" not in z.namelist()


#: bounds of an ESAC network a model file may describe (the default is 3 x 128)
MAX_HIDDEN_WIDTH = 4096
MAX_HIDDEN_LAYERS = 16
#: the metadata (``data.pkl`` in the torch file) and the whole file, inflated
MAX_META_BYTES = 16 << 20
MAX_FILE_BYTES = 1 << 30


def _read_blob(path: Path) -> tuple[dict[str, Any], int]:
    """The saved dictionary of an ESAC model (tensors and strings only: ``weights_only``), and
    the bytes its entries hold once inflated (sizes checked before anything is read)."""
    import zipfile

    from ..safe_load import check_zip_sizes

    torch = _torch()
    if not path.is_file():
        raise FileNotFoundError(f"no ESAC model at {path}")
    stored = path.stat().st_size
    if stored > MAX_FILE_BYTES:
        raise ValueError(f"{path} is {stored:,} bytes; pneugym reads ESAC models of up to "
                         f"{MAX_FILE_BYTES:,} bytes")
    if zipfile.is_zipfile(path):
        try:
            with zipfile.ZipFile(path) as z:
                stored = sum(check_zip_sizes(path, z, "ESAC model",
                                             limits={"data.pkl": MAX_META_BYTES},
                                             total=MAX_FILE_BYTES).values())
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise ValueError(f"{path} is not a readable ESAC model: {exc}") from None
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a damaged file
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        raise ValueError(f"{path} is not a readable ESAC model (a torch file written by "
                         f"train.py --algo esac): {type(exc).__name__}: {first}. Is it "
                         f"truncated, or another kind of file?") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise ValueError(f"{path} is not an ESAC model ({FORMAT})")
    return blob, stored


def torch_isfinite_all(t) -> bool:
    """True if every entry of tensor ``t`` is finite."""
    return bool(_torch().isfinite(t).all())


def _meta_error(path: Path, key: str, value: Any, expected: str) -> ValueError:
    r = repr(value)
    return ValueError(f"{path}: its metadata's {key} is {r if len(r) <= 80 else r[:80] + '...'};"
                      f" expected {expected} (not an ESAC model train.py wrote, or altered)")


def _read_meta(path: Path, blob: Mapping[str, Any]) -> dict[str, Any]:
    """The metadata of an ESAC model, checked before anything is built from it: ``n_in``,
    ``hidden`` (bounded: :data:`MAX_HIDDEN_WIDTH`, :data:`MAX_HIDDEN_LAYERS`) and ``members``
    (an ensemble's networks, 1 to :data:`~agents.esac.model.MAX_MEMBERS`), the observation
    ``layout`` (:func:`agents.learned.check_layout_record`) and ``n_in`` consistent with it,
    ``delay_input``, ``lookahead_s`` and the tuned ``rule`` (:func:`check_rule`). ValueError
    (:class:`~agents.learned.LayoutMismatchError` for the layout) names the file and key."""
    from ..learned import check_layout_record, is_finite_number

    try:
        meta = json.loads(blob["meta"])
    except (KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: its metadata is missing or not JSON ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: its metadata is JSON nested too deeply (not an ESAC model "
                         f"train.py wrote)") from None
    except ValueError as exc:  # e.g. an integer beyond Python's digit limit
        raise ValueError(f"{path}: its metadata is not the JSON train.py writes: {exc}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: its metadata is a JSON {type(meta).__name__}; expected an "
                         f"object (n_in, hidden, layout, rule, ...)")

    def count(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)

    n_in = meta.get("n_in")
    if not count(n_in) or n_in <= 0:
        raise _meta_error(path, "n_in", n_in, "the network's input size, an integer > 0")
    hidden = meta.get("hidden")
    if not (isinstance(hidden, list) and len(hidden) <= MAX_HIDDEN_LAYERS and all(
            count(h) and 1 <= h <= MAX_HIDDEN_WIDTH for h in hidden)):
        raise _meta_error(path, "hidden", hidden, f"a list of at most {MAX_HIDDEN_LAYERS} layer "
                          f"widths from 1 to {MAX_HIDDEN_WIDTH}")
    members = meta.get("members", 1)
    if not count(members) or not 1 <= members <= MAX_MEMBERS:
        raise _meta_error(path, "members", members, f"the ensemble's number of networks, an "
                          f"integer from 1 to {MAX_MEMBERS}")
    if "layout" not in meta:
        raise _meta_error(path, "layout", None, "the observation layout it was trained on")
    layout = check_layout_record(meta["layout"], f"{path}: its metadata's layout")
    delay_input = meta.get("delay_input", False)
    if not isinstance(delay_input, bool):
        raise _meta_error(path, "delay_input", delay_input, "true or false")
    if n_in != int(layout["size"]) + int(delay_input):
        raise _meta_error(path, "n_in", n_in, f"{int(layout['size']) + int(delay_input)}: the "
                          f"layout's size {layout['size']}"
                          f"{' + 1 (the delay input)' if delay_input else ''}")
    look = meta.get("lookahead_s", [])
    if not (isinstance(look, list) and len(look) <= 1000 and all(
            is_finite_number(d) and 0 <= d <= 3600 for d in look)):
        raise _meta_error(path, "lookahead_s", look, "a list of delays in seconds (finite, 0 to "
                          "3600)")
    if "rule" in meta:
        meta["rule"] = check_rule(meta["rule"], f"{path}: its metadata's rule")
    return meta


def load(path: str | Path) -> tuple[ESACPredictor, dict[str, Any]]:
    """The predictor and the metadata of a saved ESAC model. Only tensors and strings are read
    (``torch.load(weights_only=True)``); a damaged file, another kind of file or metadata out of
    bounds (:func:`_read_meta`) is a ValueError naming it, raised before the network is built.
    """
    path = Path(path)
    blob, stored = _read_blob(path)
    meta = _read_meta(path, blob)
    widths = [int(meta["n_in"]), *meta["hidden"], len(CLASS_HEADS) + len(REG_HEADS)]
    members = int(meta.get("members", 1))
    need = 4 * members * sum(a * b + b for a, b in zip(widths, widths[1:]))
    what = f"n_in {meta['n_in']}, hidden {meta['hidden']}" + (
        f", {members} members" if members > 1 else "")
    if need > stored:
        raise ValueError(f"{path}: its metadata describes a network ({what}) of {need:,} bytes "
                         f"of weights, but the file holds {stored:,}: altered or damaged; "
                         f"pneugym does not build it")
    net = make_net(int(meta["n_in"]), meta["hidden"], members)
    try:
        net.load_state_dict(blob.get("state_dict"))
    except (RuntimeError, TypeError, AttributeError) as exc:
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        raise ValueError(f"{path}: its weights do not fit the network its metadata describes "
                         f"({what}): {first}") from None
    state = net.state_dict()
    bad = [k for k, t in state.items() if not torch_isfinite_all(t)]
    bad += [k for k in ("in_std", "out_std") if k not in bad and not bool((state[k] > 0).all())]
    if bad:
        raise ValueError(f"{path}: its weights {bad} hold NaN, infinite or (for a scale) "
                         f"non-positive values: a damaged file; retrain it")
    net.eval()
    return ESACPredictor(net, meta["layout"], meta.get("delay_input", False),
                         meta.get("lookahead_s", ())), meta

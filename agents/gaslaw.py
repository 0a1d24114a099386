"""The thesis's Gas-Law predictor (eqs. 1.3, 5.1, 6.5): cut the supply when

    P > K * P_st * (V_o / V)^n,     P_st = Fs / A_p,

``P`` the driving-chamber pressure, ``V`` the driving-chamber volume now and ``V_o`` at full stroke,
``n`` the identified expansion index (2.7 in the thesis). The rule only knows the nominal rig
(breakaway friction, bore, dead volume); its factor ``K`` must be retuned whenever load, supply or
friction change. Here ``K`` is calibrated per supply pressure on the nominal rig by a sweep
(:func:`calibrate`; the thesis tuned it by trial) and interpolated on the supply set-point.
On another rig the rule takes that rig's bore, dead volume and breakaway friction (its rig file's
values), and its K is calibrated on that rig (``--rig``).

``python -m agents.gaslaw`` re-runs the calibration and writes ``agents/gaslaw_k.json`` and a plot;
``python -m agents.gaslaw --rig my_rig.yaml --out runs/my_rig/gaslaw_k.json`` calibrates K for
another rig (``evaluate.py --policies gaslaw_mine=runs/my_rig/gaslaw_k.json`` runs it).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from pneugym.params import RigParams

from .base import Policy, run_first_episodes

CALIBRATION_FILE = Path(__file__).with_name("gaslaw_k.json")
#: K used by the thesis (5.8, 6.5): on the rig, and in its own simulation.
THESIS_K = {"experiment": {1.5: 0.1, 2.5: 0.2}, "simulation": {1.5: 2.2, 2.5: 1.2}}


MAX_CALIBRATION_BYTES = 1 << 20


def read_calibration(path: Path | str = CALIBRATION_FILE) -> dict[str, Any]:
    """A calibration file's content, checked: a JSON object whose ``table`` lists
    ``{"supply_bar_gauge", "k"}`` rows of finite numbers (K >= 0), and whose ``rig``, if any, is a
    valid rig. ValueError names the file."""
    p = Path(path)
    if p.stat().st_size > MAX_CALIBRATION_BYTES:
        raise ValueError(f"{p}: {p.stat().st_size:,} bytes is too large for a Gas-Law calibration "
                         f"(at most {MAX_CALIBRATION_BYTES:,})")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p}: not a Gas-Law calibration (JSON): {exc}") from None
    table = data.get("table") if isinstance(data, dict) else None
    ok = isinstance(table, list) and table and all(
        isinstance(r, dict) and all(isinstance(r.get(k), (int, float)) and not isinstance(
            r.get(k), bool) and math.isfinite(r[k]) for k in ("supply_bar_gauge", "k"))
        and r["k"] >= 0 for r in table)
    if not ok:
        raise ValueError(f"{p}: not a Gas-Law calibration: expected a 'table' of "
                         f"{{supply_bar_gauge, k}} rows (finite numbers, k >= 0), as "
                         f"python -m agents.gaslaw writes")
    if data.get("rig") is not None:
        from pneugym.rigfile import as_rig

        as_rig(data["rig"], f"{p}: its rig")
    rule = data.get("policy") or {}
    if not (isinstance(rule, dict) and set(rule) <= set(RULE_OPTIONS)):
        raise ValueError(f"{p}: its 'policy' = {rule!r:.120} must hold only the rule's options "
                         f"{list(RULE_OPTIONS)} (the formula K was calibrated for)")
    return data


#: the rule's options a calibration records (``policy``): K holds for that formula only
RULE_OPTIONS = ("n", "pressure", "volume")


def rule_options(calibration: Mapping[str, Any]) -> dict[str, Any]:
    """The rule's options a calibration was made for (its ``policy``; the defaults if none)."""
    return dict(calibration.get("policy") or {})


def k_table(calibration: Mapping[str, Any]) -> dict[float, float]:
    """``{supply_bar_gauge: K}`` of a calibration (:func:`calibrate`'s result or a file's)."""
    return {float(r["supply_bar_gauge"]): float(r["k"]) for r in calibration["table"]}


def load_calibration(path: Path | str = CALIBRATION_FILE) -> dict[float, float]:
    """``{supply_bar_gauge: K}`` from a calibration file."""
    return k_table(read_calibration(path))


class GasLawPolicy(Policy):
    """Eq. 5.1 on the measured position and driving-port pressure.

    ``k``: a number, a table ``{supply_bar_gauge: K}`` (interpolated linearly on the supply
    set-point, held constant outside), or an array with one K per observation row; default: the
    calibrated table. ``pressure``: ``"gauge"`` or ``"absolute"`` for ``P`` and ``P_st``
    (the thesis does not say). ``volume``: ``"chamber"`` (dead volume included) or ``"position"``
    (``x_end / x``, as in the thesis's appendix code). ``k_scale`` (a number, or one per
    observation row) multiplies K: what an adaptive controller tunes
    (:class:`agents.adaptive.AdaptiveGasLaw`)."""

    name = "gaslaw"

    def __init__(self, layout: Mapping[str, Any], k: float | Mapping[float, float] | np.ndarray |
                 None = None, n: float = 2.7, pressure: str = "gauge", volume: str = "chamber",
                 rig: RigParams | None = None):
        super().__init__(layout)
        if pressure not in ("gauge", "absolute"):
            raise ValueError(f"pressure = {pressure!r}: choose 'gauge' or 'absolute'")
        if volume not in ("chamber", "position"):
            raise ValueError(f"volume = {volume!r}: choose 'chamber' or 'position'")
        if not (math.isfinite(n) and n > 0):
            raise ValueError(f"n = {n!r} must be > 0")
        self.rig = rig or RigParams()
        self.n, self.pressure, self.volume = float(n), pressure, volume
        self.k_scale: float | np.ndarray = 1.0
        if k is None:
            k = load_calibration()
        if isinstance(k, Mapping):
            pts = sorted((float(p), float(v)) for p, v in k.items())
            self._k_bar = np.array([p for p, _ in pts])
            self._k_val = np.array([v for _, v in pts])
            self.k: Any = dict(pts)
        else:
            self._k_bar = None
            self.k = np.asarray(k, dtype=float)
        if np.any(~np.isfinite(self._k_val if self._k_bar is not None else self.k)) or \
                np.any((self._k_val if self._k_bar is not None else self.k) < 0):
            raise ValueError(f"k = {k!r} must be finite and >= 0")
        self._geometry([self.rig])

    def _geometry(self, rigs: Sequence[RigParams]) -> None:
        """The rule's rig values (bore, dead volume, stroke, breakaway friction): one rig for
        every row, or one per row."""
        def col(f):
            v = np.array([f(r) for r in rigs], dtype=float)
            return float(v[0]) if v.size == 1 else v

        self._area = col(lambda r: r.drive_piston_area_m2)
        self._v0 = col(lambda r: r.drive_dead_volume_m3 + r.effects.dead_volume_m3)
        self._stroke = col(lambda r: r.cylinder.stroke_m)
        self._pa = col(lambda r: r.gas.ambient_pressure_pa)
        p_st = col(lambda r: r.friction.static_n) / self._area
        self._p_st = p_st if self.pressure == "gauge" else p_st + self._pa

    def begin_episodes(self, conditions: Sequence[Any]) -> None:
        """Episodes on rigs of their own (``rig_changes``, e.g. the transfer suite): the rule
        takes each one's values, as its rig file would state them."""
        if any(getattr(c, "rig_changes", ()) for c in conditions):
            from pneugym.envs.family import apply_changes

            self._geometry([apply_changes(self.rig, c.rig_changes) for c in conditions])
        else:
            self._geometry([self.rig])

    @classmethod
    def for_env(cls, env, **kwargs: Any) -> "GasLawPolicy":
        """The rule for ``env``'s rig (its bore, dead volume and breakaway friction)."""
        u = env.unwrapped
        return cls(u.observation_layout(), **{"rig": u.rig, **kwargs})

    def k_for(self, supply_gauge_pa: np.ndarray) -> np.ndarray:
        """K for each supply set-point [Pa gauge] (times ``k_scale``)."""
        if self._k_bar is None:
            return np.broadcast_to(self.k, supply_gauge_pa.shape) * self.k_scale
        return np.interp(supply_gauge_pa / 1e5, self._k_bar, self._k_val) * self.k_scale

    def act(self, obs: np.ndarray) -> np.ndarray:
        x = np.clip(self.read(obs, "position"), 0.0, self._stroke)
        p = self.read(obs, "p_drive") + (self._pa if self.pressure == "absolute" else 0.0)
        if self.volume == "chamber":
            ratio = (self._v0 + self._area * self._stroke) / (self._v0 + self._area * x)
        else:
            ratio = self._stroke / np.maximum(x, 1e-6)
        k = self.k_for(self.read(obs, "supply_setpoint"))
        return (p > k * self._p_st * ratio ** self.n).astype(np.int64)


class GasLawPerRigPolicy(GasLawPolicy):
    """The Gas-Law rule with K calibrated for each episode's rig (:func:`calibrate` on that rig at
    its load, per supply pressure, cached per rig): what an engineer gets by re-tuning K on their
    own rig, the fair baseline of the transfer suite. On a single rig it is :func:`calibrate` run
    once for the environment's rig."""

    name = "gaslaw-rig"
    SUPPLIES_BAR = (1.5, 2.0, 2.5, 3.0, 4.0, 5.0)  # as the shipped table (held beyond)
    needs_conditions = True

    def __init__(self, layout: Mapping[str, Any], env_config: Mapping[str, Any] | None = None,
                 rig: RigParams | None = None, seed: int = 0, **kwargs: Any):
        super().__init__(layout, k=1.0, rig=rig, **kwargs)
        self.env_config = {k: v for k, v in dict(env_config or {}).items()
                           if k not in ("preset", "conditions", "render_mode", "rig")}
        self.seed = seed
        self._tables: dict[tuple, dict[float, float]] = {}

    @classmethod
    def for_env(cls, env, **kwargs: Any) -> "GasLawPerRigPolicy":
        u = env.unwrapped
        return cls(u.observation_layout(), env_config=u.config, **{"rig": u.rig, **kwargs})

    def table(self, changes: tuple = ()) -> dict[float, float]:
        """``{supply_bar_gauge: K}`` calibrated on the rig with ``changes`` (cached), for this
        rule's formula (its ``n``, ``pressure`` and ``volume``)."""
        if changes not in self._tables:
            from pneugym.envs.family import apply_changes

            rig = apply_changes(self.rig, changes)
            self._tables[changes] = k_table(calibrate(
                self.SUPPLIES_BAR, env_config={**self.env_config, "rig": rig}, seed=self.seed,
                progress=False, n=self.n, pressure=self.pressure, volume=self.volume))
        return self._tables[changes]

    def begin_episodes(self, conditions: Sequence[Any]) -> None:
        super().begin_episodes(conditions)
        ks = []
        for c in conditions:
            t = self.table(getattr(c, "rig_changes", ()))
            ks.append(np.interp(c.supply_bar_gauge, list(t), list(t.values())))
        self._k_bar, self.k = None, np.array(ks)
        self._told_rows = len(conditions)


def sweep(supply_bar: float, ks: Sequence[float], env_config: Mapping[str, Any] | None = None,
          seed: int = 0, **policy_kwargs: Any) -> np.ndarray:
    """The episode return of the Gas-Law rule for each K on the rig of ``env_config`` (default
    the thesis rig) with its load (10 kg for the thesis rig) at ``supply_bar`` gauge: one batched
    run, one sub-environment per K."""
    from pneugym.envs import Conditions
    from pneugym.envs.cutoff import CutOffVectorEnv

    ks = np.asarray(ks, dtype=float)
    env = CutOffVectorEnv(num_envs=ks.size, autoreset=False, **dict(env_config or {}))
    pol = GasLawPolicy(env.observation_layout(), k=ks, rig=env.rig, **policy_kwargs)
    cond = Conditions(supply_pressure_gauge_pa=supply_bar * 1e5, load_mass_kg=env.rig.load_mass_kg)
    return run_first_episodes(env, pol, [cond] * ks.size, seed)["objective"]


def calibrate(supplies_bar: Sequence[float] = (1.5, 2.0, 2.5, 3.0, 4.0, 5.0),
              ks: Sequence[float] | None = None, env_config: Mapping[str, Any] | None = None,
              seed: int = 0, progress: bool = True, **policy_kwargs: Any) -> dict[str, Any]:
    """Best K per supply pressure: the highest episode return on the rig of ``env_config``
    (default the thesis rig, 10 kg) at its load; the result records the rig.
    (Choosing the best return averaged with its grid neighbours instead, for a broader
    optimum, did worse on the robustness suite: oracle fraction 0.839 against 0.896.)"""
    from tqdm import tqdm

    ks = np.geomspace(0.02, 20.0, 64) if ks is None else np.asarray(ks, dtype=float)
    table, curves = [], {}
    for p in tqdm(supplies_bar, desc="Gas-Law K sweep", unit="pressure", disable=not progress):
        j = sweep(p, ks, env_config, seed, **policy_kwargs)
        i = int(np.argmax(j))
        table.append({"supply_bar_gauge": float(p), "k": float(ks[i]), "return": float(j[i])})
        curves[str(p)] = [float(v) for v in j]
    from pneugym.rigfile import as_rig

    cfg = dict(env_config or {})
    rig = cfg.pop("rig", None)
    out = {"table": table, "k_grid": [float(v) for v in ks], "returns": curves,
           "thesis_k": {k: {str(p): v for p, v in d.items()} for k, d in THESIS_K.items()},
           "env_config": cfg, "policy": dict(policy_kwargs), "seed": seed}
    if rig is not None:
        out["rig"] = as_rig(rig).to_dict()
    return out


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description="Calibrate the thesis's Gas-Law cut-off rule: K per supply pressure by a "
                    "sweep on the rig (the return of each K), written as a K table.",
        epilog="examples:\n  pneugym gaslaw                       # writes agents/gaslaw_k.json\n"
               "  pneugym gaslaw --out /tmp/k.json --plot /tmp/k.png --seed 1\n"
               "  pneugym gaslaw --rig my_rig.yaml --out runs/my_rig/gaslaw_k.json "
               "--plot runs/my_rig/gaslaw_k.png",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(CALIBRATION_FILE), metavar="FILE",
                    help="calibration JSON (default: the K table the Gas-Law policy reads)")
    ap.add_argument("--plot", default=None,
                    help="PNG of return vs K (default results/gaslaw_k.png for the thesis rig, "
                         "beside --out with --rig)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the sweep's episodes (0)")
    ap.add_argument("--rig", default=None, metavar="FILE",
                    help="calibrate K for this rig (a rig file; default the thesis rig); give "
                         "--out too, so that the shipped table stays the thesis rig's")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    from pneugym.outputs import atomic_write_json, check_output_file
    from pneugym.provenance import provenance

    try:  # before the calibration: an unusable path must not cost the run
        env_config = {}
        if args.rig is not None:
            from pneugym.rigfile import as_rig

            env_config["rig"] = as_rig(args.rig, "--rig")
            if Path(args.out).resolve() == CALIBRATION_FILE.resolve():
                raise ValueError(f"--rig calibrates K for another rig: give --out FILE (the "
                                 f"default {CALIBRATION_FILE} is the shipped thesis-rig table)")
        check_output_file(args.out, "--out")
        if args.plot is None:  # (another rig's plot never replaces the thesis rig's)
            args.plot = ("results/gaslaw_k.png" if args.rig is None
                         else str(Path(args.out).with_suffix(".png")))
        if args.plot:
            check_output_file(args.plot, "--plot")
    except ValueError as exc:
        ap.error(str(exc))
    result = calibrate(env_config=env_config, seed=args.seed, progress=not args.no_progress)
    result["provenance"] = provenance()
    atomic_write_json(args.out, result)
    print(f"{'supply [bar g]':>14} {'K calibrated':>12} {'return':>8}   thesis K (rig / sim)")
    for r in result["table"]:
        p = r["supply_bar_gauge"]
        th = "  /  ".join(str(THESIS_K[s].get(p, "-")) for s in ("experiment", "simulation"))
        print(f"{p:14.1f} {r['k']:12.3g} {r['return']:8.3f}   {th}")
    if args.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(6, 4))
        for p, j in result["returns"].items():
            ax.semilogx(result["k_grid"], j, label=f"{p} bar")
        ax.set_ylim(-2.0, 0.0)
        ax.set_xlabel("K"), ax.set_ylabel("episode return (objective)")
        where = "the thesis rig" if args.rig is None else Path(args.rig).name
        ax.set_title(f"Gas-Law rule on {where}"), ax.legend(), ax.grid(alpha=0.3)
        fig.savefig(args.plot, dpi=120, bbox_inches="tight")
        print(f"wrote {args.out} and {args.plot}")


if __name__ == "__main__":
    main()

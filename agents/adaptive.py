"""Controllers for a rig's operating life (:mod:`pneugym.operation`): a frozen policy, and two that
adapt from the strokes they have made (thesis 6.8, ch. 7).

Every controller here sees only what a real one sees: its sensors during a stroke, the supply
set-point and the payload, and each finished stroke's measured outcome (completed, stalled, the
stick-slip events the position trace shows, the stroke time an end switch gives, the wasted
energy from the driving chamber's final pressure; :data:`MEASURED`).
The conventional stroke time and energy that the objective is counted against are measured on
*reference strokes*: every ``reference_every``-th stroke runs uncut (its air is spent, and counted).

- :class:`Frozen`: any policy (a baseline's name or ``NAME=PATH`` of a trained one), unchanged.
- :class:`AdaptiveGasLaw`: the Gas-Law rule with its K table scaled by a factor adjusted after
  every block of strokes by perturb-and-observe: alternate strokes run K slightly higher and
  lower, and the factor moves toward the side whose measured objective (stick-slip included)
  was better; a stroke short of its end moves it up (a later cut) at once.
- :class:`AdaptiveESAC`: ESAC fine-tuned from its own recorded strokes (each stroke labels the
  observations at its cut and before it with its measured outcome, as rollouts do), a share of
  strokes exploring another time demand; a candidate is deployed only if it predicts the most
  recent strokes, which it was not trained on, better than the running model.

The operating loop calls :meth:`Frozen.plan` before each block, :meth:`Frozen.update` with the
block's measured outcome, :meth:`Frozen.adapt` at the start of each block (with the record) and
:meth:`Frozen.state` / :meth:`Frozen.restore` to checkpoint.
"""
from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .base import Policy

#: the outcome columns a controller may read (measured); ``objective`` and ``saving_ratio`` are
#: the simulator's and stay with the report
MEASURED = ("stroke", "reference", "explore", "supply_setpoint_pa", "cutoff_time_s", "completed",
            "stalled", "stick_slip_events", "stroke_time_s", "final_position_m",
            "energy_wasted_j", "free_air_nl")


def measured_objective(rec: Mapping[str, np.ndarray], conv_time_s: np.ndarray,
                       conv_energy_j: np.ndarray, w_time: float = 0.3, w_stick: float = 0.5,
                       w_stall: float = 2.0) -> np.ndarray:
    """The environment's objective as a controller can measure it: wasted energy over the
    reference stroke's, minus the weighted time increase over the reference stroke's, stick-slip
    (once per stroke with any, where the environment counts each event) and stall (an incomplete
    stroke scores as a stall)."""
    t = np.asarray(rec["stroke_time_s"], dtype=float)
    done = np.asarray(rec["completed"], dtype=bool)
    inc = np.where(done, np.maximum(np.nan_to_num(t / conv_time_s - 1.0), 0.0), 0.0)
    return (-np.asarray(rec["energy_wasted_j"], float) / conv_energy_j - w_time * inc
            - w_stick * (np.asarray(rec["stick_slip_events"]) > 0)
            - w_stall * (~done))


class Frozen:
    """A policy that never changes: ``spec`` a baseline's name (``gaslaw``, ``endstroke``, ...)
    or ``NAME=PATH`` of a trained model, built for ``env`` (the operating vector environment)."""

    needs_inputs = False  #: whether the loop records the observations at each cut
    reference_every = 0  #: 0: no reference strokes
    privileged = False  #: told the true conditions (the oracle: a check, not a controller)

    def __init__(self, spec: str, env: Any, seed: int = 0):
        from .evaluation.specs import make_named_policy

        self.spec = spec
        self.name, self.policy = make_named_policy(spec, env)
        self.privileged = bool(getattr(self.policy, "privileged", False))
        self.seed = int(seed)
        self.version = f"{self.name}"

    def config(self) -> dict[str, Any]:
        """What identifies the controller (recorded with the run)."""
        return {"kind": type(self).__name__, "spec": self.spec}

    def plan(self, strokes: np.ndarray) -> tuple[Policy, dict[str, np.ndarray]]:
        """The policy for a block of strokes and each stroke's flags: ``reference`` (run uncut)
        and ``explore``."""
        n = strokes.size
        return self.policy, {"reference": self.is_reference(strokes),
                             "explore": np.zeros(n, dtype=bool)}

    def is_reference(self, strokes: np.ndarray) -> np.ndarray:
        if not self.reference_every:
            return np.zeros(strokes.size, dtype=bool)
        return strokes % self.reference_every == 0

    def update(self, rec: Mapping[str, np.ndarray]) -> None:
        """Learn from a block's measured outcome (:data:`MEASURED`)."""

    def adapt(self, record: Any, run_id: str, stroke: int) -> list[dict[str, Any]]:
        """Before stroke ``stroke``: build and perhaps deploy a new model from the record.
        Returns the models built (rows of the record's ``models`` table)."""
        return []

    def state(self) -> bytes:
        """The controller's state, for the checkpoint."""
        return json.dumps({"version": self.version}).encode()

    def restore(self, state: bytes, record: Any, run_id: str) -> None:
        """Back to a checkpointed state."""


#: the adaptive Gas-Law factor stays within exp(+-LOG_G_MAX) of the calibrated K (0.25-4x)
LOG_G_MAX = math.log(4.0)


class AdaptiveGasLaw(Frozen):
    """The Gas-Law rule (as shipped, K per supply pressure) with its K scaled by a factor ``g``
    learned in operation: within a block, even strokes run ``g * exp(+delta)``, odd ones
    ``g * exp(-delta)``; after it, ``log g`` moves by ``step`` toward the better side (mean
    measured objective, stick-slip included), and by ``backoff`` up after any stroke that did
    not reach its end; ``g`` stays within 0.25-4."""

    reference_every = 100

    def __init__(self, env: Any, seed: int = 0, delta: float = 0.08, step: float = 0.04,
                 backoff: float = 0.15, spec: str = "gaslaw"):
        super().__init__(spec, env, seed)
        self.delta, self.step, self.backoff = float(delta), float(step), float(backoff)
        self.log_g = 0.0
        self.conv = (math.nan, math.nan)  # the latest reference stroke's time [s], energy [J]
        self.version = self._version()

    def _version(self) -> str:
        return f"gaslaw-adaptive g={math.exp(self.log_g):.4f}"

    def config(self) -> dict[str, Any]:
        return {**super().config(), "delta": self.delta, "step": self.step,
                "backoff": self.backoff, "reference_every": self.reference_every}

    def plan(self, strokes: np.ndarray) -> tuple[Any, dict[str, np.ndarray]]:
        ref = self.is_reference(strokes)
        sign = np.where(strokes % 2 == 0, 1.0, -1.0)
        factor = np.exp(self.log_g + self.delta * sign)
        factor[ref] = 1e9  # never cut
        self.policy.k_scale = factor
        return self.policy, {"reference": ref, "explore": np.zeros(strokes.size, bool)}

    def update(self, rec: Mapping[str, np.ndarray]) -> None:
        ref = np.asarray(rec["reference"], dtype=bool)
        if ref.any():
            i = np.flatnonzero(ref)[-1]
            self.conv = (float(rec["stroke_time_s"][i]), float(rec["energy_wasted_j"][i]))
        cut = ~ref
        if not cut.any() or not math.isfinite(self.conv[0]):
            return
        if (~np.asarray(rec["completed"], bool) & cut).any():
            self.log_g += self.backoff  # a stroke short of its end: cut later at once
        else:  # stick-slip is in the measured objective: the side that sticks less wins
            j = measured_objective(rec, self.conv[0], self.conv[1])
            up = cut & (np.asarray(rec["stroke"]) % 2 == 0)
            down = cut & ~up
            if up.any() and down.any():
                self.log_g += self.step * np.sign(j[up].mean() - j[down].mean())
        self.log_g = float(np.clip(self.log_g, -LOG_G_MAX, LOG_G_MAX))
        self.version = self._version()

    def state(self) -> bytes:
        return json.dumps({"log_g": self.log_g, "conv": list(self.conv)}).encode()

    def restore(self, state: bytes, record: Any, run_id: str) -> None:
        s = json.loads(state)
        self.log_g, self.conv = float(s["log_g"]), tuple(float(v) for v in s["conv"])
        self.version = self._version()


class AdaptiveESAC(Frozen):
    """ESAC fine-tuned in operation from its recorded strokes.

    Every ``adapt_every`` strokes it takes the last ``window`` recorded cut strokes, labels each
    one's observations at the cut (and before it, for a model with delay input) with its
    measured outcome and the latest reference stroke's conventional figures, fine-tunes the
    running network on the older ones (``epochs`` at learning rate ``lr``) and scores both on
    the newest ``holdout`` share: the candidate is deployed only if its loss there is lower by
    ``min_gain`` (relative). A share ``explore`` of the strokes runs with a time demand drawn
    from ``explore_range`` instead of the tuned one, so that the record shows the outcome of
    other cut times too."""

    needs_inputs = True
    reference_every = 100

    def __init__(self, spec: str, env: Any, seed: int = 0, adapt_every: int = 250,
                 window: int = 1000, holdout: float = 0.25, epochs: int = 30, lr: float = 5e-4,
                 min_gain: float = 0.02, explore: float = 0.2,
                 explore_range: tuple[float, float] = (0.0, 0.3)):
        super().__init__(spec, env, seed)
        from .esac.policy import ESACPolicy

        if not isinstance(self.policy, ESACPolicy):
            raise ValueError(f"{spec!r} is not an ESAC model: adaptive ESAC fine-tunes ESAC "
                             f"models (give esac=runs/esac)")
        if not (1 <= adapt_every and 0.0 < holdout < 1.0 and 0.0 <= explore < 1.0):
            raise ValueError("adapt_every >= 1, holdout in (0, 1), explore in [0, 1)")
        self.adapt_every, self.window, self.holdout = int(adapt_every), int(window), holdout
        self.epochs, self.lr, self.min_gain = int(epochs), float(lr), float(min_gain)
        self.explore, self.explore_range = float(explore), tuple(explore_range)
        self.layout = env.unwrapped.observation_layout()
        from .esac.data import LAGS

        # the recorded lags' delays [s] (the loop records the observations LAGS periods back)
        self.lag_s = np.asarray(LAGS, dtype=float) * float(self.layout["control_period_s"])
        self.rule = self.policy.rule()
        self.generation = 0
        self.last_adapt = 0
        self.version = f"{self.name}-v0"

    def config(self) -> dict[str, Any]:
        return {**super().config(), "adapt_every": self.adapt_every, "window": self.window,
                "holdout": self.holdout, "epochs": self.epochs, "lr": self.lr,
                "min_gain": self.min_gain, "explore": self.explore,
                "explore_range": list(self.explore_range), "reference_every": self.reference_every}

    def plan(self, strokes: np.ndarray) -> tuple[Any, dict[str, np.ndarray]]:
        from .esac.policy import ESACPolicy

        ref = self.is_reference(strokes)
        u = np.array([np.random.default_rng([self.seed, int(k), 7]).random(2) for k in strokes])
        explore = (u[:, 0] < self.explore) & ~ref
        lo, hi = self.explore_range
        demand = np.where(explore, lo + (hi - lo) * u[:, 1], float(self.rule["max_time_increase"]))
        rule = {k: v for k, v in self.rule.items() if k != "max_time_increase"}
        pol = ESACPolicy(self.layout, self.policy.predictor, max_time_increase=demand,
                         source=self.policy.source, **rule)
        return pol, {"reference": ref, "explore": explore}

    # -- learning from the record --------------------------------------------------------------
    def _samples(self, rec: Mapping[str, np.ndarray], first: int = 0
                 ) -> tuple[np.ndarray, ...] | None:
        """Inputs, targets, mask and stroke index of the record's cut strokes from ``first`` on,
        labelled with the latest earlier reference stroke's conventional time and energy."""
        from .esac.data import samples

        ref = rec["reference"].astype(bool)
        idx = np.arange(ref.size)
        last_ref = np.maximum.accumulate(np.where(ref, idx, -1))
        use = ~ref & (last_ref >= 0) & np.array([b is not None for b in rec["decision_inputs"]])
        use &= rec["stroke"] >= first
        use &= ~np.isnan(rec["cutoff_time_s"])
        if use.sum() < 20:
            return None
        j = last_ref[use]
        pred = self.policy.predictor
        size = int(pred.layout["size"])
        obs_lag = np.stack([np.frombuffer(b, dtype=np.float32).reshape(-1, size)
                            for b in rec["decision_inputs"][use]])
        data = {
            "obs": obs_lag[:, 0], "obs_lag": obs_lag, "lag_s": self.lag_s,
            "completed": rec["completed"][use].astype(bool),
            "stick_slip_events": rec["stick_slip_events"][use].astype(np.int64),
            "final_position_m": rec["final_position_m"][use].astype(float),
            "stroke_time_s": np.array([np.nan if v is None else v
                                       for v in rec["stroke_time_s"][use]], dtype=float),
            "conventional_time_s": rec["stroke_time_s"][j].astype(float),
            "energy_wasted_j": rec["energy_wasted_j"][use].astype(float),
            "energy_conventional_j": rec["energy_wasted_j"][j].astype(float),
        }
        x, y, mask, rows = samples(data, pred.stroke_m, pred.delay_input)
        return x, y, mask, rec["stroke"][use][rows]


    def adapt(self, record: Any, run_id: str, stroke: int) -> list[dict[str, Any]]:
        if stroke - self.last_adapt < self.adapt_every:
            return []
        from .esac.model import fit, loss

        self.last_adapt = stroke
        # a further reference_every strokes back: the reference stroke that labels the first ones
        rec = record.strokes(run_id, max(0, stroke - self.window - self.reference_every),
                             stroke - 1, columns=MEASURED + ("decision_inputs",))
        got = self._samples(rec, first=stroke - self.window) if rec["stroke"].size else None
        if got is None:
            return []
        x, y, mask, st = got
        cut = np.quantile(np.unique(st), 1.0 - self.holdout)
        tr, te = st < cut, st >= cut
        if tr.sum() < 20 or te.sum() < 5:
            return []
        running = self.policy.predictor.net
        cand, hist = fit(x[tr], y[tr], mask[tr], epochs=self.epochs, lr=self.lr,
                         batch_size=128, seed=self.seed + stroke, patience=self.epochs,
                         groups=st[tr], progress=False, init=running)
        s_new, s_old = loss(cand, x[te], y[te], mask[te]), loss(running, x[te], y[te], mask[te])
        deploy = s_new < (1.0 - self.min_gain) * s_old
        self.generation += 1
        version = f"{self.name}-v{self.generation}"
        if deploy:
            self.policy.predictor.net = cand
            self.version = version
        return [{"version": version, "stroke": stroke, "kind": "esac", "deployed": bool(deploy),
                 "score_new": s_new, "score_running": s_old,
                 "detail": {"train_samples": int(tr.sum()), "holdout_samples": int(te.sum()),
                            "epochs_run": hist["epochs_run"]},
                 "blob": _net_bytes(cand, self.policy)}]

    def state(self) -> bytes:
        return json.dumps({"version": self.version, "generation": self.generation,
                           "last_adapt": self.last_adapt}).encode()

    def restore(self, state: bytes, record: Any, run_id: str) -> None:
        s = json.loads(state)
        self.generation, self.last_adapt = int(s["generation"]), int(s["last_adapt"])
        self.version = s["version"]
        if self.version != f"{self.name}-v0":
            row = record.con.execute("SELECT blob FROM models WHERE run_id = ? AND version = ?",
                                     [run_id, self.version]).fetchone()
            if row is None:
                raise ValueError(f"run {run_id!r}: its checkpoint names model {self.version}, "
                                 f"which the record does not hold")
            self.policy.predictor.net = _net_from_bytes(row[0])


def _net_bytes(net: Any, policy: Any) -> bytes:
    """A network as the bytes of an ESAC model file (:mod:`agents.esac.modelfile`)."""
    from .esac.modelfile import save

    pred = policy.predictor
    meta = {"layout": pred.layout, "n_in": pred.n_in, "hidden": _hidden(net),
            "delay_input": pred.delay_input, "lookahead_s": pred.lookahead_s.tolist(),
            "rule": policy.rule()}
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "model.pt"
        save(f, net, meta)
        return f.read_bytes()


def _net_from_bytes(blob: bytes) -> Any:
    from .esac.modelfile import load

    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "model.pt"
        f.write_bytes(blob)
        return load(f)[0].net


def _hidden(net: Any) -> list[int]:
    import torch

    return [m.out_features for m in net.body if isinstance(m, torch.nn.Linear)][:-1]


def make_controller(spec: str, env: Any, seed: int = 0) -> Frozen:
    """An operating controller from its spec: ``NAME`` or ``NAME=PATH`` (frozen),
    ``gaslaw-adaptive``, or ``esac-adaptive=PATH`` (an ESAC run or model)."""
    if spec == "gaslaw-adaptive":
        return AdaptiveGasLaw(env, seed)
    if spec.startswith("esac-adaptive="):
        return AdaptiveESAC(spec, env, seed)
    return Frozen(spec, env, seed)

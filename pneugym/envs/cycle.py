"""The cycle mode of the cut-off task: one episode is a working cycle (extend, dwell, retract,
dwell), with one cut-off decision per stroke direction.

Each stroke is a :class:`~pneugym.envs.cutoff.CutOffEnv` episode on the rig's own stroke
direction (the extension on the rig with ``stroke_direction="extend"``, the retraction with
``"retract"``): the same actions (0 keep, 1 cut; latched within a stroke), the same termination,
and the same objective per stroke, thesis eq. 5.9 on whichever side drives. Between them the
plant dwells ``dwell_s`` after the extension's arrival, and the chambers keep their air and its
temperature across the reversal (as :func:`pneugym.cycle.run_cycle`): an extension cut off early
leaves less back-pressure for the retraction. Both strokes run under the same conditions (load,
supply, friction; one draw per cycle).

**Observation**: the stroke episode's (its ``time`` and ``position`` count from the stroke's own
command and start), then ``stroke``: 0 during the extension, 1 during the retraction.

**Reward**: each stroke's rewards, so the return is ``J_extend + J_retract``. An extension that
does not arrive (a stall or the time limit) ends the cycle there.

**Info**: the current stroke's state (as ``CutOffEnv``'s, times from its own command) and
``stroke`` (``"extend"``, ``"retract"``); the step that ends the extension returns the
retraction's first state and the extension's figures under ``extend``. At the end: ``extend`` and ``retract`` (each stroke's final info, as ``CutOffEnv``'s),
and for the cycle ``cycle_time_s`` (the simulated time to the end of the last dwell),
``air_mass_kg``, ``free_air_nl``, ``compressor_kwh`` (:mod:`pneugym.units`), ``saving_ratio``
(both strokes' wasted energy against both conventional strokes'; None, as ``cycle_time_s``,
unless both strokes arrived) and ``objective`` (a retraction that never ran counts as all its
air wasted plus the stall penalty, ``-(1 + w_stall)``), ``cycle_completed``. Each stroke's own
figures are under ``extend`` and ``retract`` only. Both strokes replay the conditions' supply
dip from their own command.
"""
from __future__ import annotations

import math
import warnings
from typing import Any, Mapping

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..physics import layout as L
from ..physics import system as K
from ..physics.energy import saving_ratio
from ..plant import SimulationError
from ..params import did_you_mean
from ..cycle import CARRIED, check_cycle_rig
from ..units import compressor_energy_kwh, free_air_nl
from .conditions import as_conditions
from .cutoff import (
    _DEFAULTS, OBS_BOUND, CutOffEnv, check_action, check_options, conventional_figures,
)

#: the per-step keys a cycle's final info keeps at its top level (the strokes' own figures
#: are under ``extend`` and ``retract``)
STEP_KEYS = ("time_s", "position_m", "p_drive_pa", "p_exhaust_pa", "supply_cut", "measured_x_m",
             "measured_p_drive_pa", "measured_p_exhaust_pa", "stroke")
CYCLE_MAX_STEPS = 1600  # max_episode_steps of pneugym/CutOffCycle-v0 (two strokes of 4 s)


class CutOffCycleEnv(gym.Env):
    """One working cycle per reset (module docstring). Options: those of :class:`CutOffEnv`
    (the rig's ``stroke_direction`` is ignored: the cycle runs both) and ``dwell_s`` [s], the
    pause after each stroke's arrival (0.2 s)."""

    metadata = {"render_modes": []}

    def __init__(self, dwell_s: float = 0.2, **config: Any):
        unknown = set(config) - set(_DEFAULTS)
        if unknown:
            raise ValueError(f"unknown CutOffCycleEnv option(s) {sorted(unknown)}"
                             f"{did_you_mean(sorted(unknown)[0], [*_DEFAULTS, 'dwell_s'])}; known: "
                             f"{sorted(_DEFAULTS) + ['dwell_s']}")
        ok = isinstance(dwell_s, (int, float)) and not isinstance(dwell_s, bool)
        if not (ok and math.isfinite(dwell_s) and 0.0 <= dwell_s <= 60.0):
            raise ValueError(f"dwell_s = {dwell_s!r} is invalid: must be a number in [0, 60] s")
        self.dwell_s = float(dwell_s)
        from ..rigfile import as_rig

        rig = as_rig(config.get("rig"), "rig")
        check_cycle_rig(rig)
        cfg = {**config, "rig": rig}
        with warnings.catch_warnings():  # a stroke's step-limit hint is not the cycle's (below)
            warnings.simplefilter("ignore", UserWarning)
            self.strokes = (CutOffEnv(**{**cfg, "rig": rig.with_(stroke_direction="extend")}),
                            CutOffEnv(**{**cfg, "rig": rig.with_(stroke_direction="retract")}))
        ext = self.strokes[0]
        steps = 2 * math.ceil(ext.time_limit_s / ext.control_period_s - 1e-9)
        if steps > CYCLE_MAX_STEPS:
            gym.logger.warn(
                f"two strokes of time_limit_s / control_period_s = {steps} steps, more than the "
                f"{CYCLE_MAX_STEPS} of the registered TimeLimit: with gymnasium.make, pass "
                f"max_episode_steps={steps} too, or cycles end early")
        self.config = {**self.strokes[0].config, "dwell_s": self.dwell_s, "rig": rig}
        self.rig = rig
        n = self.strokes[0].observation_space.shape[0] + 1
        self.observation_space = spaces.Box(-OBS_BOUND, OBS_BOUND, shape=(n,), dtype=np.float32)
        self.action_space = spaces.Discrete(2)
        self._phase = -1  # -1 before reset, 0 extending, 1 retracting, 2 ended
        self._finals: list[dict[str, Any]] = []

    @property
    def observation_names(self) -> list[str]:
        return [*self.strokes[0].observation_names, "stroke"]

    def _obs(self, obs: np.ndarray, phase: int) -> np.ndarray:
        return np.append(obs, np.float32(phase)).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: Mapping[str, Any] | None = None):
        super().reset(seed=seed)
        ext = self.strokes[0]
        if "commissioning" in check_options(options):
            raise ValueError("options['commissioning']: the cycle environment simulates each "
                             "stroke's commissioning stroke from the conditions (observe_"
                             "commissioning); a measured one is told to CutOff-v0, one stroke "
                             "at a time")
        cond = check_options(options).get("conditions")
        if cond is None:
            cond = ext.space.sample(self.np_random, ext.rig)
        self._cond = as_conditions(cond, "options['conditions']")
        ret = self.strokes[1]
        try:  # the retraction must be feasible too: say so now, not after the extension
            conventional_figures(self._cond.rig(ret.rig), self._cond.dip,
                                 period_s=ret.control_period_s)
        except ValueError as exc:
            raise ValueError(f"the retract stroke of this cycle: {exc}") from None
        self._seeds = [int(s) for s in self.np_random.integers(0, 2**31 - 1, size=2)]
        obs, info = ext.reset(seed=self._seeds[0], options={"conditions": self._cond})
        self._phase, self._finals = 0, []
        info["stroke"] = "extend"
        return self._obs(obs, 0), info

    def step(self, action):
        if self._phase < 0:
            raise RuntimeError("call reset() before step()")
        if self._phase > 1:
            raise RuntimeError("the cycle has ended: call reset()")
        act = check_action(action)
        phase = self._phase
        obs, r, term, trunc, info = self.strokes[phase].step(act)
        info["stroke"] = ("extend", "retract")[phase]
        if not (term or trunc):
            return self._obs(obs, phase), r, False, False, info
        self._finals.append({k: info[k] for k in info if k != "stroke"})
        if phase == 0 and info["completed"]:
            self._dwell(0)
            obs, info = self._begin_retraction()
            return self._obs(obs, 1), r, False, False, info
        self._phase = 2
        if info["completed"]:
            self._dwell(phase)
        final = {k: info[k] for k in STEP_KEYS if k in info}
        final.update(self._cycle_info())
        r += final["objective"] - self._finals[0]["objective"] - (
            self._finals[1]["objective"] if len(self._finals) > 1 else 0.0)
        return self._obs(obs, phase), r, bool(term), bool(trunc), final

    # -- the reversal ----------------------------------------------------------------------
    def _dwell(self, phase: int) -> None:
        """Advance stroke ``phase``'s plant to ``dwell_s`` after its arrival, the command held;
        its final info then counts the air drawn until the end of the dwell (a supply never cut
        fills the driving side to supply pressure, as eq. 5.9 assumes)."""
        env = self.strokes[phase]
        y, P, d = env.Y[0], env.P[0], env.D[0]
        rest = d[L.D_T_ARRIVE] + self.dwell_s - d[L.D_T]
        if rest > 0.0:
            st = K.command_advance(y, P, d, env._W[0], -1.0, rest, False)
            if st != L.STATUS_OK:
                raise SimulationError(f"the dwell after the {env.rig.stroke_direction} stroke "
                                      f"went non-physical (status {st})")
        mass = float(y[env._b + L.Y_MIN])
        self._finals[phase].update(air_mass_kg=mass, free_air_nl=free_air_nl(mass),
                                   end_time_s=float(d[L.D_T]))

    def _begin_retraction(self) -> tuple[np.ndarray, dict[str, Any]]:
        """Start the retraction from the extension's chambers (line vented, piston at the end):
        its first observation, and an info of its state with the extension's figures."""
        ext, ret = self.strokes
        ret.reset(seed=self._seeds[1], options={"conditions": self._cond})
        be, br = ext._b, ret._b
        for a, b in CARRIED:
            ret.Y[0, br + b] = ext.Y[0, be + a]
        ret._observe(ret._all, ret.np_random, fresh=True)
        self._phase = 1
        return ret._obs[0].copy(), {**ret._step_info(0), "stroke": "retract",
                                    "extend": self._finals[0]}

    def _cycle_info(self) -> dict[str, Any]:
        """The cycle's figures from the strokes' final infos."""
        ext = self._finals[0]
        ret = self._finals[1] if len(self._finals) > 1 else None
        done = ret is not None and ext["completed"] and ret["completed"]
        mass = ext["air_mass_kg"] + (ret["air_mass_kg"] if ret else 0.0)
        ew = ext["energy_wasted_j"] + (ret["energy_wasted_j"] if ret else 0.0)
        ec = ext["energy_conventional_j"] + (ret["energy_conventional_j"] if ret else 0.0)
        # a retraction that never ran: all its air wasted, and the stall penalty
        missed = 0.0 if ret is not None else -(1.0 + self.strokes[1].weights["w_stall"])
        return {
            "extend": ext, "retract": ret,
            # from the extend command to the end of the last dwell, as simulated (a stroke
            # cut off at its arrival ends when its valve has closed, after the dwell if later)
            "cycle_time_s": ext["end_time_s"] + ret["end_time_s"] if done else None,
            "air_mass_kg": mass, "free_air_nl": free_air_nl(mass),
            "compressor_kwh": compressor_energy_kwh(mass),
            "saving_ratio": float(saving_ratio(ec, ew)) if done else None,
            "objective": ext["objective"] + (ret["objective"] if ret else missed),
            "cycle_completed": bool(done),
        }

"""Model-predictive cut-off on a commissioned rig model (``mpc-rig``).

A deployable, non-privileged policy for a rig no policy was trained on. Before it runs, the rig
makes two recorded strokes (:func:`pneugym.commission.commissioning_protocol`: a conventional
one, one cut off on arrival and held) and :func:`pneugym.commission.commission` fits a model of
the rig to them: valve delay and areas, friction, cushions, leaks, a transducer lag, the
supply line's model (and heat exchange and Stribeck friction where they are significant), with
the fit's uncertainty; a fit that stays far from the strokes (a wrong basin) is fitted again
from more starts (``COMMISSION_OPTIONS``). At the start of every stroke
the policy reads the operating point it is told (the supply set-point and the payload, as every
policy is) and plans on the model: it runs the plant ahead for every cut-off time (the oracle's
search, :func:`agents.oracle.search_cuts`) on ``members`` plausible rigs (the fitted one and
draws from the fit's uncertainty at twice its standard deviations,
:meth:`~pneugym.commission.Commissioned.members`), averages the return over them and cuts at the
time whose mean average within ``margin_periods`` (one control period) either side is best
(:func:`agents.mpc.expected_best`, every period of that window tried:
:func:`agents.oracle.settle_windows`): a cut on the edge of a stick-slip or a stall, which the
model may misplace by a few ms, is given up for a little air (issue 12, part 5). It takes only a cut
whose stroke every plausible rig completes (``min_completion``, a chance constraint): on a fit
far from the rig every completing stroke may stick, and a stroke that never completes would
then score better (docs/policies.md). The wide spread puts
the edge where rigs a little unlike the fitted one have it; the earlier plan (the fit's own
spread, the worst return within three periods: ``spread=1, rule="worst", margin_periods=3``)
did worse on 100 fresh family draws pooled (docs/policies.md).

Plans are cached per operating point: on a real controller they are computed between strokes
(about a second each on one core) and the stroke itself only compares the time with the plan.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from pneugym.envs import Conditions, conventional_figures
from pneugym.plant import RigWarning, SimulationError
from pneugym.rigfile import rig_fields

from .mpc import expected_best, robust_best
from .oracle import OraclePolicy, TimedCutPolicy, search_cuts, settle_windows

#: how the evaluation commissions a model per rig (:func:`pneugym.commission.commission`'s
#: options; ``pneugym evaluate --commission-starts/--commission-nfev/--commission-refit`` set
#: them): a fit that ends above the misfit flag is fitted again from 4 more starts per line
#: model (docs/policies.md: a wrong basin, not the plan, was what the plan lost most on)
COMMISSION_OPTIONS: dict[str, Any] = {"starts": 2, "max_nfev": 40, "n_jobs": 2,
                                      "refit_starts": 4}

#: the rig fields a member may change against the fitted rig (what the fit estimates, and the
#: model form: :attr:`pneugym.commission.Commissioned.alternatives`)
MEMBER_FIELDS = (
    "valve.delay_s", "valve.area_m2", "valve.exhaust_area_m2", "cylinder.port_area_m2",
    "friction.static_n", "friction.coulomb_n", "friction.viscous_n_s_per_m",
    "cylinder.cushion_length_m", "cylinder.cushion_factor_drive",
    "cylinder.cushion_factor_exhaust", "effects.leak_drive_area_m2",
    "effects.leak_piston_area_m2", "effects.heat_transfer_time_constant_s",
    "effects.sensor_lag_s", "effects.stribeck_force_n", "effects.stribeck_velocity_m_s",
    "line.model", "valve.flow_model", "solver.dt_s")
#: how a plan picks its cut from the plausible rigs' mean returns (RigModelPolicy's ``rule``)
RULES = {"mean": expected_best, "worst": robust_best}
#: the plausible rigs' figures a plan reads: the return, and whether the stroke completed
PLAN_FIGURES = ("objective", "completed")
#: of those, the model form (and its substep): another form's fit differs in them
FORM_FIELDS = ("line.model", "valve.flow_model", "solver.dt_s")


class RigModelPolicy(TimedCutPolicy):
    """Plans its cut on a commissioned model of the rig (module docstring). ``model``: a
    :class:`~pneugym.commission.Commissioned` or the folder ``pneugym commission`` wrote (or
    ``None``: give one with :meth:`commission` before the first stroke); ``members``: plausible
    rigs the plan averages over (1: the fitted rig alone); ``spread``: their spread, times the
    fit's standard deviations (:meth:`~pneugym.commission.Commissioned.members`); ``forms``:
    the best fits of the other model forms the strokes cannot rule out among them;
    ``margin_periods``: half-width of the choice's window; ``rule``: ``"worst"`` (the cut whose
    worst return within the window is best, :func:`agents.mpc.robust_best`) or ``"mean"``
    (whose mean, :func:`agents.mpc.expected_best`); ``coarse``: the search's coarse grid in
    control periods (1: every period); ``stick_weight``: a plausible rig's stick-slip priced at
    this many times the environment's ``w_stick`` in the plan (the operator's aversion to
    sticking; the figures keep ``w_stick``); ``stall_weight``: a plausible rig's stroke not
    completed priced so against ``w_stall``; ``shift_periods``: the chosen cut moved this many
    control periods later; ``min_completion``: a chance constraint, the plan only takes a cut
    whose stroke at least this share of the plausible rigs complete (default 1: all of them;
    0: any cut; never cutting qualifies wherever every plausible rig's conventional stroke
    arrives within the episode's time limit; :func:`completing`). The observation must hold
    the payload (``observe_rig=True``, as every evaluation has)."""

    name = "mpc-rig"
    #: the evaluation commissions a model per rig when none is given (agents.evaluation.run)
    commissioned_per_rig = True

    def __init__(self, layout: Mapping[str, Any], env_config: Mapping[str, Any] | None = None,
                 model: Any = None, members: int = 8, spread: float = 2.0, forms: bool = False,
                 margin_periods: int = 1, rule: str = "mean", coarse: int = 4, seed: int = 0,
                 stick_weight: float = 1.0, stall_weight: float = 1.0, shift_periods: int = 0,
                 min_completion: float = 1.0):
        super().__init__(layout, math.inf)
        if not (isinstance(min_completion, (int, float)) and not isinstance(min_completion, bool)
                and 0 <= min_completion <= 1):
            raise ValueError(f"min_completion = {min_completion!r} must be a share in [0, 1]")
        for name, v in (("spread", spread), ("stick_weight", stick_weight),
                        ("stall_weight", stall_weight)):
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v < math.inf):
                raise ValueError(f"{name} = {v!r} must be a finite number >= 0")
        if rule not in RULES:
            raise ValueError(f"rule = {rule!r}: choose from {tuple(RULES)}")
        for name, v, lo in (("members", members, 1), ("margin_periods", margin_periods, 0),
                            ("coarse", coarse, 1), ("shift_periods", shift_periods, 0)):
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= lo):
                raise ValueError(f"{name} = {v!r} must be an integer >= {lo}")
        names = {f["name"] for f in layout.get("rig_features") or []}
        if "payload" not in names:
            raise ValueError("mpc-rig reads the payload from the observation: make the "
                             "environment with observe_rig=True (as evaluate does)")
        self.layout = dict(layout)
        self.env_config = {k: v for k, v in dict(env_config or {}).items()
                           if k not in ("preset", "conditions", "render_mode", "rig")}
        self.n_members, self.margin, self.coarse, self.seed = members, margin_periods, coarse, seed
        self.rule, self.spread, self.forms = rule, float(spread), bool(forms)
        self.stick_weight, self.stall_weight = float(stick_weight), float(stall_weight)
        self.shift, self.min_completion = shift_periods, float(min_completion)
        self.period = float(layout["control_period_s"])
        self.window = float(self.env_config.get("decision_window_s", 0.02))
        self.model = None
        self.commission_options = dict(COMMISSION_OPTIONS)
        self._plans: dict[tuple[float, float], float] = {}
        self._prev_t = np.zeros(0)
        if model is not None:
            self.set_model(model)

    @classmethod
    def for_env(cls, env, **kwargs: Any) -> "RigModelPolicy":
        u = env.unwrapped
        return cls(u.observation_layout(), env_config=u.config, **kwargs)

    # -- the model ---------------------------------------------------------------------------
    def set_model(self, model: Any) -> None:
        """Plan on ``model`` from now on (a :class:`~pneugym.commission.Commissioned` or its
        folder); forgets every plan."""
        from pneugym.commission import Commissioned

        if isinstance(model, (str, Path)):
            model = Commissioned.load(model)
        if not isinstance(model, Commissioned):
            raise ValueError(f"mpc-rig needs a commissioned model (pneugym commission), got "
                             f"{type(model).__name__}")
        self.model = model
        self.source = f"mpc-rig on a model of {', '.join(model.runs) or 'measured runs'}"
        self.rigs = model.members(self.n_members, self.seed, self.spread, self.forms)
        priced = {"w_stick": self.stick_weight * float(self.env_config.get("w_stick", 0.5)),
                  "w_stall": self.stall_weight * float(self.env_config.get("w_stall", 2.0))}
        self.planner = OraclePolicy(self.layout, {**self.env_config, "rig": model.rig, **priced},
                                    coarse=self.coarse, seed=self.seed)
        fitted = rig_fields(model.rig)
        self.changes = [tuple((k, v) for k, v in rig_fields(r).items()
                              if k in MEMBER_FIELDS and v != fitted[k]) for r in self.rigs]
        self._plans = {}

    def commission(self, runs: Sequence[Any], base: Any = None, **kwargs: Any) -> None:
        """Fit the model to the rig's measured ``runs`` (:func:`pneugym.commission.commission`,
        ``kwargs`` its options) and plan on it."""
        from pneugym.commission import commission

        self.set_model(commission(runs, base, **kwargs))

    # -- the control loop --------------------------------------------------------------------
    def act(self, obs: np.ndarray) -> np.ndarray:
        if self.model is None:
            raise RuntimeError("mpc-rig has no rig model: commission one (pneugym commission "
                               "RUNS --out DIR, then mpc-rig=DIR) before the first stroke")
        t = self.read(obs, "time")
        n = obs.shape[0]
        if self.t_cut_s.shape != (n,):
            self.t_cut_s = np.full(n, math.inf)
            self._prev_t = np.full(n, math.inf)
        new = np.flatnonzero(t < self._prev_t)  # a stroke began (its time went back)
        self._prev_t = t.copy()
        if new.size:
            sup = self.read(obs[new], "supply_setpoint")
            load = self.read(obs[new], "payload")
            points = [(round(float(s), 0), round(float(m), 4)) for s, m in zip(sup, load)]
            self.plan(sorted(set(points) - set(self._plans)))
            self.t_cut_s[new] = [self._plans[p] for p in points]
        return (t >= self.t_cut_s - self._half).astype(np.int64)

    def members_at(self, sup: float, load: float) -> tuple[dict[int, Conditions], list[float]]:
        """The plausible rigs (by index) that complete a conventional stroke at supply set-point
        ``sup`` [Pa gauge] and payload ``load`` [kg], as conditions, and their stroke times [s]."""
        members, t_end = {}, []
        with warnings.catch_warnings():  # a plausible rig that needs a smaller substep is ours
            warnings.simplefilter("ignore", RigWarning)
            for j, ch in enumerate(self.changes):
                c = Conditions(supply_pressure_gauge_pa=sup, load_mass_kg=load, rig_changes=ch)
                try:
                    t_end.append(conventional_figures(c.rig(self.model.rig), c.dip,
                                                      period_s=self.period)[0])
                except (ValueError, SimulationError):
                    continue  # a member that cannot complete a stroke here
                members[j] = c
        return members, t_end

    def plan(self, points: Sequence[tuple[float, float]]) -> dict[tuple[float, float], float]:
        """Plan the cut-off time [s] (``inf``: never) of each operating point ``(supply set-point
        [Pa gauge], payload [kg])``, all searched together; cached."""
        if not points:
            return {}
        with warnings.catch_warnings():  # a plausible rig that needs a smaller substep is ours
            warnings.simplefilter("ignore", RigWarning)
            conds, ranges = {}, {}
            for k, (sup, load) in enumerate(points):
                members, t_end = self.members_at(sup, load)
                if not members:  # no plausible rig completes a stroke: never cut
                    self._plans[points[k]] = math.inf
                    continue
                conds.update({(k, j): c for j, c in members.items()})
                ranges[k] = (0, int(math.ceil((max(t_end) + self.window) / self.period)) + 1)

            mean: dict = {k: {} for k in ranges}  # mean return and completed share, by cut
            done: dict = {k: {} for k in ranges}

            def score(cands: dict) -> dict:
                per = self.planner.score_figures(conds, {(k, j): cands[k] for k, j in conds
                                                         if k in cands}, PLAN_FIGURES)
                for k in cands:
                    for tc in cands[k]:
                        figs = [per[kk, j][tc] for kk, j in per if kk == k]
                        mean[k][tc] = float(np.mean([f[0] for f in figs]))
                        done[k][tc] = float(np.mean([f[1] for f in figs]))
                # the search refines around the best cuts the plan may take
                return {k: {tc: mean[k][tc] if _completes(done[k][tc], self.min_completion)
                            else -math.inf for tc in cands[k]} for k in cands}

            def pick(k: int) -> float:
                return RULES[self.rule](mean[k], self.margin * self.period,
                                        completing(done[k], self.min_completion))

            scores = search_cuts(score, ranges, self.period, self.coarse)
            for k, t in settle_windows(score, scores, pick, ranges, self.period,
                                       self.margin).items():
                self._plans[points[k]] = t + self.shift * self.period  # (inf stays inf)
        return {p: self._plans[p] for p in points}


def completing(done: Mapping[float, float], share: float) -> list[float]:
    """The cut-off times whose stroke at least ``share`` of the plausible rigs complete
    (``done``: the share by time), or, if none, those the most of them complete."""
    allowed = [t for t, d in done.items() if _completes(d, share)]
    return allowed or [t for t, d in done.items() if d == max(done.values(), default=0.0)]


def _completes(done: float, share: float) -> bool:
    """Whether a completed share ``done`` reaches ``share`` (a mean of 0/1 figures: rounding
    spared)."""
    return done >= share - 1e-9

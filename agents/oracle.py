"""The oracle: the best single cut-off time for an episode, found with **privileged** access to
the episode's conditions (load, supply, friction, valve delay, dip), by searching on copies of the
plant. No deployable controller knows these; the oracle is the upper bound for any latched
policy at the control period's resolution, and the reference of ``oracle_fraction``.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .base import Policy, run_first_episodes


def search_cuts(score: Callable[[dict], dict], ranges: Mapping[Any, tuple[int, int]],
                period: float, coarse: int) -> dict[Any, dict[float, float]]:
    """Returns of cut-off times for several cases, searched together: ``score({key: [t_cut,
    ...]})`` gives ``{key: {t_cut: return}}`` (one batched run); each case ``key`` is tried at
    every ``coarse``-th control step of its range ``(first, last)`` and never cutting (``inf``),
    then at every step around its three best. Returns every case's tried cuts and returns."""
    cands = {key: [k * period for k in range(k0, k1 + 1, coarse)] + [math.inf]
             for key, (k0, k1) in ranges.items()}
    scores = score(cands)
    fine: dict[Any, list[float]] = {}
    for key, js in scores.items():
        k0 = ranges[key][0]
        tried = {round(t / period) for t in js if math.isfinite(t)}
        steps: set[int] = set()
        for t in sorted(js, key=js.get, reverse=True)[:3]:
            if math.isfinite(t):
                k = int(round(t / period))
                steps.update(range(max(k0, k - coarse + 1), k + coarse))
        fine[key] = [k * period for k in sorted(steps - tried)]
    for key, js in score(fine).items():
        scores[key].update(js)
    return scores


def settle_windows(score: Callable[[dict], dict], scores: dict[Any, dict[float, float]],
                   pick: Callable[[Any], float], ranges: Mapping[Any, tuple[int, int]],
                   period: float, margin: int) -> dict[Any, float]:
    """The cut ``pick(key)`` chooses for every case of a :func:`search_cuts` search (``scores``,
    updated in place) once every control step of its range within ``margin`` steps of that cut
    has been tried: a rule that judges a cut by its neighbours (the mean or worst return within
    a window) would otherwise judge a coarse-grid cut by itself alone. Untried steps are scored
    with ``score`` (batched over the cases) and every case that had some chooses again, until
    none is missing."""
    chosen: dict[Any, float] = {}
    todo = list(scores)
    while todo:
        missing: dict[Any, list[float]] = {}
        for key in todo:
            t = chosen[key] = pick(key)
            if margin <= 0 or not math.isfinite(t):
                continue
            k, (k0, k1) = int(round(t / period)), ranges[key]
            tried = {round(s / period) for s in scores[key] if math.isfinite(s)}
            need = [j * period for j in range(max(k0, k - margin), min(k1, k + margin) + 1)
                    if j not in tried]
            if need:
                missing[key] = need
        if missing:
            for key, js in score(missing).items():
                scores[key].update(js)
        todo = list(missing)
    return chosen


class TimedCutPolicy(Policy):
    """Cuts the supply from time ``t_cut_s`` on (one value, or one per observation row;
    ``inf`` = never)."""

    name = "timed"

    def __init__(self, layout: Mapping[str, Any], t_cut_s: float | np.ndarray = math.inf):
        super().__init__(layout)
        self.t_cut_s = np.asarray(t_cut_s, dtype=float)
        self._half = 0.5 * float(layout["control_period_s"])

    def act(self, obs: np.ndarray) -> np.ndarray:
        return (self.read(obs, "time") >= self.t_cut_s - self._half).astype(np.int64)


class OraclePolicy(TimedCutPolicy):
    """Cuts at the control step that maximises the episode's return under its true conditions.

    Call :meth:`begin_episodes` with the conditions of the episodes about to start (evaluate.py
    does, from the reset ``info``). The search evaluates a cut at every ``coarse``-th control step
    (and never cutting) in one batched run, then every step around the three best; ``plan`` results
    are cached per condition. ``env_config`` must be the evaluated environment's configuration.
    """

    name = "oracle"
    privileged = True

    def __init__(self, layout: Mapping[str, Any], env_config: Mapping[str, Any] | None = None,
                 coarse: int = 4, seed: int = 0):
        super().__init__(layout)
        if not (isinstance(coarse, int) and coarse >= 1):
            raise ValueError(f"coarse = {coarse!r} must be an integer >= 1")
        self.env_config = {k: v for k, v in dict(env_config or {}).items()
                           if k not in ("preset", "conditions", "render_mode")}
        self.coarse, self.seed = coarse, seed
        self.period = float(layout["control_period_s"])
        self._cache: dict[tuple, tuple[float, float]] = {}

    @classmethod
    def for_env(cls, env, **kwargs: Any) -> "OraclePolicy":
        u = env.unwrapped
        return cls(u.observation_layout(), env_config=u.config, **kwargs)

    @property
    def base_rig(self):
        """The evaluated environment's rig (what each episode's ``rig_changes`` apply to)."""
        from pneugym.envs.cutoff import CutOffVectorEnv

        if not hasattr(self, "_base_rig"):
            self._base_rig = CutOffVectorEnv(num_envs=1, **self.env_config).rig
        return self._base_rig

    def _figures(self, conds: Sequence[Any], t_cuts: np.ndarray) -> dict[str, np.ndarray]:
        """Final figures of each (conditions, cut-off time) pair, all in one batched run."""
        from pneugym.envs.cutoff import CutOffVectorEnv

        env = CutOffVectorEnv(num_envs=t_cuts.size, autoreset=False, **self.env_config)
        pol = TimedCutPolicy(env.observation_layout(), t_cuts)
        return run_first_episodes(env, pol, list(conds), self.seed)

    def plan(self, cond) -> tuple[float, float]:
        """``(t_cut_s, return)`` of the best cut-off for conditions ``cond`` (``inf`` = never)."""
        return self.plan_many([cond])[0]

    def plan_many(self, conditions: Sequence[Any]) -> list[tuple[float, float]]:
        """:meth:`plan` for many conditions, searched together (two batched runs)."""
        todo = [c for c in conditions if c.physics_key() not in self._cache]
        if todo:
            for key, js in self._search(todo).items():
                t = max(js, key=js.get)
                self._cache[key] = (float(t), float(js[t]))
        return [self._cache[c.physics_key()] for c in conditions]

    def returns_many(self, conditions: Sequence[Any]) -> list[dict[float, float]]:
        """The return of every cut-off time [s] the search tried for each of ``conditions``
        (``inf``: never cutting); with ``coarse=1`` every control step up to the conventional
        stroke's end and the decision window."""
        scores = self._search(conditions)
        return [scores[c.physics_key()] for c in conditions]

    def _search(self, conditions: Sequence[Any]) -> dict[Any, dict[float, float]]:
        from pneugym.envs import conventional_figures

        todo = {}
        for c in conditions:
            todo.setdefault(c.physics_key(), c.noise_free())
        window = float(self.env_config.get("decision_window_s", 0.02))
        ranges = {}
        for key, c in todo.items():
            t_conv, _ = conventional_figures(c.rig(self.base_rig), c.dip)
            ranges[key] = (0, int(math.ceil((t_conv + window) / self.period)) + 1)
        return search_cuts(lambda cands: self.score_cuts(todo, cands), ranges, self.period,
                           self.coarse)

    def score_cuts(self, conds: dict, cands: dict) -> dict[Any, dict[float, float]]:
        """Returns of cut-off times: ``conds`` ``{key: Conditions}`` (noise-free), ``cands``
        ``{key: [t_cut_s, ...]}``; all pairs in one batched run of the environment."""
        return {key: {t: v[0] for t, v in js.items()}
                for key, js in self.score_figures(conds, cands, ("objective",)).items()}

    def score_figures(self, conds: dict, cands: dict, names: Sequence[str]
                      ) -> dict[Any, dict[float, tuple[float, ...]]]:
        """:meth:`score_cuts` with the final figures ``names`` (e.g. ``("objective",
        "stick_slip_events")``) of every cut, as a tuple, from the same batched run (a figure
        the environment leaves ``None``, e.g. a stalled stroke's time, as ``nan``)."""
        pairs = [(key, t) for key, ts in cands.items() for t in ts]
        out: dict[Any, dict[float, tuple[float, ...]]] = {key: {} for key in cands}
        if not pairs:
            return out
        fig = self._figures([conds[k] for k, _ in pairs], np.array([t for _, t in pairs]))
        for i, (key, t) in enumerate(pairs):
            out[key][t] = tuple(math.nan if fig[n][i] is None else float(fig[n][i])
                                for n in names)  # (None, e.g. a stalled stroke's time: nan)
        return out

    needs_conditions = True

    def begin_episodes(self, conditions: Sequence[Any]) -> None:
        self.t_cut_s = np.array([t for t, _ in self.plan_many(conditions)])
        self._told_rows = len(conditions)

"""agents/learned.py: observation layouts of saved models against environments, and the history a
policy stacks itself in a ``history=1`` environment."""
import numpy as np
import pytest

from agents.base import run_first_episodes
from agents.learned import HistoryStack, LayoutMismatchError, LearnedPolicy, check_layout
from pneugym.envs import Conditions
from pneugym.envs.cutoff import CutOffVectorEnv

CONDS = [Conditions(supply_pressure_gauge_pa=p, load_mass_kg=m, position_noise_m=3e-5,
                    pressure_noise_pa=400.0) for p, m in ((1.5e5, 10.0), (4e5, 25.0))]


def layout(**cfg):
    return CutOffVectorEnv(num_envs=1, **cfg).observation_layout()


def test_same_layout_needs_no_stacking():
    assert check_layout(layout(history=4), layout(history=4)) == 0
    assert check_layout(layout(), layout()) == 0


def test_history_is_stacked_only_from_single_samples():
    assert check_layout(layout(history=8), layout(history=1)) == 8
    with pytest.raises(LayoutMismatchError, match="history 8 .model. vs 2 .env."):
        check_layout(layout(history=8), layout(history=2))


@pytest.mark.parametrize("cfg, what", [
    ({"time_limit_s": 8.0}, "time_limit_s"),
    ({"observe_params": True}, "observe_params"),
    ({"control_period_s": 0.01}, "control_period_s"),
])
def test_mismatches_are_named(cfg, what):
    with pytest.raises(LayoutMismatchError, match=what):
        check_layout(layout(history=4), layout(history=1, **cfg), "model m.zip")


def test_stacked_single_samples_equal_the_environments_history():
    """A history=1 environment plus HistoryStack gives exactly the history=4 observations
    (same seeds, same conditions, same noise), through an autoreset too."""
    n, k = len(CONDS), 4
    e1 = CutOffVectorEnv(num_envs=n, history=1, preset="randomized")
    e4 = CutOffVectorEnv(num_envs=n, history=k, preset="randomized")
    o1, _ = e1.reset(seed=3, options={"conditions": CONDS})
    o4, _ = e4.reset(seed=3, options={"conditions": CONDS})
    stack = HistoryStack(k, 7, 0)
    tidx = [f["name"] for f in e1.observation_layout()["features"]].index("time")
    rng = np.random.default_rng(0)
    resets = 0
    for step in range(700):
        np.testing.assert_array_equal(stack(o1, tidx), o4)
        a = (rng.random(n) < 0.01).astype(np.int64)
        o1, _, te, tr, _ = e1.step(a)
        o4, _, te4, tr4, _ = e4.step(a)
        np.testing.assert_array_equal(te | tr, te4 | tr4)
        resets += int((te | tr).sum())
    assert resets >= 2  # the comparison crossed autoresets


class _Recorder(LearnedPolicy):
    def __init__(self, env_layout, model_layout):
        super().__init__(env_layout, model_layout)
        self.seen = []

    def act_model(self, obs):
        self.seen.append(obs.copy())
        return np.zeros(obs.shape[0], dtype=np.int64)


def test_learned_policy_sees_its_own_layout_in_a_history1_env():
    env = CutOffVectorEnv(num_envs=2, autoreset=False)
    pol = _Recorder(env.observation_layout(), layout(history=3))
    run_first_episodes(env, pol, CONDS, 5)
    assert all(o.shape == (2, 21) for o in pol.seen)
    first = pol.seen[0]
    np.testing.assert_array_equal(first[:, :7], first[:, 14:])  # a reset repeats the sample
    np.testing.assert_array_equal(pol.seen[2][:, 7:14], pol.seen[1][:, 14:])  # shifted


def _ppo_cutting_with(p_cut: float):
    """A PPO model whose policy cuts with probability ``p_cut`` in every state, its env, layout."""
    import torch
    from stable_baselines3 import PPO

    from pneugym.envs.sb3 import CutOffVecEnv

    venv = CutOffVecEnv(num_envs=2)
    ppo = PPO("MlpPolicy", venv, n_steps=8, batch_size=16, device="cpu", seed=0)
    with torch.no_grad():
        ppo.policy.action_net.weight.zero_()
        ppo.policy.action_net.bias[:] = torch.tensor([0.0, float(np.log(p_cut / (1 - p_cut)))])
    return venv, venv.observation_layout(), ppo


def test_sb3_decision_rules():
    """quantile: cut once 1 - prod(1 - p_cut) reaches the value; advantage: Q(cut) - Q(keep)."""
    import torch
    from stable_baselines3 import DQN

    from agents.learned import SB3Policy

    venv, lay, ppo = _ppo_cutting_with(0.1)
    pol = SB3Policy(lay, ppo, lay, decision={"rule": "quantile", "value": 0.5})
    obs = np.zeros((1, 7), dtype=np.float32)
    obs[0, 5] = 0.01
    acts = [int(pol.act(obs)[0]) for _ in range(8)]
    # 1 - 0.9^k >= 0.5 first at k = 7
    assert acts == [0] * 6 + [1] * 2
    obs[0, 5] = 0.0  # a new episode restarts the count
    assert int(pol.act(obs)[0]) == 0
    with pytest.raises(ValueError, match="Q-network"):
        SB3Policy(lay, ppo, lay, decision={"rule": "advantage", "value": 0.0})
    dqn = DQN("MlpPolicy", venv, learning_starts=0, buffer_size=100, device="cpu", seed=0)
    q = dqn.q_net(torch.as_tensor(obs)).detach().numpy()[0]
    adv = float(q[1] - q[0])
    for value, want in ((adv - 1e-3, 1), (adv + 1e-3, 0)):
        p = SB3Policy(lay, dqn, lay, decision={"rule": "advantage", "value": value})
        assert int(p.act(obs)[0]) == want
    with pytest.raises(ValueError, match="decision rule"):
        SB3Policy(lay, dqn, lay, decision={"rule": "vote"})


def test_sb3_hazard_rule():
    """hazard: cut at the first step whose own p_cut reaches the value (latched after)."""
    from agents.learned import SB3Policy

    _, lay, ppo = _ppo_cutting_with(0.1)
    obs = np.zeros((2, 7), dtype=np.float32)
    obs[:, 5] = 0.01
    pol = SB3Policy(lay, ppo, lay, decision={"rule": "hazard", "value": np.array([0.09, 0.11])})
    assert pol.act(obs).tolist() == [1, 0]
    obs[1, 6] = 1.0  # already cut: stays cut
    assert pol.act(obs).tolist() == [1, 1]


def test_asymmetric_actor_ignores_privileged_features():
    """The privileged critic's policy: the actor reads only the public columns, the critic all;
    it saves and loads (agents.safe_load: nothing unpickled) and runs in an environment without privileged features
    (zeros are fed), while a plain model with privileged features is still refused there."""
    import torch
    from stable_baselines3 import PPO

    from agents.learned import AsymmetricActorCriticPolicy, SB3Policy
    from agents.safe_load import load_sb3
    from pneugym.envs.sb3 import CutOffVecEnv

    venv = CutOffVecEnv(num_envs=2, history=2, observe_params=True)
    lay = venv.observation_layout()
    n_pub = lay["size"] - len(lay["param_features"])
    assert len(lay["param_features"]) == 3 and n_pub == 14
    ppo = PPO(AsymmetricActorCriticPolicy, venv, n_steps=8, batch_size=16, device="cpu", seed=0,
              policy_kwargs={"actor_inputs": n_pub, "net_arch": [16, 16]})
    rng = np.random.default_rng(0)
    obs = rng.uniform(-1, 1, (5, lay["size"])).astype(np.float32)
    other = obs.copy()
    other[:, n_pub:] = rng.uniform(-3, 3, (5, 3))
    with torch.no_grad():
        for layer in ppo.policy.mlp_extractor.policy_net:  # make every input matter
            if isinstance(layer, torch.nn.Linear):
                layer.weight.normal_()
        a, b = (ppo.policy.get_distribution(torch.as_tensor(x)).distribution.probs
                for x in (obs, other))
        va, vb = (ppo.policy.predict_values(torch.as_tensor(x)) for x in (obs, other))
    assert torch.equal(a, b) and not torch.allclose(va, vb)
    assert ppo.policy.mlp_extractor.policy_net[0].in_features == n_pub
    assert ppo.policy.mlp_extractor.value_net[0].in_features == lay["size"]
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        ppo.save(f"{d}/m.zip")
        loaded = load_sb3(f"{d}/m.zip", "ppo")
    assert type(loaded.policy).__name__ == "AsymmetricActorCriticPolicy"
    assert loaded.policy.actor_inputs == n_pub
    # in a public, history-1 environment: zeros for the privileged columns
    env_lay = CutOffVectorEnv(num_envs=1).observation_layout()
    pol = SB3Policy(env_lay, loaded, lay, decision={"rule": "hazard", "value": 0.5})
    x = pol.model_obs(np.zeros((1, 7), dtype=np.float32))
    assert x.shape == (1, lay["size"]) and not x[:, n_pub:].any()
    # a model whose actor reads the privileged features still needs them
    plain = PPO("MlpPolicy", venv, n_steps=8, batch_size=16, device="cpu", seed=0)
    with pytest.raises(LayoutMismatchError, match="privileged"):
        SB3Policy(env_lay, plain, lay)
    # and the public features must still match
    with pytest.raises(LayoutMismatchError, match="time_limit_s"):
        SB3Policy(CutOffVectorEnv(num_envs=1, time_limit_s=6.0).observation_layout(), loaded,
                  lay)


def test_recorded_layouts_are_checked_before_use():
    from agents.learned import check_layout_record

    good = layout(history=3, observe_params=True)
    assert check_layout_record(good, "m.zip: pneugym_layout") is good
    for bad, match in (
            ([], r"m: x is \[\]; expected an object"),
            ({**good, "features": good["features"] * 10}, r"expected a list of up to 64"),
            ({**good, "param_features": "abc"}, r"param_features is 'abc'"),
            ({**good, "history": True}, r"history is True"),
            ({**good, "history": 10 ** 6}, r"history is 1000000; expected an integer from 1 to "
                                           r"1000"),
            ({**good, "size": 21}, r"size is 21; expected 24 \(history 3 x 7 features \+ 3 "
                                   r"privileged features\)"),
            ({**good, "control_period_s": float("inf")}, r"control_period_s is inf"),
            ({**good, "features": [{"name": "position", "scale": 1.0}] * 2}, r"names 'position' "
                                                                             r"twice"),
            ({**good, "features": [{**f, "unit": 1} for f in good["features"]]},
             r"features\[0\] \('position'\).unit is 1; expected text")):
        with pytest.raises(LayoutMismatchError, match=match):
            check_layout_record(bad, "m: x")


def test_decisions_are_checked():
    from agents.learned import check_decision

    assert check_decision({"rule": "argmax"}, "d") == {"rule": "argmax"}
    assert check_decision({"rule": "quantile", "value": 1}, "d")["value"] == 1
    arr = np.array([0.1, 0.5])
    assert check_decision({"rule": "hazard", "value": arr}, "d", per_row=True)["value"] is arr
    for bad, match in (({"rule": "hazard", "value": np.array([0.1, 1.5])}, r"value is"),
                       ({"rule": "quantile", "value": True}, r"value is True"),
                       ({"rule": "quantile", "value": -0.1}, r"\(0, 1\]"),
                       ({"rule": "advantage", "value": float("-inf")}, r"a finite number"),
                       ({"rule": "argmax", "value": "x"}, r"argmax does not use it"),
                       ({"rule": None}, r"the decision rule is None")):
        with pytest.raises(ValueError, match=f"d: .*{match}"):
            check_decision(bad, "d", per_row=True)
    _, lay, ppo = _ppo_cutting_with(0.1)
    from agents.learned import SB3Policy
    with pytest.raises(ValueError, match=r"the decision value is nan for the quantile rule"):
        SB3Policy(lay, ppo, lay, decision={"rule": "quantile", "value": float("nan")})


def test_a_model_of_another_stroke_is_refused_with_what_to_do():
    """The position is scaled by the stroke: a model of the 180 mm rig is refused on a 300 mm
    one, and the message says to retrain for the rig or use mpc-rig (not to rebuild the env)."""
    from agents.learned import LayoutMismatchError, check_layout
    from pneugym.envs.cutoff import CutOffEnv
    from pneugym.params import RigParams

    model = CutOffEnv().observation_layout()
    env = CutOffEnv(rig=RigParams().with_(cylinder={"stroke_m": 0.3})).observation_layout()
    with pytest.raises(LayoutMismatchError, match="retrain it for this rig .*mpc-rig"):
        check_layout(model, env)

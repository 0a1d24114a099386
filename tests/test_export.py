"""pneugym/deploy/export.py: neural policies' networks on onnxruntime and numpy give torch's
outputs within the stated tolerance and the same decisions over whole episodes; the exported
directory rebuilds the policy without torch, and refuses changed files and policies without a
network."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
torch = pytest.importorskip("torch")

from agents import esac  # noqa: E402
from agents.base import run_first_episodes  # noqa: E402
from agents.evaluation.suites import suite_episodes  # noqa: E402
from agents.learned import SB3Policy  # noqa: E402
from pneugym.deploy import export as ex  # noqa: E402
from pneugym.envs.cutoff import CutOffVectorEnv  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HISTORY = 2  # the models' history; the episodes run in history-1 environments (stacked)
POS = (HISTORY - 1) * 7  # the newest sample's position column in a model observation
CUT = POS + 6  # and its supply_cut column


def _layout(**cfg):
    return CutOffVectorEnv(num_envs=1, history=HISTORY, **cfg).observation_layout()


def _env_layout():
    return CutOffVectorEnv(num_envs=1, observe_rig=True).observation_layout()


# ------------------------------------------------------------------------------------------
# small policies whose cut depends on the piston's position (so that episodes cut mid-stroke)
# ------------------------------------------------------------------------------------------
def esac_policy(delay_input=False):
    """An ESAC predictor (16 SiLU units) sure of a complete stroke once the piston is ~70 % out,
    its other outputs small random; with a delay input, the lookahead rule."""
    torch.manual_seed(1)
    lay = _layout()
    net = esac.make_net(lay["size"] + int(delay_input), (16,))
    with torch.no_grad():
        net.in_mean[:] = 0.1 * torch.randn(net.in_mean.shape)
        net.in_std[:] = 1.0 + 0.2 * torch.rand(net.in_std.shape)
        net.out_mean[:] = torch.tensor([0.9, -0.02, 1.1, 0.4, 300.0])
        net.out_std[:] = torch.tensor([0.1, 0.05, 0.2, 0.2, 50.0])
        first, last = net.body[0], net.body[2]
        first.weight[0].zero_()
        first.weight[0, POS] = 4.0
        first.bias[0] = 0.0
        last.weight.mul_(0.1)
        last.weight[0, 0], last.bias[0] = 12.0, -30.0  # complete: logit > 3 from x ~ 0.7 stroke
        last.bias[1] = -8.0  # no stick-slip
        last.bias[2] = 2.0  # final position: the stroke's end
        last.bias[3] = -0.5  # log time ratio ~ 0.85: within the time demand
        if delay_input:  # a later cut wastes more: waiting does not pay
            first.weight[1].zero_()
            first.weight[1, -1], first.bias[1] = 20.0, 0.0
            last.weight[5, 1] = 5.0
    pred = esac.ESACPredictor(net.eval(), lay, delay_input=delay_input,
                              lookahead_s=[0.0, 0.02, 0.08] if delay_input else ())
    return esac.ESACPolicy(_env_layout(), pred, lookahead=int(delay_input), margin=0.05,
                           source="test ESAC" + (" (delay input)" if delay_input else ""))


def esac_ensemble_policy():
    """:func:`esac_policy`'s network and a perturbed copy of it as an ensemble of two (its
    outputs the worst member's or the mean, head by head)."""
    pol = esac_policy()
    net, lay = pol.predictor.net, pol.predictor.layout
    ens = esac.make_net(lay["size"], (16,), members=2)
    torch.manual_seed(3)
    with torch.no_grad():
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            getattr(ens, name).copy_(getattr(net, name))
        for member in ens.members:
            member.load_state_dict(net.body.state_dict())
        last = ens.members[1][2]
        last.weight.add_(0.02 * torch.randn(last.weight.shape))
        last.bias[0] -= 0.5  # less sure of a complete stroke: cuts later
    pred = esac.ESACPredictor(ens.eval(), lay)
    return esac.ESACPolicy(_env_layout(), pred, margin=0.05, source="test ESAC ensemble")


def _shape_actor(linear_in, linear_out, gain=1.0):
    """Make the first hidden unit follow the newest position and drive the cut output."""
    torch.manual_seed(2)
    with torch.no_grad():
        linear_in.weight.mul_(0.3)
        linear_in.weight[0].zero_()
        linear_in.weight[0, POS] = 3.0
        linear_in.bias[0] = 0.0
        linear_out.weight.normal_(0.0, 0.05)
        linear_out.weight[1, 0], linear_out.bias[1] = 8.0 * gain, -6.0 * gain
        linear_out.weight[0, 0], linear_out.bias[0] = 0.0, 0.0


def ppo_policy(rule="argmax", value=None, asymmetric=False):
    from stable_baselines3 import PPO

    from agents.learned import AsymmetricActorCriticPolicy
    from pneugym.envs.sb3 import CutOffVecEnv

    venv = CutOffVecEnv(num_envs=2, history=HISTORY, observe_params=asymmetric)
    lay = venv.observation_layout()
    kwargs = {"net_arch": [16]}
    if asymmetric:
        kwargs["actor_inputs"] = lay["size"] - len(lay["param_features"])
    ppo = PPO(AsymmetricActorCriticPolicy if asymmetric else "MlpPolicy", venv, n_steps=8,
              batch_size=16, device="cpu", seed=0, policy_kwargs=kwargs)
    _shape_actor(ppo.policy.mlp_extractor.policy_net[0], ppo.policy.action_net)
    decision = {"rule": rule} if value is None else {"rule": rule, "value": value}
    return SB3Policy(_env_layout(), ppo, lay, source=f"test PPO {rule}", decision=decision)


def dqn_policy(value=3.0):
    from stable_baselines3 import DQN

    from pneugym.envs.sb3 import CutOffVecEnv

    venv = CutOffVecEnv(num_envs=2, history=HISTORY)
    dqn = DQN("MlpPolicy", venv, learning_starts=0, buffer_size=100, device="cpu", seed=0,
              policy_kwargs={"net_arch": [16]})
    _shape_actor(dqn.q_net.q_net[0], dqn.q_net.q_net[2], gain=0.8)
    return SB3Policy(_env_layout(), dqn, venv.observation_layout(), source="test DQN",
                     decision={"rule": "advantage", "value": value})


POLICIES = {
    "esac": lambda: esac_policy(),
    "esac-delay": lambda: esac_policy(delay_input=True),
    "esac-ensemble": lambda: esac_ensemble_policy(),
    "ppo-argmax": lambda: ppo_policy(),
    "ppo-quantile": lambda: ppo_policy("quantile", 0.5),
    "ppo-hazard": lambda: ppo_policy("hazard", 0.7),
    "dqn-advantage": lambda: dqn_policy(),
    "ppo-asymmetric": lambda: ppo_policy("hazard", 0.6, asymmetric=True),
}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Every test policy and its exported directory."""
    root = tmp_path_factory.mktemp("exported")
    out = {}
    for name, make in POLICIES.items():
        pol = make()
        paths = ex.export(pol, root / name)
        out[name] = (pol, paths["controller"].parent)
    return out


@pytest.fixture(scope="module")
def observations():
    """Real observations (history 2, rig features): 8 randomized episodes, random cuts."""
    env = CutOffVectorEnv(num_envs=8, history=HISTORY, observe_rig=True, preset="randomized")
    obs, _ = env.reset(seed=5)
    rng = np.random.default_rng(5)
    rows = []
    for _ in range(150):
        rows.append(obs.copy())
        obs, *_ = env.step((rng.random(8) < 0.01).astype(np.int64))
    return np.concatenate(rows)


def _net_io(pol, obs, rng):
    """The network's inputs for history-2 observations ``obs`` (the model's layout: rig columns
    dropped, an asymmetric model's privileged columns zero, ESAC's delay) and the policy's
    network evaluation (its seam)."""
    x = obs[:, :HISTORY * 7]
    if isinstance(pol, esac.ESACPolicy):
        if pol.predictor.delay_input:
            x = np.concatenate([x, rng.choice([0.0, 0.02, 0.08], size=(x.shape[0], 1))], axis=1)
        return x.astype(np.float32), pol.predictor.backend
    x = np.concatenate([x, np.zeros((x.shape[0], pol._pad))], axis=1)
    return x.astype(np.float32), pol.network_outputs


# ------------------------------------------------------------------------------------------
# outputs within tolerance, identical decisions
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(POLICIES))
def test_backends_agree_on_real_observations(exported, observations, name):
    """torch vs onnx vs numpy (in memory and from the exported directory): every raw output
    within ATOL + RTOL |out| of torch's."""
    pol, d = exported[name]
    rng = np.random.default_rng(0)
    x, torch_fn = _net_io(pol, observations, rng)
    ref = torch_fn(x)
    assert ref.dtype == np.float32 and ref.shape == (x.shape[0], 7 if "esac" in name else 2)
    others = {b: _net_io(ex.with_backend(pol, b), observations[:1], rng)[1]
              for b in ("onnx", "numpy")}
    for b in ("onnx", "numpy"):
        others[f"exported-{b}"] = _net_io(ex.load_exported(d, _env_layout(), b),
                                          observations[:1], rng)[1]
    for b, fn in others.items():
        diff = ex.max_difference(fn(x), ref)
        print(f"{name} {b}: max |diff| {diff['max_abs']:.3g} (ratio to tolerance "
              f"{diff['max_ratio']:.3f})")
        assert diff["max_ratio"] <= 1.0, (b, diff)
    check = json.loads((d / "controller.json").read_text())["check"]
    assert check["onnx"]["max_ratio"] <= 1.0 and check["numpy"]["max_ratio"] <= 1.0


@pytest.mark.parametrize("name", list(POLICIES))
def test_backends_decide_alike_over_episodes(exported, name):
    """Whole episodes (8 nominal-suite conditions, history-1 environment: the policies stack the
    samples themselves) cut at the same instants on every backend."""
    pol, d = exported[name]
    conds = [c for _, c in suite_episodes("nominal", episodes=4, seed=11)]
    lay = _env_layout()
    policies = {"torch": ex.with_backend(pol, "torch"),
                **{b: ex.with_backend(pol, b) for b in ("onnx", "numpy")},
                **{f"exported-{b}": ex.load_exported(d, lay, b) for b in ("onnx", "numpy")}}
    cuts = {}
    for b, p in policies.items():
        env = CutOffVectorEnv(num_envs=len(conds), autoreset=False, observe_rig=True)
        cuts[b] = run_first_episodes(env, p, conds, seed=11)["cutoff_time_s"].astype(float)
    ref = cuts["torch"]
    assert np.isfinite(ref).any(), f"{name} never cut: the test would not compare decisions"
    for b, c in cuts.items():
        np.testing.assert_array_equal(c, ref, err_msg=f"{name} on {b}")


def test_sb3_decisions_are_sb3s_deterministic_predict(exported, observations):
    """The argmax rule through the network seam is SB3's ``predict(deterministic=True)``, for an
    actor-critic and a Q-network (a DQN's argmax rule is its greedy action)."""
    pol = exported["ppo-argmax"][0]
    x = observations[:, :HISTORY * 7]
    want, _ = pol.model.predict(x, deterministic=True)
    np.testing.assert_array_equal(np.argmax(pol.network_outputs(x), axis=1), want)
    dqn = exported["dqn-advantage"][0]
    greedy = SB3Policy(_env_layout(), dqn.model, dqn.full_layout)
    want, _ = dqn.model.predict(x, deterministic=True)
    np.testing.assert_array_equal(greedy.act_model(x), want)
    assert 0 < want.mean() < 1  # both actions occur


def test_ties_go_to_the_first_action_as_in_torch():
    q = np.array([[0.5, 0.5], [0.2, 0.7], [1.0, 1.0]], dtype=np.float32)
    np.testing.assert_array_equal(np.argmax(q, axis=1), torch.as_tensor(q).argmax(dim=1).numpy())


def test_with_backend_copies_and_the_original_keeps_torch(exported, observations):
    pol = exported["ppo-quantile"][0]
    other = ex.with_backend(pol, "numpy")
    assert other is not pol and other.model is pol.model and pol._backend is None
    assert isinstance(other.backend, ex.NumpyNetwork)
    e = exported["esac"][0]
    on = ex.with_backend(e, "onnx")
    assert on.predictor is not e.predictor and e.predictor._backend is None
    assert isinstance(on.predictor.backend, ex.OnnxNetwork)
    asym = ex.with_backend(exported["ppo-asymmetric"][0], "numpy")
    assert isinstance(asym.backend, ex.FirstColumns) and asym.backend.n == 14
    with pytest.raises(ValueError, match=r"choose one of \['torch', 'onnx', 'numpy'\]"):
        ex.with_backend(pol, "tensorrt")


def test_controller_json_records_the_policy(exported):
    pol, d = exported["ppo-asymmetric"]
    meta = json.loads((d / "controller.json").read_text())
    assert meta["kind"] == "sb3" and meta["sb3"]["algo"] == "ppo"
    assert meta["sb3"]["actor_inputs"] == 14 and meta["sb3"]["pad"] == 3
    assert meta["sb3"]["decision"] == {"rule": "hazard", "value": 0.6}
    assert meta["model_layout"] == json.loads(json.dumps(pol.model_layout))
    assert meta["network"]["inputs"] == 14 and meta["network"]["output"] == "softmax"
    assert set(meta["sha256"]) == {"model.onnx", "weights.npz"}
    e, d = exported["esac-delay"]
    meta = json.loads((d / "controller.json").read_text())
    assert meta["kind"] == "esac" and meta["esac"]["delay_input"] is True
    assert meta["esac"]["lookahead_s"] == [0.02, 0.08]
    assert meta["esac"]["rule"] == e.rule() and meta["esac"]["stroke_m"] == e.predictor.stroke_m
    assert meta["network"]["activations"] == ["silu", "identity"]
    assert meta["tolerance"] == {"atol": ex.ATOL, "rtol": ex.RTOL}


def test_an_export_loads_at_the_period_and_time_limit_it_was_built_for(exported, tmp_path):
    """Controller.load reads an export's control period and time scale from its
    controller.json (an export has no run.json)."""
    import shutil

    from pneugym.deploy.controller import _trained_env

    _, d = exported["ppo-asymmetric"]
    assert _trained_env(d) == {"control_period_s": 0.005, "time_limit_s": 4.0}
    copy = tmp_path / "slow"
    shutil.copytree(d, copy)
    meta = json.loads((copy / "controller.json").read_text())
    meta["model_layout"]["control_period_s"] = 0.01
    for f in meta["model_layout"]["features"]:
        if f["name"] == "time":
            f["scale"] = 6.0
    (copy / "controller.json").write_text(json.dumps(meta))
    assert _trained_env(copy) == {"control_period_s": 0.01, "time_limit_s": 6.0}


# ------------------------------------------------------------------------------------------
# refusals
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["conventional", "endstroke", "gaslaw", "mpc", "oracle"])
def test_baselines_need_no_export(tmp_path, name):
    from agents import make_policy

    pol = make_policy(name, CutOffVectorEnv(num_envs=1, observe_rig=True))
    with pytest.raises(ValueError, match="no neural network: it needs no export"):
        ex.export(pol, tmp_path)
    with pytest.raises(ValueError, match="few lines of numpy"):
        ex.with_backend(pol, "onnx")
    assert not any(tmp_path.iterdir())


def test_export_refuses_what_the_runtimes_would_compute_differently(tmp_path, monkeypatch):
    """A layer the numpy runtime lacks, or runtimes that compute another network (here: numpy
    weights off by 0.01), stop the export before anything is written."""
    pol = esac_policy()
    real = ex.network_arrays

    def off(p):
        a = real(p)
        a["bias_1"] = a["bias_1"] + np.float32(0.01)
        return a

    monkeypatch.setattr(ex, "network_arrays", off)
    with pytest.raises(ValueError, match="times the tolerance .*not the same network"):
        ex.export(pol, tmp_path / "off")
    monkeypatch.undo()
    pol.predictor.net.body[1] = torch.nn.GELU()
    with pytest.raises(ValueError, match="GELU is not a Linear layer .*numpy runtime cannot"):
        ex.export(pol, tmp_path / "gelu")
    assert not any(tmp_path.iterdir())


def test_numpy_runtime_combines_an_ensemble_as_its_model_and_refuses_a_bad_one():
    """The numpy network of an ensemble is every member combined head by head as torch's
    (a member alone differs); ``members`` out of range, an unknown or missing ``combine`` and a
    missing member's layer are named."""
    pol = esac_ensemble_policy()
    arrays = ex.network_arrays(pol)
    assert int(arrays["members"]) == 2 and list(arrays["combine"]) == [
        esac.ENSEMBLE_COMBINE[h] for h in (*esac.CLASS_HEADS, *esac.REG_HEADS)]
    x = np.random.default_rng(2).normal(size=(64, HISTORY * 7)).astype(np.float32)
    net = ex.NumpyNetwork(arrays)
    assert ex.max_difference(net(x), pol.predictor.backend(x))["max_ratio"] <= 1.0
    first = ex.NumpyNetwork({k: v for k, v in arrays.items() if k not in ("members", "combine")
                             and not k.startswith("m1_")} | {
        k[3:]: v for k, v in arrays.items() if k.startswith("m0_")})
    assert ex.max_difference(first(x), net(x))["max_ratio"] > 1.0
    for change, match in (({"members": np.array(40)}, "members = 40"),
                          ({"combine": np.array(["min"] * 6 + ["median"])}, "combine"),
                          ({"members": np.array(3)}, "has no 'm2_weight_0'")):
        with pytest.raises(ValueError, match=match):
            ex.NumpyNetwork({**arrays, **change})
    with pytest.raises(ValueError, match="has no 'combine'"):
        ex.NumpyNetwork({k: v for k, v in arrays.items() if k != "combine"})


@pytest.mark.parametrize("victim", ["model.onnx", "weights.npz"])
def test_a_changed_file_is_refused(exported, tmp_path, victim):
    import shutil

    d = tmp_path / "copy"
    shutil.copytree(exported["esac"][1], d)
    ex.load_exported(d, _env_layout())  # intact: loads
    data = bytearray((d / victim).read_bytes())
    data[len(data) // 2] ^= 0x01
    (d / victim).write_bytes(bytes(data))
    for backend in ("numpy", "onnx"):
        with pytest.raises(ValueError, match=f"{victim} does not match the checksum"):
            ex.load_exported(d, _env_layout(), backend)


def test_exported_runs_on_onnx_or_numpy_only(exported):
    d = exported["dqn-advantage"][1]
    with pytest.raises(ValueError, match="'onnx' or 'numpy'"):
        ex.load_exported(d, _env_layout(), "torch")
    pol = ex.load_exported(d, _env_layout(), "onnx")
    with pytest.raises(ValueError, match="without torch"):
        ex.with_backend(pol, "torch")
    assert isinstance(ex.with_backend(pol, "numpy").backend, ex.NumpyNetwork)
    with pytest.raises(ValueError, match="already exported"):
        ex.export(pol, d.parent / "again")


# ------------------------------------------------------------------------------------------
# saved models -> export -> a process without torch
# ------------------------------------------------------------------------------------------
_CHILD = """
import json, sys
import numpy as np
from pneugym.deploy.export import load_exported
d = sys.argv[1]
rec = np.load(d + "/episode.npz")
lay = json.load(open(d + "/env_layout.json"))
for name in ("esac", "ppo"):
    for backend in ("numpy", "onnx"):
        pol = load_exported(d + "/" + name, lay, backend)
        pol.begin_episodes([None] * rec["obs"].shape[1])
        acts = np.array([pol.predict(o)[0] for o in rec["obs"]])
        assert np.array_equal(acts, rec[name]), (name, backend)
bad = [m for m in ("torch", "stable_baselines3") if m in sys.modules]
assert not bad, bad
print("ok")
"""


def test_saved_models_run_exported_without_torch(tmp_path):
    """An ESAC model file and an SB3 zip, loaded by agents.registry, exported; a fresh process
    rebuilds both from the directories without importing torch or stable-baselines3 and takes
    the torch policies' decisions, step by step, through a whole batch of episodes."""
    from agents.registry import load_policy

    probe = CutOffVectorEnv(num_envs=1, observe_rig=True)
    e = esac_policy()
    meta = {"n_in": e.predictor.n_in, "hidden": [16], "layout": e.predictor.layout,
            "delay_input": False, "lookahead_s": [], "rule": {"margin": 0.05}}
    esac.save(tmp_path / "esac.pt", e.predictor.net, meta)
    p = ppo_policy("hazard", 0.6, asymmetric=True)
    p.model.pneugym_layout = p.full_layout
    p.model.pneugym_decision = p.decision
    p.model.save(tmp_path / "ppo.zip")
    pols = {"esac": load_policy(tmp_path / "esac.pt", probe),
            "ppo": load_policy(tmp_path / "ppo.zip", probe)}
    assert pols["ppo"].decision == {"rule": "hazard", "value": 0.6} and pols["ppo"]._pad == 3
    conds = [c for _, c in suite_episodes("nominal", episodes=3, seed=3)]
    rec: dict[str, list] = {"obs": [], "esac": [], "ppo": []}
    env = CutOffVectorEnv(num_envs=len(conds), autoreset=False, observe_rig=True)
    obs, _ = env.reset(seed=3, options={"conditions": conds})
    for pol in pols.values():
        pol.begin_episodes(conds)
    for _ in range(400):
        rec["obs"].append(obs.copy())
        for name, pol in pols.items():
            rec[name].append(pol.predict(obs)[0])
        obs, _, term, trunc, _ = env.step(rec["esac"][-1])
        if (term | trunc).all():
            break
    assert 0 < np.mean(rec["esac"]) < 1 and 0 < np.mean(rec["ppo"]) < 1
    for name, pol in pols.items():
        ex.export(pol, tmp_path / name)
    np.savez(tmp_path / "episode.npz", **{k: np.asarray(v) for k, v in rec.items()})
    (tmp_path / "env_layout.json").write_text(json.dumps(probe.observation_layout()))
    res = subprocess.run([sys.executable, "-c", _CHILD, str(tmp_path)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr[-2000:]


def test_an_exported_controller_keeps_its_training_conditions(tmp_path):
    import warnings

    from agents.registry import check_operating_point
    from agents.training import TrainingRangeWarning
    from pneugym.params import RigParams

    pol = esac_policy()
    pol.trained_preset, pol.trained_conditions = "randomized", {"load_mass_kg": [2.0, 40.0]}
    d = ex.export(pol, tmp_path / "c")["controller"].parent
    back = ex.load_exported(d, _env_layout())
    assert (back.training_space.supply_pressure_gauge_pa, back.training_space.load_mass_kg) == (
        (150_000.0, 500_000.0), (2.0, 40.0))
    env = CutOffVectorEnv(num_envs=1, history=HISTORY, observe_rig=True,
                          rig=RigParams().with_(supply_pressure_gauge_pa=600_000.0,
                                                load_mass_kg=35.0))
    with pytest.warns(TrainingRangeWarning, match=r"operating point lies outside .*\(supply 6 "
                                                  r"bar g outside 1.5-5\)"):
        check_operating_point(back, env)
    with warnings.catch_warnings():  # the thesis rig's 2.5 bar g and 10 kg: inside
        warnings.simplefilter("error", TrainingRangeWarning)
        check_operating_point(back, CutOffVectorEnv(num_envs=1, history=HISTORY,
                                                    observe_rig=True))
    meta = json.loads((d / "controller.json").read_text())
    meta["trained_conditions"] = [1, 2]
    (d / "controller.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="trained_conditions is \\[1, 2\\]; expected"):
        ex.load_exported(d, _env_layout())

"""agents/safe_load.py and the run.json readers: no code runs from a model file or a replay
buffer, and run.json names only files inside its run directory.

The crafted files carry a pickle whose ``__reduce__`` creates a marker file when unpickled: a
control test shows SB3's own ``load`` does run it, the others that pneugym's loaders never do."""
import base64
import io
import json
import os
import pickle
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from agents import safe_load, training
from agents.learned import LayoutMismatchError, RunFileError, read_run, run_member
from agents.registry import load_policy
from agents.training.checkpoints import load_checkpoint, restore_replay_buffer
from agents.training.sb3 import LatchedDQN, TrainingVecEnv
from pneugym.envs.cutoff import CutOffVectorEnv

TINY = {
    # lin_ makes learning_rate a callable: pickled in the file, replaced on load
    "ppo": ["env.num_envs=4", "env.history=3", "algo.n_steps=64", "algo.batch_size=128",
            "algo.n_epochs=1", "eval_every=256", "checkpoint_every=256", "validation.episodes=2",
            "algo.learning_rate=lin_0.001"],
    "dqn": ["env.num_envs=4", "env.history=3", "algo.learning_starts=100",
            "algo.buffer_size=2000", "algo.batch_size=32", "eval_every=256",
            "checkpoint_every=256", "validation.episodes=2", "save_replay_buffer=true"],
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("secruns")
    out = {}
    for algo in ("ppo", "dqn"):
        training.train(algo, root / algo, timesteps=256, seed=1, progress=False,
                       overrides=TINY[algo] + [f"cache_dir={root / 'cache'}"])
        out[algo] = root / algo
    return out


class _Marker:
    """Unpickling this creates ``path`` (what a malicious pickle could do instead)."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _payload(marker: Path) -> dict:
    return {":type:": "<class 'type'>",
            ":serialized:": base64.b64encode(pickle.dumps(_Marker(marker))).decode()}


def _rewrite(src: Path, dst: Path, edit) -> Path:
    """A copy of the SB3 zip ``src`` at ``dst`` with its ``data`` JSON changed by ``edit``."""
    with zipfile.ZipFile(src) as z:
        entries = {n: z.read(n) for n in z.namelist()}
    data = json.loads(entries["data"])
    edit(data)
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(dst, "w") as z:
        for n, b in entries.items():
            z.writestr(n, b)
    return dst


def _env(history=1):
    return CutOffVectorEnv(num_envs=1, history=history)


@pytest.fixture
def no_unpickling(monkeypatch):
    """Every pickle entry point raises while the test runs."""
    import cloudpickle

    def refuse(*args, **kwargs):
        raise AssertionError("something was unpickled")

    for mod in (pickle, cloudpickle):
        monkeypatch.setattr(mod, "loads", refuse)
        monkeypatch.setattr(mod, "load", refuse)

    class Refused(pickle.Unpickler):
        def __init__(self, *args, **kwargs):
            refuse()

    monkeypatch.setattr(pickle, "Unpickler", Refused)


# ------------------------------------------------------------------------------------------------
# genuine models load without unpickling anything
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("algo", ["ppo", "dqn"])
def test_genuine_trained_models_load_without_unpickling(runs, algo, no_unpickling):
    run = json.loads((runs[algo] / "run.json").read_text())
    serialized = {k for k, v in json.loads(zipfile.ZipFile(
        runs[algo] / run["model"]).read("data")).items() if safe_load.is_serialized(v)}
    assert {"policy_class", "observation_space", "action_space", "_last_obs"} <= serialized
    pol = load_policy(runs[algo], _env())  # history 3 model in a history 1 env
    a = pol.act(np.zeros((1, 7), dtype=np.float32))
    assert a.shape == (1,) and a[0] in (0, 1)
    if algo == "ppo":
        assert "learning_rate" in serialized  # the lin_ schedule was a pickled callable
        assert type(pol.model.policy).__name__ == "AsymmetricActorCriticPolicy"


def test_a2c_model_loads_without_unpickling(tmp_path, monkeypatch):
    from stable_baselines3 import A2C

    from pneugym.envs.sb3 import CutOffVecEnv

    model = A2C("MlpPolicy", CutOffVecEnv(num_envs=2), n_steps=4, device="cpu", seed=0)
    model.learn(16)
    model.save(tmp_path / "a2c.zip")
    obs = np.random.default_rng(0).uniform(-1, 1, (5, 7)).astype(np.float32)
    want, _ = model.predict(obs, deterministic=True)
    import cloudpickle
    monkeypatch.setattr(cloudpickle, "loads", lambda *a, **k: pytest.fail("unpickled"))
    loaded = safe_load.load_sb3(tmp_path / "a2c.zip")  # the algorithm told by the hyperparameters
    assert type(loaded).__name__ == "A2C"
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], want)


def _train_freq_unit(name):
    from stable_baselines3.common.type_aliases import TrainFrequencyUnit

    return TrainFrequencyUnit(name)


def test_resume_checkpoint_loads_without_unpickling(runs, no_unpickling):
    """The --resume path: a DQN checkpoint on its training environment, schedules from the config,
    and its replay buffer from plain arrays."""
    run = json.loads((runs["dqn"] / "run.json").read_text())
    venv = TrainingVecEnv(num_envs=4, history=3, preset="randomized")
    ckpt = runs["dqn"] / run["checkpoint"]
    model = load_checkpoint(LatchedDQN, "dqn", ckpt, venv, {"train_freq": [3, "step"]},
                            venv.observation_layout())
    assert model.num_timesteps == run["timesteps_done"]
    assert tuple(model.train_freq) == (3, _train_freq_unit("step"))
    assert type(model.replay_buffer).__name__ == "NStepReplayBuffer"  # rebuilt, as trained
    restore_replay_buffer(model, ckpt)
    assert model.replay_buffer.pos == run["timesteps_done"] // 4


# ------------------------------------------------------------------------------------------------
# crafted files: nothing runs
# ------------------------------------------------------------------------------------------------
def test_control_sb3_itself_runs_the_payload(runs, tmp_path):
    """The crafted file is a real attack on SB3's own loader (so the tests below can fail)."""
    from stable_baselines3 import PPO

    marker = tmp_path / "ran"
    f = _rewrite(runs["ppo"] / "best_model.zip", tmp_path / "evil.zip",
                 lambda d: d.update(evil=_payload(marker)))
    PPO.load(f, device="cpu")
    assert marker.exists()


def test_pickled_policy_class_is_replaced_not_run(runs, tmp_path):
    marker = tmp_path / "ran"
    d = tmp_path / "run"
    shutil.copytree(runs["ppo"], d)
    _rewrite(runs["ppo"] / "best_model.zip", d / "best_model.zip",
             lambda data: data.update(policy_class=_payload(marker)))
    pol = load_policy(d, _env())
    assert type(pol.model.policy).__name__ == "AsymmetricActorCriticPolicy"
    assert not marker.exists()


@pytest.mark.parametrize("key", ["evil", "policy_kwargs", "pneugym_layout"])
def test_unknown_pickled_entries_are_refused(runs, tmp_path, key):
    marker = tmp_path / "ran"

    def edit(data):
        if key == "pneugym_layout":  # nested in a plain entry: refused too
            data[key]["features"][0] = _payload(marker)
        else:
            data[key] = _payload(marker)

    f = _rewrite(runs["ppo"] / "best_model.zip", tmp_path / "m.zip", edit)
    with pytest.raises(safe_load.UnsafeModelError,
                       match=f"m.zip holds a pickled object under '{key}'; pneugym never "
                             f"unpickles model files"):
        load_policy(f, _env(3))
    assert not marker.exists()


def test_pickled_policy_kwargs_are_rebuilt_from_an_allowlist(runs, tmp_path):
    """A pickled policy_kwargs dict (an activation class, A2C's RMSprop) is rebuilt from the
    names SB3 writes beside the pickle, for a few known classes only; others are refused."""
    import torch

    marker = tmp_path / "ran"

    def activation(name):
        def edit(d):
            d["policy_kwargs"] = {**_payload(marker), ":type:": "<class 'dict'>",
                                  **d["policy_kwargs"], "activation_fn": name}
        return edit

    f = _rewrite(runs["ppo"] / "best_model.zip", tmp_path / "m.zip",
                 activation(str(torch.nn.Tanh)))
    assert safe_load.load_sb3(f, "ppo").policy.activation_fn is torch.nn.Tanh
    f = _rewrite(runs["ppo"] / "best_model.zip", tmp_path / "m.zip",
                 activation("<class 'posix.system'>"))
    with pytest.raises(safe_load.UnsafeModelError,
                       match="under 'policy_kwargs'.*activation_fn is <class 'posix.system'>"):
        safe_load.load_sb3(f, "ppo")
    assert not marker.exists()


def test_resume_refuses_a_crafted_checkpoint(runs, tmp_path):
    marker = tmp_path / "ran"
    d = tmp_path / "dqn"
    shutil.copytree(runs["dqn"], d)
    run = json.loads((d / "run.json").read_text())
    ck = d / run["checkpoint"]
    _rewrite(ck, ck, lambda data: data.update(evil=_payload(marker)))
    with pytest.raises(safe_load.UnsafeModelError, match="under 'evil'"):
        training.train("dqn", d, timesteps=512, seed=1, resume=True, progress=False,
                       overrides=TINY["dqn"] + [f"cache_dir={runs['dqn'].parent / 'cache'}"])
    assert not marker.exists()


def test_weights_holding_objects_are_refused(runs, tmp_path):
    """The ``.pth`` entries are read with ``torch.load(weights_only=True)``: an object is refused."""
    import torch

    marker = tmp_path / "ran"
    buf = io.BytesIO()
    torch.save({"x": _Marker(marker)}, buf)
    src = runs["ppo"] / "best_model.zip"
    with zipfile.ZipFile(src) as z:
        entries = {n: z.read(n) for n in z.namelist()}
    entries["policy.pth"] = buf.getvalue()
    with zipfile.ZipFile(tmp_path / "m.zip", "w") as z:
        for n, b in entries.items():
            z.writestr(n, b)
    with pytest.raises(safe_load.UnsafeModelError, match="m.zip: a weights file .* holds "
                                                         "Python objects"):
        safe_load.load_sb3(tmp_path / "m.zip", "ppo")
    assert not marker.exists()


def test_entries_sb3_never_saves_are_refused(runs, tmp_path):
    """A plain ``env`` would make SB3 build an environment by the name in the file."""
    f = _rewrite(runs["ppo"] / "best_model.zip", tmp_path / "m.zip",
                 lambda d: d.update(env="some.module:Env"))
    with pytest.raises(safe_load.UnsafeModelError, match=r"\['env'\].*never saves"):
        safe_load.load_sb3(f, "ppo")


# ------------------------------------------------------------------------------------------------
# spaces
# ------------------------------------------------------------------------------------------------
def test_wrong_observation_size_is_a_layout_error(runs, tmp_path):
    def shape(value):
        return lambda d: d["observation_space"].update(_shape=value)

    f = _rewrite(runs["dqn"] / "best_model.zip", tmp_path / "m.zip", shape([99]))
    with pytest.raises(LayoutMismatchError, match=r"_shape is \(99,\), but its recorded "
                                                  r"observation layout has size 21"):
        safe_load.load_sb3(f, "dqn")  # refused before any space or network is built

    def shape_only(d):  # no layout recorded: the weights tell
        d["observation_space"]["_shape"] = [99]
        d.pop("pneugym_layout")

    f = _rewrite(runs["dqn"] / "best_model.zip", tmp_path / "m.zip", shape_only)
    with pytest.raises(LayoutMismatchError, match="weights do not fit 99 observations"):
        safe_load.load_sb3(f, "dqn")
    # an unreadable size: the one pneugym recorded (21 = history 3 x 7) is used
    f = _rewrite(runs["dqn"] / "best_model.zip", tmp_path / "m.zip", shape("21"))
    assert safe_load.load_sb3(f, "dqn").observation_space.shape == (21,)

    def no_size(d):
        d["observation_space"].pop("_shape")
        d.pop("pneugym_layout")

    f = _rewrite(runs["dqn"] / "best_model.zip", tmp_path / "m.zip", no_size)
    with pytest.raises(LayoutMismatchError, match="do not fit 7 observations"):
        safe_load.load_sb3(f, "dqn", obs_size=7)  # the environment's size: wrong here


def test_other_action_spaces_are_refused(runs, tmp_path):
    f = _rewrite(runs["dqn"] / "best_model.zip", tmp_path / "m.zip",
                 lambda d: d["action_space"].update(n="3"))
    with pytest.raises(ValueError, match="action space has n = 3.*Discrete\\(2\\)"):
        safe_load.load_sb3(f, "dqn")


def test_not_a_model(tmp_path):
    z = tmp_path / "m.zip"
    with zipfile.ZipFile(z, "w") as f:
        f.writestr("data", "[1, 2]")
    with pytest.raises(ValueError, match="m.zip: its 'data' entry is a JSON list"):
        safe_load.load_sb3(z, "ppo")
    with zipfile.ZipFile(z, "w") as f:
        f.writestr("other", "x")
    with pytest.raises(ValueError, match="without the 'data' entry"):
        safe_load.load_sb3(z, "ppo")


# ------------------------------------------------------------------------------------------------
# replay buffers
# ------------------------------------------------------------------------------------------------
def test_replay_buffer_round_trip_and_checks(runs, tmp_path):
    venv = TrainingVecEnv(num_envs=4, history=3, preset="randomized")
    run = json.loads((runs["dqn"] / "run.json").read_text())
    ckpt = runs["dqn"] / run["checkpoint"]
    a = load_checkpoint(LatchedDQN, "dqn", ckpt, venv, {}, venv.observation_layout())
    b = load_checkpoint(LatchedDQN, "dqn", ckpt, venv, {}, venv.observation_layout())
    rng = np.random.default_rng(0)
    buf = a.replay_buffer
    for k in safe_load.REPLAY_ARRAYS:
        arr = getattr(buf, k)
        arr[...] = rng.integers(0, 2, arr.shape) if k == "actions" else rng.normal(size=arr.shape)
    buf.pos, buf.full = 7, True
    f = safe_load.save_replay_buffer(buf, tmp_path / "r.npz")
    n = safe_load.load_replay_buffer(b.replay_buffer, f)
    assert n == buf.buffer_size * 4 and b.replay_buffer.pos == 7 and b.replay_buffer.full
    for k in safe_load.REPLAY_ARRAYS:
        np.testing.assert_array_equal(getattr(b.replay_buffer, k), getattr(buf, k))
    # another buffer size: refused, naming what differs
    np.savez(tmp_path / "small.npz", pos=np.int64(0), full=np.bool_(False),
             **{k: getattr(buf, k)[:10] for k in safe_load.REPLAY_ARRAYS})
    with pytest.raises(ValueError, match=r"small.npz: observations is float32\[10, 4, 21\]"):
        safe_load.load_replay_buffer(b.replay_buffer, tmp_path / "small.npz")
    # object arrays (pickles inside the npz) are never read
    np.savez(tmp_path / "obj.npz", pos=np.int64(0), full=np.bool_(False),
             observations=np.array([_Marker(tmp_path / "ran")], dtype=object))
    with pytest.raises(ValueError, match="not a readable replay buffer"):
        safe_load.load_replay_buffer(b.replay_buffer, tmp_path / "obj.npz")
    assert not (tmp_path / "ran").exists()


def test_pickled_replay_buffer_needs_the_trust_flag(runs, tmp_path, capsys):
    venv = TrainingVecEnv(num_envs=4, history=3, preset="randomized")
    run = json.loads((runs["dqn"] / "run.json").read_text())
    ckpt = tmp_path / "ckpt_000000256.zip"
    shutil.copy(runs["dqn"] / run["checkpoint"], ckpt)
    model = load_checkpoint(LatchedDQN, "dqn", ckpt, venv, {}, venv.observation_layout())
    marker = tmp_path / "ran"
    (tmp_path / "replay_000000256.pkl").write_bytes(pickle.dumps(_Marker(marker)))
    restore_replay_buffer(model, ckpt)
    assert not marker.exists() and model.replay_buffer.pos == 0
    assert "--trust-pickled-replay-buffer" in capsys.readouterr().out
    with pytest.raises(AssertionError):  # trusted: unpickled (SB3 then finds no buffer in it)
        restore_replay_buffer(model, ckpt, trust_pickle=True)
    assert marker.exists()


# ------------------------------------------------------------------------------------------------
# run.json
# ------------------------------------------------------------------------------------------------
def _run_copy(runs, tmp_path, **changes) -> Path:
    d = tmp_path / "run"
    shutil.copytree(runs["ppo"], d)
    run = json.loads((d / "run.json").read_text())
    run.update(changes)
    (d / "run.json").write_text(json.dumps(run))
    return d


@pytest.mark.parametrize("name", ["../outside/best_model.zip", "/etc/passwd",
                                  "checkpoints/../../outside/best_model.zip", "C:\\m.zip"])
def test_run_json_paths_stay_inside_the_run(runs, tmp_path, name):
    (tmp_path / "outside").mkdir()
    shutil.copy(runs["ppo"] / "best_model.zip", tmp_path / "outside" / "best_model.zip")
    d = _run_copy(runs, tmp_path, model=name, checkpoint=name)
    with pytest.raises(RunFileError, match="outside the run directory"):
        load_policy(d, _env())
    with pytest.raises(RunFileError, match="'model'.*outside the run directory"):
        training.model_path(d)
    with pytest.raises(RunFileError, match="'checkpoint'.*outside the run directory"):
        training.train("ppo", d, timesteps=512, seed=1, resume=True, progress=False,
                       overrides=TINY["ppo"])


def test_symlinks_out_of_the_run_are_refused(runs, tmp_path):
    (tmp_path / "outside").mkdir()
    shutil.copy(runs["ppo"] / "best_model.zip", tmp_path / "outside" / "m.zip")
    d = _run_copy(runs, tmp_path, model="link.zip")
    os.symlink(tmp_path / "outside" / "m.zip", d / "link.zip")
    with pytest.raises(RunFileError, match="symbolic link"):
        load_policy(d, _env())
    os.symlink(tmp_path / "outside", d / "sub")
    with pytest.raises(RunFileError, match="symbolic link"):
        run_member(d, "sub/m.zip")
    # a link inside the run is fine
    os.symlink(d / "best_model.zip", d / "inner.zip")
    assert run_member(d, "inner.zip") == d / "inner.zip"


@pytest.mark.parametrize("text, match", [
    ("{not json", "is not valid JSON"),
    ("[1, 2]", "holds a JSON list, expected an object"),
    ('{"model": 5}', "'model' is 5; expected the name of a file"),
    ('{"model": "m.zip", "algo": ["ppo"]}', "'algo' is \\['ppo'\\]; expected a JSON str"),
    ('{"a": ' + "[" * 100_000, "its JSON is nested too deeply"),
    ('{"seed": 1' + "0" * 5000 + "}", "not a run record train.py wrote: Exceeds the limit"),
])
def test_malformed_run_json_is_named(tmp_path, text, match):
    (tmp_path / "run.json").write_text(text)
    with pytest.raises(RunFileError, match=f"{tmp_path / 'run.json'}.*{match}"):
        read_run(tmp_path)
    with pytest.raises(RunFileError, match=match):
        load_policy(tmp_path, _env())
    with pytest.raises(RunFileError, match=match):
        training.model_path(tmp_path)


# ------------------------------------------------------------------------------------------------
# malformed entries: a ValueError naming the file and the key, never a raw traceback
# ------------------------------------------------------------------------------------------------
def _serialized_pkw(extra):
    def edit(d):
        d["policy_kwargs"] = {":type:": "<class 'dict'>", ":serialized:": "gAR9lC4=",
                              **d["policy_kwargs"], **extra}
    return edit


@pytest.mark.parametrize("value", [{"a": 1}, [1], 5, None])
def test_unhashable_classes_in_pickled_policy_kwargs_are_refused(runs, tmp_path, value):
    f = _rewrite(runs["ppo"] / "best_model.zip", tmp_path / "m.zip",
                 _serialized_pkw({"activation_fn": value}))
    with pytest.raises(safe_load.UnsafeModelError, match=r"m.zip holds a pickled object under "
                                                         r"'policy_kwargs'.*its activation_fn is"):
        safe_load.load_sb3(f, "ppo")


@pytest.mark.parametrize("layout, match", [
    ("abc", r"pneugym_layout is 'abc'; expected an object"),
    ({}, r"pneugym_layout has no 'features'"),
    ({"features": "abc"}, r"pneugym_layout: features is 'abc'; expected a list"),
    ({"history": 0}, r"pneugym_layout: history is 0; expected an integer from 1 to 1000"),
    ({"history": -3}, r"history is -3"),
    ({"history": 2.5}, r"history is 2.5"),
    ({"size": "21"}, r"pneugym_layout: size is '21'; expected 21"),
    ({"size": 10 ** 9}, r"size is 1000000000; expected 21"),
    ({"control_period_s": "5ms"}, r"control_period_s is '5ms'"),
    ({"features": [{"name": "position", "scale": float("nan")}]},
     r"features\[0\] \('position'\).scale is nan"),
    ({"features": [{"name": "time", "scale": 4.0}]}, r"lack \['position', 'supply_cut'\]"),
])
def test_malformed_recorded_layouts_are_named(runs, tmp_path, layout, match):
    def edit(d):
        d["pneugym_layout"] = layout if not isinstance(layout, dict) or not layout else {
            **d["pneugym_layout"], **layout}

    f = _rewrite(runs["dqn"] / "best_model.zip", tmp_path / "m.zip", edit)
    with pytest.raises(LayoutMismatchError, match=f"m.zip: .*{match}"):
        load_policy(f, _env())


@pytest.mark.parametrize("algo, decision, match", [
    ("dqn", "argmax", r" is 'argmax'; expected an object"),
    ("dqn", [1], r" is \[1\]"),
    ("dqn", {"rule": "argmaxx"}, r"the decision rule is 'argmaxx'.*did you mean 'argmax'"),
    ("dqn", {"rule": "advantage", "value": "abc"}, r"the decision value is 'abc' for the "
                                                   r"advantage rule; expected a finite number"),
    ("dqn", {"rule": "advantage", "value": float("nan")}, r"the decision value is nan"),
    ("dqn", {"rule": "advantage", "value": [0.1, 0.2]}, r"the decision value is \[0.1, 0.2\]"),
    ("dqn", {"rule": "advantage"}, r"the advantage rule without a value"),
    ("dqn", {"rule": "quantile", "value": 0.5}, r"the quantile rule needs a stochastic policy"),
    ("dqn", {"rule": "advantage", "value": 0.1, "grid": [1]}, r"has \['grid'\]"),
    ("ppo", {"rule": "quantile", "value": 5}, r"the decision value is 5 for the quantile rule; "
                                              r"expected a probability in \(0, 1\]"),
    ("ppo", {"rule": "hazard", "value": 0}, r"the decision value is 0 for the hazard rule"),
    ("ppo", {"rule": "advantage", "value": 0}, r"the advantage rule needs a Q-network"),
])
def test_malformed_recorded_decisions_are_named(runs, tmp_path, algo, decision, match):
    f = _rewrite(runs[algo] / "best_model.zip", tmp_path / "m.zip",
                 lambda d: d.update(pneugym_decision=decision))
    with pytest.raises(ValueError, match=f"m.zip: pneugym_decision.*{match}"):
        load_policy(f, _env())


def test_data_json_beyond_the_parser_limits_names_the_file(runs, tmp_path):
    src = runs["ppo"] / "best_model.zip"
    with zipfile.ZipFile(src) as z:
        entries = {n: z.read(n) for n in z.namelist()}
    for name, data, match in (
            ("digits.zip", b'{"n_steps": 1' + b"0" * 5000 + b"}", "not the JSON of a "
             "stable-baselines3 model"),
            ("deep.zip", b'{"a": ' + b"[" * 100_000, "nested too deeply")):
        with zipfile.ZipFile(tmp_path / name, "w") as z:
            for n, b in entries.items():
                z.writestr(n, data if n == "data" else b)
        with pytest.raises(ValueError, match=f"{name}: its 'data' entry .*{match}"):
            safe_load.load_sb3(tmp_path / name, "ppo")


# ------------------------------------------------------------------------------------------------
# small files never make pneugym allocate much: sizes are checked before anything is built
# ------------------------------------------------------------------------------------------------
def _peak_mb(fn):
    import tracemalloc

    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak / 2 ** 20


def test_a_huge_observation_size_is_refused_before_a_space_is_built(runs, tmp_path):
    def no_layout(d):
        d["observation_space"]["_shape"] = [10 ** 9]
        d.pop("pneugym_layout")

    f = _rewrite(runs["dqn"] / "best_model.zip", tmp_path / "m.zip", no_layout)

    def load():
        with pytest.raises(LayoutMismatchError, match=r"_shape is \(1000000000,\), but the "
                                                      r"environment's observation has size 7"):
            load_policy(f, _env())
    assert _peak_mb(load) < 64
    with pytest.raises(ValueError, match=r"_shape is \(1000000000,\); the cut-off environment's "
                                         r"observations have at most 65536"):
        safe_load.load_sb3(f, "dqn")  # no environment to compare with: bounded anyway


def test_a_network_larger_than_its_weights_is_refused_before_it_is_built(runs, tmp_path):
    f = _rewrite(runs["ppo"] / "best_model.zip", tmp_path / "m.zip",
                 lambda d: d["policy_kwargs"].update(net_arch=[300_000, 300_000]))

    def load():
        with pytest.raises(ValueError, match=r"m.zip: its policy_kwargs \(net_arch \[300000, "
                                             r"300000\]\).*but policy.pth holds"):
            load_policy(f, _env())
    assert _peak_mb(load) < 64


def test_zip_entries_are_sized_before_they_are_read(runs, tmp_path, monkeypatch):
    src = runs["ppo"] / "best_model.zip"
    with zipfile.ZipFile(src) as z:
        entries = {n: z.read(n) for n in z.namelist()}
    # a data entry that inflates beyond 16 MB (here 20 MB of spaces in 20 kB)
    with zipfile.ZipFile(tmp_path / "big.zip", "w", zipfile.ZIP_DEFLATED) as z:
        for n, b in entries.items():
            z.writestr(n, b + b" " * (20 << 20) if n == "data" else b)
    assert (tmp_path / "big.zip").stat().st_size < 1 << 20

    def load():
        with pytest.raises(ValueError, match=r"big.zip: its entry 'data' inflates to 20,9\d\d,\d+ "
                                             r"bytes, more than the 16,777,216"):
            safe_load.load_sb3(tmp_path / "big.zip", "ppo")
    assert _peak_mb(load) < 16
    # an entry that inflates a thousandfold (a zip bomb), and too many entries
    with zipfile.ZipFile(tmp_path / "bomb.zip", "w", zipfile.ZIP_DEFLATED) as z:
        for n, b in entries.items():
            z.writestr(n, b)
        z.writestr("extra.bin", b"\0" * (40 << 20))
    monkeypatch.setattr(safe_load, "MAX_INFLATION", 100)
    with pytest.raises(ValueError, match=r"bomb.zip: its entry 'extra.bin' inflates .* "
                                         r"\(a zip bomb\)"):
        safe_load.load_sb3(tmp_path / "bomb.zip", "ppo")
    monkeypatch.setattr(safe_load, "MAX_ENTRIES", 3)
    with pytest.raises(ValueError, match=r"m.zip holds \d+ entries"):
        safe_load.load_sb3(shutil.copy(src, tmp_path / "m.zip"), "ppo")


def test_replay_buffers_get_the_umask_mode(tmp_path):
    """Like the checkpoints beside them (not mkstemp's 0600)."""
    from types import SimpleNamespace

    buf = SimpleNamespace(pos=0, full=False, **{k: np.zeros((4, 1, 3), np.float32)
                                                for k in safe_load.REPLAY_ARRAYS})
    f = safe_load.save_replay_buffer(buf, tmp_path / "replay_000000001.npz")
    mask = os.umask(0)
    os.umask(mask)
    assert f.stat().st_mode & 0o777 == 0o666 & ~mask
    assert [p.name for p in tmp_path.iterdir()] == [f.name]

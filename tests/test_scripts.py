"""train.py and evaluate.py at the top of a checkout: thin entry points to agents.training.cli and
agents.evaluation.cli, which ``pneugym train`` and ``pneugym evaluate`` call too. Their
``--help`` works, and importing the command lines loads neither torch nor stable-baselines3."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("script, expect", [
    ("train.py", ["--algo", "--out", "--seed", "--no-progress", "--resume", "--force",
                  "examples:", "pneugym train --algo ppo", "python train.py --algo ppo"]),
    ("evaluate.py", ["--policies", "--out", "--seed", "--no-progress", "--suite", "examples:",
                     "pneugym evaluate --policies", "python evaluate.py --policies"]),
])
def test_scripts_help(tmp_path, script, expect):
    out = subprocess.run([sys.executable, str(ROOT / script), "--help"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    for text in expect:
        assert text in out.stdout, text


def test_command_lines_import_light():
    code = ("import sys, agents.training, agents.training.cli, agents.evaluation.cli; "
            "print(sorted(m for m in ('torch', 'stable_baselines3') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_main_takes_argv_and_returns_the_result(capsys):
    """What ``pneugym <command>`` relies on: ``main(argv)`` parses ``argv``, not sys.argv."""
    from agents.evaluation.cli import main as evaluate_main
    from agents.training.cli import main as train_main

    for main in (train_main, evaluate_main):
        with pytest.raises(SystemExit) as exc:
            main(["--help"])
        assert exc.value.code == 0
    assert "--no-progress" in capsys.readouterr().out

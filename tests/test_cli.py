"""pneugym/cli.py: the ``pneugym`` command dispatches to every job's own command line."""
from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from pneugym import cli


def test_help_lists_every_command(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in cli.COMMANDS:
        assert f"  {name}" in out
    assert cli.main([]) == 0


def test_version(capsys):
    import pneugym

    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"pneugym {pneugym.__version__}"


def test_unknown_command_is_refused_with_the_nearest(capsys):
    assert cli.main(["evalute"]) == 2
    assert "did you mean 'evaluate'" in capsys.readouterr().err


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_each_command_has_help_with_examples_under_its_pneugym_name(name, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main([name, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: pneugym {name}")
    assert "examples:" in out
    assert sys.argv[0] != f"pneugym {name}"  # restored


def test_the_command_sees_its_own_argv(monkeypatch):
    import types

    seen = {}
    fake = types.SimpleNamespace(main=lambda argv: seen.update(argv=list(argv), sys=list(sys.argv)) or 3)
    monkeypatch.setitem(sys.modules, "agents.fake_cli", fake)
    monkeypatch.setitem(cli.COMMANDS, "fake", ("agents.fake_cli", "a test command"))
    assert cli.main(["fake", "--x", "1"]) == 3
    assert seen == {"argv": ["--x", "1"], "sys": ["pneugym fake", "--x", "1"]}


def test_a_command_error_is_exit_status_2(capsys, tmp_path):
    f = tmp_path / "file"
    f.write_text("")
    with pytest.raises(SystemExit) as exc:
        cli.main(["validate", "--out", str(f)])
    assert exc.value.code == 2


@pytest.mark.skipif(shutil.which("pneugym") is None, reason="the console script is not installed")
def test_the_console_script_is_installed():
    res = subprocess.run(["pneugym", "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "commands:" in res.stdout

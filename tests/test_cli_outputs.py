"""Commands check their outputs before the work: a path that cannot be written fails at once
(exit status 2 and a message), without running the sweep, fit or report."""
from __future__ import annotations

import pytest

from agents import gaslaw
from pneugym import calibrate, validate


def _no_work(*args, **kwargs):
    raise AssertionError("the work started before the output path was checked")


@pytest.mark.parametrize("command,work,argv", [
    (gaslaw.main, (gaslaw, "calibrate"), ["--out", "{dir}"]),
    (gaslaw.main, (gaslaw, "calibrate"), ["--out", "{dir}/k.json", "--plot", "{dir}"]),
    (gaslaw.main, (gaslaw, "calibrate"), ["--out", ""]),
    (calibrate.main, (calibrate, "calibrate"), ["--out", "{dir}"]),
    (validate.main, (validate, "build_report"), ["--json", "{dir}", "--plots", "{dir}"]),
    (validate.main, (validate, "build_report"), ["--json", "{dir}/r.json", "--plots", "{file}"]),
])
def test_unusable_outputs_fail_before_the_work(tmp_path, monkeypatch, capsys, command, work, argv):
    monkeypatch.setattr(*work, _no_work)
    (tmp_path / "file").write_text("")
    args = [a.format(dir=tmp_path, file=tmp_path / "file") for a in argv]
    with pytest.raises(SystemExit) as exc:
        command(args)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "is a folder" in err or "not a folder" in err or "empty" in err

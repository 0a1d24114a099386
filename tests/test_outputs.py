"""pneugym/outputs.py: output folders checked before work, atomic writes, file sets written whole."""
from __future__ import annotations

import os
import stat

import pytest

from pneugym.outputs import (
    OutputError, atomic_write_json, atomic_write_text, check_output_dir, check_output_file,
    staged_files,
)


def test_check_output_dir_creates_and_refuses(tmp_path):
    assert check_output_dir(tmp_path / "a" / "b").is_dir()
    f = tmp_path / "file"
    f.write_text("")
    with pytest.raises(OutputError, match="exists and is not a folder"):
        check_output_dir(f)
    with pytest.raises(OutputError, match="cannot be written"):
        check_output_dir(f / "sub")
    for empty in ("", "  "):
        with pytest.raises(OutputError, match="empty"):
            check_output_dir(empty, "--out")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_check_output_dir_refuses_a_read_only_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OutputError, match="cannot be written"):
            check_output_dir(ro)
    finally:
        ro.chmod(0o700)


def test_check_output_file_refuses_a_folder_and_an_empty_path(tmp_path):
    with pytest.raises(OutputError, match="is a folder"):
        check_output_file(tmp_path, "--out")
    with pytest.raises(OutputError, match="empty"):
        check_output_file("", "--out")
    p = check_output_file(tmp_path / "new" / "x.json")
    assert p.parent.is_dir() and not p.exists()


def test_atomic_writes_replace_whole_files_with_the_umask_mode(tmp_path):
    p = atomic_write_json(tmp_path / "r.json", {"a": 1})
    assert p.read_text() == '{\n "a": 1\n}\n'
    atomic_write_text(p, "new")
    assert p.read_text() == "new"
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~mask
    assert [q.name for q in tmp_path.iterdir()] == ["r.json"]  # no temporary file left
    with pytest.raises(ValueError):
        atomic_write_json(p, {"a": float("nan")})
    assert p.read_text() == "new"


def test_staged_files_replace_the_set_only_when_all_is_written(tmp_path):
    (tmp_path / "a.txt").write_text("old a")
    (tmp_path / "b.txt").write_text("old b")
    with pytest.raises(RuntimeError):
        with staged_files(tmp_path) as st:
            (st / "a.txt").write_text("new a")
            raise RuntimeError("disk full")
    assert (tmp_path / "a.txt").read_text() == "old a"
    with staged_files(tmp_path) as st:
        (st / "a.txt").write_text("new a")
        (st / "b.txt").write_text("new b")
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == {"a.txt": "new a",
                                                                  "b.txt": "new b"}


def test_staged_files_remove_what_the_set_owns_and_did_not_write_again(tmp_path):
    """An evaluation's plots of a suite not run again go with the set they belonged to; other
    files stay (a user's own, or ones the pattern does not name)."""
    from agents.evaluation.outputs import OWNED

    for name in ("results.json", "robustness_heatmaps.png", "transfer_saving_vs_time.png",
                 "mine.png", "notes.md"):
        (tmp_path / name).write_text("old")
    with staged_files(tmp_path, replaces=OWNED) as st:
        (st / "results.json").write_text("new")
        (st / "nominal_saving_vs_time.png").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "mine.png", "nominal_saving_vs_time.png", "notes.md", "results.json"]
    with pytest.raises(RuntimeError):  # a failed set removes nothing
        with staged_files(tmp_path, replaces=OWNED) as st:
            raise RuntimeError("disk full")
    assert (tmp_path / "nominal_saving_vs_time.png").exists()


def test_staged_files_check_every_target_before_moving_any(tmp_path):
    """A folder where a result file goes must not leave half a set (results.csv moved, then
    results.json failing)."""
    (tmp_path / "results.csv").write_text("old csv")
    (tmp_path / "results.json").mkdir()
    with pytest.raises(OutputError, match="in the way; nothing in"):
        with staged_files(tmp_path) as st:
            (st / "results.csv").write_text("new csv")
            (st / "results.json").write_text("{}")
    assert (tmp_path / "results.csv").read_text() == "old csv"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".staging")]

"""Docs that cannot rot: every fenced code block of README.md and docs/*.md runs here.

Per page, blocks run in document order in one scratch folder (holding links to the repository's
``configs/``, ``train.py``, ``evaluate.py`` and ``benchmarks/``), python blocks in one namespace:

- ```` ```python ```` blocks are executed;
- ```` ```bash ```` blocks run line by line in a shell (``set -e``), ``#`` comments and empty lines
  skipped, a trailing ``\\`` joining lines. A comment right before a block,
  ``<!-- test: NAME="extra args" ... -->``, appends the extra arguments to every command whose
  program is NAME (``train``, ``evaluate``, ``discrepancy``, ``validate``, ``calibrate``,
  ``gaslaw``, ``bench_plant``, ...): the page shows the real command, the test runs it on a small
  budget. For a ```` ```python ```` block, ``<!-- test: swap="TEXT => SMALLER" -->`` runs it with
  ``TEXT`` (which must be there) replaced by ``SMALLER``, e.g. a fit's options on a small budget
  (several swaps separated by ``;;``). ``<!-- test: skip="why" -->`` skips a block: only for
  installing, which CI does itself;
- other blocks (```` ```text ````, ```` ```json ````, tables) are output and are not run.

``PNEUGYM_DOCS_ONLY=page.md`` runs one page.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ONE_THREAD

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("**/*.md"))]
LINKED = ("configs", "train.py", "evaluate.py", "benchmarks", "calibration")
FENCE = re.compile(r"(?:<!--\s*test:(?P<opts>.*?)-->\s*\n)?```(?P<lang>[\w-]*)[^\n]*\n(?P<code>.*?)```",
                   re.S)
#: a command's program name, as the extra arguments of ``<!-- test: -->`` address it
PROGRAM = re.compile(r"^(?:pneugym\s+(?P<sub>[\w-]+)|python\s+(?:-m\s+(?P<mod>[\w.]+)|"
                     r"(?P<script>[\w/.-]+\.py)))")


def blocks(page: Path) -> list[tuple[str, str, dict[str, str]]]:
    """``(language, code, test options)`` of every fenced block of ``page``."""
    out = []
    for m in FENCE.finditer(page.read_text(encoding="utf-8")):
        opts = dict(re.findall(r'(\w+)="([^"]*)"', m.group("opts") or ""))
        out.append((m.group("lang").lower(), m.group("code"), opts))
    return out


def program(command: str) -> str | None:
    """``train`` for ``pneugym train ...``, ``python train.py ...`` or ``python -m ...train``."""
    m = PROGRAM.match(command)
    if not m:
        return None
    name = m.group("sub") or m.group("mod") or m.group("script")
    name = name.rsplit("/", 1)[-1].removesuffix(".py").removesuffix(".__main__")
    return name.rsplit(".", 1)[-1]


def commands(code: str) -> list[str]:
    """The command lines of a shell block (continuations joined, comments dropped)."""
    lines, parts = [], []
    for raw in code.splitlines():
        line = "" if raw.lstrip().startswith("#") else raw.split(" #", 1)[0].strip()
        if line.endswith("\\"):
            parts.append(line[:-1].strip())
            continue
        parts.append(line)
        cmd = " ".join(p for p in parts if p)
        if cmd:
            lines.append(cmd)
        parts = []
    return lines


def swapped(code: str, swaps: str, where: str) -> str:
    """``code`` with every ``TEXT => SMALLER`` of ``swaps`` (``;;``-separated) applied; a
    ``TEXT`` the code no longer holds is an error, so the swap cannot silently stop applying."""
    for swap in filter(None, (w.strip() for w in swaps.split(";;"))):
        old, sep, new = (x.strip() for x in swap.partition("=>"))
        assert sep and old in code, f"{where}: swap {swap!r} does not apply to the code"
        code = code.replace(old, new)
    return code


def run_shell(code: str, opts: dict[str, str], cwd: Path) -> None:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "MPLBACKEND": "Agg", **ONE_THREAD}
    bindir = Path(sys.executable).parent
    env["PATH"] = f"{bindir}{os.pathsep}{env['PATH']}"
    for cmd in commands(code):
        extra = opts.get(program(cmd) or "", "")
        full = f"{cmd} {extra}".strip()
        if full.startswith("python "):
            full = shlex.quote(sys.executable) + full[len("python"):]
        res = subprocess.run(full, shell=True, cwd=cwd, env=env, capture_output=True, text=True,
                             timeout=600)
        assert res.returncode == 0, (f"`{full}` failed ({res.returncode}):\n"
                                     f"{res.stdout[-3000:]}\n{res.stderr[-3000:]}")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_fence_of_the_page_is_seen(page):
    """A fence the harness does not pair (three backticks in prose, an unclosed block) would
    silently leave a block untested: every line that opens or closes a fence must be one of
    the parsed blocks' fences."""
    fences = [ln for ln in page.read_text(encoding="utf-8").splitlines()
              if ln.lstrip().startswith("```")]
    assert len(fences) == 2 * len(blocks(page)), (
        f"{page.name}: {len(fences)} fence lines but {len(blocks(page))} blocks parsed")


def page_id(page: Path) -> str:
    return str(page.relative_to(ROOT))


@pytest.mark.parametrize("page", PAGES, ids=page_id)
def test_every_code_block_of_the_page_runs(page, tmp_path, monkeypatch):
    only = os.environ.get("PNEUGYM_DOCS_ONLY")
    if only and page.name != only:
        pytest.skip(f"PNEUGYM_DOCS_ONLY={only}")
    for name in LINKED:
        (tmp_path / name).symlink_to(ROOT / name)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    namespace: dict = {"__name__": "__docs__"}
    for k, (lang, code, opts) in enumerate(blocks(page)):
        if "skip" in opts:
            assert "install" in opts["skip"], f"{page_id(page)} block {k}: only installs may skip"
            continue
        if lang == "python":
            code = swapped(code, opts.get("swap", ""), f"{page_id(page)} block {k}")
            try:
                exec(compile(code, f"{page_id(page)}[block {k}]", "exec"), namespace)
            except Exception as exc:
                raise AssertionError(f"{page_id(page)} block {k} failed: {exc!r}\n{code}") from exc
        elif lang in ("bash", "sh", "shell", "console"):
            run_shell(code, opts, tmp_path)


def test_the_harness_parses_options_programs_and_continuations():
    text = ('<!-- test: train="--timesteps 8" -->\n```bash\npneugym train --algo ppo \\\n'
            '  --out runs/ppo   # a comment\n# only a comment\n```\n```python\nx = 1\n```\n')
    page = Path(os.environ.get("TMPDIR", "/tmp")) / "pneugym-docs-harness.md"
    page.write_text(text)
    try:
        (lang, code, opts), (lang2, _, opts2) = blocks(page)
    finally:
        page.unlink()
    assert (lang, opts, lang2, opts2) == ("bash", {"train": "--timesteps 8"}, "python", {})
    assert commands(code) == ["pneugym train --algo ppo --out runs/ppo"]
    assert swapped("fit(a, n=4)", "n=4 => n=1;; fit( => go(", "x") == "go(a, n=1)"
    with pytest.raises(AssertionError, match="does not apply"):
        swapped("fit(a)", "n=4 => n=1", "x")
    assert [program(c) for c in ("pneugym train --algo ppo", "python train.py", "python -m "
            "pneugym.discrepancy x", "python benchmarks/bench_plant.py --quick", "ls")] == \
        ["train", "train", "discrepancy", "bench_plant", None]

"""The validation report: schema of the JSON, analytic rows pass, plots are written."""
import json

import pytest

from pneugym import validate


def test_report_json_schema_and_analytic_rows(tmp_path):
    out = tmp_path / "report.json"
    assert validate.main(["--json", str(out), "--plots", str(tmp_path)]) == 0
    rep = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON {c}"))
    rows = rep["rows"]
    for r in rows:
        assert {"quantity", "simulated", "reference", "tolerance", "unit", "passed"} <= set(r)
    analytic = [r for r in rows if r["group"] == "analytic"]
    assert len(analytic) >= 7 and all(r["passed"] for r in analytic)
    # the thesis's published figures (stroke times, savings, breakaway, the line experiment) and
    # the standard cylinders' rows: each one with a tolerance passes (the others are for
    # information)
    thesis = [r for r in rows if r["group"].startswith("thesis")]
    assert sum(r["passed"] is True for r in thesis) >= 10
    assert not [r["quantity"] for r in rows if r["passed"] is False]
    assert {"versions", "git_commit"} <= set(rep["provenance"])
    for name in ("thesis_strokes.png", "line_experiment.png", "convergence.png", "analytic.png"):
        assert (tmp_path / name).stat().st_size > 10_000


def test_row_tolerance_logic():
    assert validate.Row("g", "q", 1.1, 1.0, 0.15, "s", relative=True).passed
    assert not validate.Row("g", "q", 1.2, 1.0, 0.15, "s", relative=True).passed
    assert validate.Row("g", "q", 45.0, 40.1, 10.0, "%").passed
    assert validate.Row("g", "q", 1.0, 2.0, None, "s").passed is None

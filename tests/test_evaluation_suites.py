"""agents.evaluation.suites: the issue's condition grid, seeded episodes."""
import pytest

from agents.evaluation.suites import suite_cells, suite_episodes


def test_suites_cover_the_issue_grid():
    rob = dict(suite_cells("robustness"))
    for m in (5, 10, 15, 20, 30):
        for b in (1.5, 2, 2.5, 3, 4, 5):
            assert f"{b:g}bar-{m:g}kg" in rob
    assert any("dip" in k for k in rob) and any("friction" in k for k in rob)
    assert any("valve-delay" in k for k in rob)
    assert [lab for lab, _ in suite_cells("nominal")] == ["1.5bar-10kg", "2.5bar-10kg"]
    with pytest.raises(ValueError, match="unknown suite"):
        suite_cells("nope")


def test_episodes_are_seeded_and_distinct():
    a = suite_episodes("robustness", 2, 1_000_000)
    b = suite_episodes("robustness", 2, 1_000_000)
    c = suite_episodes("robustness", 2, 1_000_001)
    assert a == b
    dips_a = [cond.dip for lab, cond in a if "dip" in lab]
    dips_c = [cond.dip for lab, cond in c if "dip" in lab]
    assert dips_a != dips_c and all(cond.dip_depth >= 0.1 for cond in [x[1] for x in a
                                                                       if "dip" in x[0]])

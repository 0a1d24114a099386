"""A rig's operating life: thousands of consecutive strokes while the rig's hidden truth drifts
(:mod:`~pneugym.operation.scenarios`), every stroke recorded in DuckDB
(:mod:`~pneugym.operation.record`), run by a frozen or an adapting controller
(:mod:`agents.adaptive`) in :func:`~pneugym.operation.run.operate`, and reported per hour and per
shift against a conventional controller and the drift-aware oracle
(:mod:`~pneugym.operation.report`).

    python -m pneugym.operation --scenario wear --policy esac=runs/esac --strokes 5000 \\
        --db ops.duckdb
"""
from .scenarios import SCENARIOS, Scenario, scenario

__all__ = ["SCENARIOS", "Scenario", "scenario"]

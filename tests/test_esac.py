"""agents/esac/__init__.py: the package re-exports every name of the former agents/esac.py, and its
modules import one another one way only (tests of each module: tests/test_esac_<module>.py)."""
import ast
from pathlib import Path

from agents import esac

#: each module of the package and the package modules it may import
ALLOWED = {"data": set(), "model": set(), "rule": set(), "modelfile": {"model", "rule"},
           "report": {"model"}, "policy": {"model", "modelfile", "rule"}}


def test_public_names_are_reexported():
    from agents.esac import data, model, modelfile, policy, report, rule

    for name in esac.__all__:
        assert hasattr(esac, name), name
    assert esac.rollouts is data.rollouts and esac.LAGS is data.LAGS
    assert esac.ESACPredictor is model.ESACPredictor and esac.load is modelfile.load
    assert esac.ESACPolicy is policy.ESACPolicy and esac.accuracy is report.accuracy
    assert esac.check_rule is rule.check_rule


def test_modules_import_one_way():
    root = Path(esac.__file__).parent
    assert {p.stem for p in root.glob("*.py")} - {"__init__"} == set(ALLOWED)
    for stem, allowed in ALLOWED.items():
        tree = ast.parse((root / f"{stem}.py").read_text(encoding="utf-8"))
        used = {n.module for n in ast.walk(tree)
                if isinstance(n, ast.ImportFrom) and n.level == 1 and n.module}
        assert used <= allowed, (stem, used - allowed)

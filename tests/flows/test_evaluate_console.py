"""``tumor3d evaluate``'s console table and ``--evaluation`` help come from the registry.

Issue 31 item 4: a registered evaluation's declared console columns (label, format) are
the table's, and the help lists the registered evaluations' names.
"""

from __future__ import annotations

import io

import pandas as pd
import pytest
from rich.console import Console
from typer.testing import CliRunner

from tumor3d.evaluation import EvaluationRows, registered_evaluations
from tumor3d.evaluation.registry import ReportColumn, ReportColumns, register_evaluation
from tumor3d.flows.cli.evaluate import _evaluation_help, _evaluation_table

BASE = {"config": "default", "patient_id": "p1", "status": "ok", "run_status": "ok"}


@pytest.fixture
def fake(monkeypatch):
    """A fake evaluation registered for one test (in a copy of the registry)."""
    import tumor3d.evaluation.registry as registry

    registered_evaluations()  # the built-in ones first, into the registry kept
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    columns = ReportColumns(console=(ReportColumn("fake score", ("fake_score",), "{:.2f} pts"),))

    @register_evaluation("unit-fake", description="scores", default=False, columns=columns)
    def score(case):  # pragma: no cover - never run
        return EvaluationRows()

    return registered_evaluations()["unit-fake"]


def _shown(df, evaluations=None) -> str:
    buf = io.StringIO()
    Console(file=buf, width=150).print(_evaluation_table(df, evaluations))
    return buf.getvalue()


def test_a_registered_evaluations_console_columns_are_the_tables(fake):
    df = pd.DataFrame([{**BASE, "fake_score": 1.5, "dice_3d": 0.9},
                       {**BASE, "patient_id": "p2", "fake_score": None}])  # fmt: skip
    text = _shown(df, {"unit-fake": fake})
    assert "fake score" in text and "1.50 pts" in text
    assert "3-D Dice" not in text  # not the segmentation's: it was not asked for
    assert any("p2" in line and line.rstrip("│ ").endswith("-") for line in text.splitlines())
    # by default every registered evaluation's, in the registry's order
    text = _shown(df)
    assert text.index("3-D Dice") < text.index("fake score") and "0.900" in text


def test_a_console_column_without_values_is_left_out(fake):
    text = _shown(pd.DataFrame([{**BASE, "fake_score": float("nan")}]), {"unit-fake": fake})
    assert "p1" in text and "fake score" not in text


def test_the_evaluation_help_lists_the_registered_names(fake):
    # the default ones first, then by name (not in the order their modules were imported)
    assert _evaluation_help().partition(": ")[2] == (
        "segmentation (the default), interpolation, simplification, unit-fake."
    )
    from tumor3d.flows.cli import app

    r = CliRunner().invoke(app, ["evaluate", "--help"], terminal_width=200, max_content_width=200)
    assert r.exit_code == 0 and "unit-fake" in r.output, r.output
    assert "segmentation (the default), interpolation, simplification, unit-fake." in r.output

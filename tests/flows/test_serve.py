"""Scheduled reprocessing: the deployment's schedule and parameters, and what a run recomputes.

The deployment object is built without serving (``cohort_deployment``); a
run triggered through the Prefect API after a patient is added to the manifest
is executed the way Prefect's runner executes it (``python -m prefect.engine``
with the flow run's id: the flow is loaded from the deployment's entrypoint
and parameters) and computes only the new patient. A patient dropped from the
manifest is reported, its folder kept.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pandas as pd
import pytest
from phantom_rows import small_phantom_rows

from tumor3d.errors import InputError
from tumor3d.flows.serve import cohort_deployment, scheduled_cohort_flow
from tumor3d.storage.manifest import write_manifest
from tumor3d.tasks.stages import STAGES


def _row(seed: int, folder):
    return small_phantom_rows(folder, [seed], "srv")[0]


def test_deployment_carries_the_cron_schedule_and_parameters(tmp_path):
    manifest = write_manifest([_row(0, tmp_path)], tmp_path / "m.csv")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("simplify: {reduction_percent: 50}\n")
    dep = cohort_deployment(
        manifest, tmp_path / "out", cron="0 2 * * *", name="nightly", config_path=cfg, workers=3
    )
    assert dep.name == "nightly"
    assert [s.schedule.cron for s in dep.schedules] == ["0 2 * * *"]
    assert dep.schedules[0].schedule.timezone == "UTC"
    assert dep.parameters == {
        "manifest": str(manifest.resolve()),
        "out_dir": str((tmp_path / "out").resolve()),
        "config_path": str(cfg.resolve()),
        "workers": 3,
        "store_dir": None,
        "dask_address": None,
        "dask_workers": None,
    }
    assert dep.entrypoint == "tumor3d.flows.serve.scheduled_cohort_flow"
    assert dep.flow_name == "tumor3d-scheduled-cohort"


def test_deployment_refuses_a_bad_cron_or_a_missing_manifest(tmp_path):
    manifest = write_manifest([_row(0, tmp_path)], tmp_path / "m.csv")
    with pytest.raises(InputError, match="invalid --cron '61 2 \\* \\* \\*'"):
        cohort_deployment(manifest, tmp_path / "out", cron="61 2 * * *")
    with pytest.raises(InputError, match="absent.csv"):
        cohort_deployment(tmp_path / "absent.csv", tmp_path / "out", cron="0 2 * * *")


def _trigger_and_execute(dep) -> None:
    """Register the deployment, create a run through the API, execute it like a runner."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL

    deployment_id = dep.apply()
    with get_client(sync_client=True) as client:
        flow_run = client.create_flow_run_from_deployment(deployment_id)
    env = {**os.environ, "PREFECT__FLOW_RUN_ID": str(flow_run.id),
           "PREFECT_API_URL": PREFECT_API_URL.value()}  # fmt: skip
    proc = subprocess.run(
        [sys.executable, "-m", "prefect.engine"], env=env, capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    with get_client(sync_client=True) as client:
        state = client.read_flow_run(flow_run.id).state
    assert state is not None and state.is_completed(), state


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_triggered_run_computes_only_the_added_patient_and_reports_removed(tmp_path):
    inputs, out = tmp_path / "in", tmp_path / "out"
    rows = [_row(0, inputs), _row(1, inputs)]
    manifest = write_manifest(rows, tmp_path / "manifest.csv")
    dep = cohort_deployment(manifest, out, cron="0 2 * * *", workers=1)

    first = scheduled_cohort_flow(**dep.parameters)
    assert [p.status for p in first.patients] == ["ok", "ok"]
    assert not any(s.cached for p in first.patients for s in p.stages)

    # a patient is added to the manifest; the scheduled run re-reads it
    write_manifest([*rows, _row(2, inputs)], manifest)
    _trigger_and_execute(dep)
    table = pd.read_parquet(out / "cohort.parquet").set_index("patient_id")
    cached = [f"cached_{s.replace('-', '_')}" for s in STAGES]
    assert list(table.index) == ["srv0", "srv1", "srv2"]
    assert (table["status"] == "ok").all()
    assert table.loc[["srv0", "srv1"], cached].astype(bool).all(axis=None)
    assert not table.loc["srv2", cached].astype(bool).any()
    for pid in ("srv0", "srv1"):  # same numbers as the run that computed them
        before = next(p for p in first.patients if p.patient_id == pid)
        assert table.loc[pid, "volume_eq7_mm3"] == before.metrics["volume_eq7_mm3"]

    # a patient is removed: reported, its published folder kept
    write_manifest([rows[1]], manifest)
    third = scheduled_cohort_flow(**dep.parameters)
    assert [p.patient_id for p in third.patients] == ["srv1"]
    assert third.removed == ["srv0", "srv2"]
    assert (out / "srv0" / "metrics.parquet").is_file()
    md = (out / "cohort.md").read_text()
    assert "## Removed from the manifest" in md and "srv0, srv2" in md
    page = (out / "cohort.html").read_text()  # the page too (it had only the kept rows)
    assert "<h2>Removed from the manifest</h2>" in page and "kept (not deleted): srv0, srv2" in page


def test_cli_serve_builds_the_deployment_and_hands_it_to_prefect(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import tumor3d.flows.serve
    from tumor3d.flows.cli import app

    manifest = write_manifest([_row(0, tmp_path)], tmp_path / "m.csv")
    served = []
    monkeypatch.setattr(tumor3d.flows.serve, "serve_cohort", served.append)
    args = ["serve", str(manifest), "--out", str(tmp_path / "o"), "--name", "n1"]
    ok = CliRunner().invoke(app, [*args, "--cron", "30 1 * * 1-5", "--workers", "2"])
    assert ok.exit_code == 0, ok.output
    assert [d.name for d in served] == ["n1"]
    assert served[0].schedules[0].schedule.cron == "30 1 * * 1-5"
    assert served[0].parameters["workers"] == 2
    bad = CliRunner().invoke(app, [*args, "--cron", "every night"])
    assert bad.exit_code == 2 and "invalid --cron" in bad.output and len(served) == 1


@pytest.mark.parametrize(
    ("cron", "reason"),
    [
        ("61 99 * * *", "minute 61 is outside 0-59"),
        ("0 24 * * *", "hour 24 is outside 0-23"),
        ("0 2 * 13 *", "month 13 is outside 1-12"),
        ("0 2 * *", "has 5 fields"),
    ],
)
def test_a_bad_cron_says_why_in_one_line_without_a_pydantic_url(tmp_path, cron, reason):
    """Issue 29: the error dropped the reason and printed a pydantic URL."""
    manifest = write_manifest([_row(0, tmp_path)], tmp_path / "m.csv")
    with pytest.raises(InputError) as exc:
        cohort_deployment(manifest, tmp_path / "out", cron=cron)
    text = str(exc.value)
    assert reason in text and "\n" not in text
    assert "pydantic" not in text and "http" not in text


def test_a_bad_time_zone_is_named_and_a_row_not_there_yet_is_accepted(tmp_path):
    """--timezone is named for a bad time zone (it was blamed on the cron), and a manifest
    row whose image has not arrived is accepted as ``cohort`` accepts it (serve refused
    the whole manifest; a scheduled run fails that row alone)."""
    manifest = write_manifest([_row(0, tmp_path)], tmp_path / "m.csv")
    with pytest.raises(InputError) as exc:
        cohort_deployment(manifest, tmp_path / "out", cron="0 2 * * *", timezone="Mars/Base")
    assert str(exc.value).startswith("invalid --timezone 'Mars/Base': not an IANA time zone")
    text = manifest.read_text()
    late = text.splitlines()[1].replace("srv0", "late", 1).replace("srv0", "NOPE")
    manifest.write_text(text + late + "\n")
    dep = cohort_deployment(manifest, tmp_path / "out", cron="0 2 * * *", timezone="Europe/Paris")
    assert dep.schedules[0].schedule.timezone == "Europe/Paris"

"""Scheduled reprocessing: the deployment's schedule and parameters, and what a run recomputes.

The deployment object is built without serving (``cohort_deployment``); a
run triggered through the Prefect API after a patient is added to the manifest
is executed the way Prefect's runner executes it (``python -m prefect.engine``
with the flow run's id: the flow is loaded from the deployment's entrypoint
and parameters) and computes only the new patient. A patient dropped from the
manifest is reported, its folder kept. A run ends Failed when a patient failed
or the manifest broke after the deployment was made (one line, no traceback),
and every run records its outcome in ``DIR/last_run.json``.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys
from pathlib import Path

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


@pytest.mark.usefixtures("prefect_harness")
def test_the_server_makes_the_runs_of_the_cron_schedule_one_at_a_time(tmp_path):
    """The deployment's cron schedule becomes scheduled runs on the server: what the
    server's scheduler service does every loop, asked here once through the API. Prefect
    3.8's server fails this insert under SQLAlchemy 2.1, and no scheduled run was ever
    made (pyproject.toml pins 2.0). The deployment runs one run at a time."""
    from datetime import timedelta

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId

    manifest = write_manifest([_row(0, tmp_path)], tmp_path / "m.csv")
    dep = cohort_deployment(manifest, tmp_path / "out", cron="*/10 * * * *", name="every10")
    deployment_id = dep.apply()
    with get_client(sync_client=True) as client:
        client._client.post(f"/deployments/{deployment_id}/schedule", json={})
        runs = client.read_flow_runs(
            deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment_id]))
        )
        limit = client.read_deployment(deployment_id).global_concurrency_limit
    starts = sorted(r.expected_start_time for r in runs)
    assert len(starts) >= 3 and all(r.state is not None and r.state.is_scheduled() for r in runs)
    assert all(t.minute % 10 == 0 and t.second == 0 for t in starts)  # the cron's times
    assert all(b - a == timedelta(minutes=10) for a, b in itertools.pairwise(starts))
    assert limit is not None and limit.limit == 1


def _execute_triggered_run(dep):
    """Register the deployment, create a run through the API, execute it like a runner.

    Returns the flow run's id, its final state and the finished process (its output is
    what the ``serve`` console shows of the run).
    """
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
    with get_client(sync_client=True) as client:
        state = client.read_flow_run(flow_run.id).state
    assert state is not None
    return str(flow_run.id), state, proc


def _trigger_and_execute(dep) -> str:
    """:func:`_execute_triggered_run`, which must complete; returns the flow run's id."""
    run_id, state, proc = _execute_triggered_run(dep)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert state.is_completed(), state
    return run_id


def _a_run_its_process_left_running_is_crashed_by_the_next_command(run_id: str) -> None:
    """The scheduled run names the process that ran it (a runner's ``prefect.engine``).

    ``serve`` stopped mid-run left its run Running for good, holding the deployment's
    one slot, so a restarted ``serve`` ran nothing for minutes (a user audit): set back
    to Running, the run is set Crashed by the sweep every command starts with, as its
    process has ended."""
    from prefect.client.orchestration import get_client
    from prefect.states import Running

    from tumor3d.flows.stale_runs import PROCESS_TAG, crash_stale_runs, process_tags

    if not process_tags():
        pytest.skip("no /proc: nothing is tagged")
    with get_client(sync_client=True) as client:
        run = client.read_flow_run(run_id)
        mine = [t for t in run.tags if t.startswith(PROCESS_TAG)]
        assert mine and not mine[0].startswith(f"{PROCESS_TAG}{os.getpid()}:"), run.tags
        client.set_flow_run_state(run_id, Running(), force=True)
    assert run.name in crash_stale_runs()
    with get_client(sync_client=True) as client:
        assert client.read_flow_run(run_id).state.is_crashed()


def _last_run(out) -> dict:
    return json.loads((out / "last_run.json").read_text())


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
    run_id = _trigger_and_execute(dep)
    _a_run_its_process_left_running_is_crashed_by_the_next_command(run_id)
    last = _last_run(out)  # an all-ok run: recorded as completed
    assert (last["flow_run_id"], last["state"]) == (run_id, "completed")
    assert last["patients"] == {"ok": 3, "check": 0, "failed": 0}
    assert last["message"] == "3 patients completed"
    assert last["started_utc"] <= last["finished_utc"]
    assert "since_earlier_result" not in last  # two all from the cache, one new
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


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_manifest_broken_after_serve_started_fails_the_run_in_one_line(tmp_path):
    """Audit: a scheduled run on a manifest edited into an invalid one printed a traceback,
    and the folder's earlier cohort.md still looked like the latest run."""
    manifest = write_manifest([_row(0, tmp_path / "in")], tmp_path / "m.csv")
    out = tmp_path / "out"
    dep = cohort_deployment(manifest, out, cron="0 2 * * *", workers=1)
    manifest.write_text("patient,scan\nsrv0,srv0.nii.gz\n")  # no longer a manifest

    run_id, state, proc = _execute_triggered_run(dep)
    assert state.is_failed(), state
    message = state.message
    assert message.startswith(f"InputError: {manifest.resolve()}: ") and "column" in message
    assert "\n" not in message
    console = proc.stdout + proc.stderr
    assert message in console, console[-3000:]
    assert "Traceback" not in console, console[-3000:]
    last = _last_run(out)
    assert (last["flow_run_id"], last["state"], last["message"]) == (run_id, "failed", message)
    assert last["patients"] == {"ok": 0, "check": 0, "failed": 0}


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_run_where_a_patient_failed_writes_the_outputs_and_ends_failed(tmp_path):
    """Audit: a scheduled run with a failed patient ended Completed."""
    manifest = write_manifest([_row(0, tmp_path / "in")], tmp_path / "m.csv")
    text = manifest.read_text()  # a row whose image is not there: accepted, fails alone
    late = text.splitlines()[1].replace("srv0", "late", 1).replace("srv0", "NOPE")
    manifest.write_text(text + late + "\n")
    out = tmp_path / "out"
    dep = cohort_deployment(manifest, out, cron="0 2 * * *", workers=1)

    state = scheduled_cohort_flow(**dep.parameters, return_state=True)
    assert state.is_failed(), state
    assert state.message.startswith("1 of 2 patients failed: late (prepare-input: ")
    assert "NOPE" in state.message and "\n" not in state.message
    table = pd.read_parquet(out / "cohort.parquet").set_index("patient_id")
    assert table["status"].to_dict() == {"srv0": "ok", "late": "failed"}
    assert "late" in (out / "cohort.md").read_text()
    last = _last_run(out)
    assert (last["state"], last["message"]) == ("failed", state.message)
    assert last["patients"] == {"ok": 1, "check": 0, "failed": 1}


def test_an_output_folder_that_cannot_be_made_fails_the_run_in_one_line(tmp_path):
    """An environment error (OSError, as the CLI's exit 3) is the user's to fix: one line,
    state Failed, before any patient runs (run_cohort probes DIR first)."""
    manifest = write_manifest([_row(0, tmp_path / "in")], tmp_path / "m.csv")
    (tmp_path / "a_file").write_text("not a folder")
    out = tmp_path / "a_file" / "out"
    dep = cohort_deployment(manifest, out, cron="0 2 * * *", workers=1)
    state = scheduled_cohort_flow(**dep.parameters, return_state=True)
    assert state.is_failed(), state
    assert state.message.startswith("NotADirectoryError: ") and str(out) in state.message


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
    # how to trigger it now from another shell, with the server it is served on
    url = re.search(r" on\s+(\S+/api); Ctrl-C", ok.output).group(1)
    # the prefect command of this environment, which need not be on PATH (a user audit)
    prefect = Path(sys.executable).with_name("prefect")
    assert prefect.is_file()
    hint = f"PREFECT_API_URL={url} {prefect} deployment run 'tumor3d-scheduled-cohort/n1'"
    assert hint in ok.output, ok.output
    # its end is said (Ctrl-C returns from Prefect's serve; it was silent)
    assert ok.output.rstrip().endswith(
        "stopped serving tumor3d-scheduled-cohort/n1; a run it was executing, if any, ends "
        "Crashed (set by the next tumor3d command)"
    ), ok.output
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


def test_last_run_says_which_patients_changed_since_their_earlier_result(tmp_path):
    """A user audit: a scheduled run's reason for recomputing a patient was only in
    cohort.md, which the next run replaces; last_run.json keeps it with the run."""
    import logging

    from tumor3d.flows.cohort_result import CohortResult, PatientOutcome
    from tumor3d.flows.serve import _write_last_run

    patients = [
        PatientOutcome(patient_id="p1", status="ok", recomputed="configuration changed"),
        PatientOutcome(patient_id="p2", status="ok"),
        PatientOutcome(patient_id="p3", status="check", recomputed="configuration changed"),
    ]
    _write_last_run(str(tmp_path), "t0", "completed", "3 patients completed",
                    CohortResult(patients=patients), logging.getLogger("test"))  # fmt: skip
    last = _last_run(tmp_path)
    assert last["since_earlier_result"] == {"configuration changed": ["p1", "p3"]}
    assert last["patients"] == {"ok": 2, "check": 1, "failed": 0}

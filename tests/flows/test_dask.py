"""The cohort flow on Dask: a 2-worker LocalCluster, and an unreachable scheduler.

The cluster is a ``distributed.LocalCluster(n_workers=2, processes=False)``
(worker threads in the test process: seconds to start instead of two fresh
interpreters importing numba); the flow connects to it by address, exactly as
``--dask-address`` does. Its task stream shows where each stage ran. The
results must equal those of the default local runner on the same inputs.
``--dask-workers N`` (worker processes) is exercised by benchmarks/bench_dask.py.
The two fault tests share one cluster of two worker *processes* (a killed thread
is not a killed worker): one SIGKILLs a worker once (Dask reruns the stage), one
has a stage that kills its worker every time (Dask gives up with ``KilledWorker``).
"""

from __future__ import annotations

import os
import platform
import socket
import threading
import time
import uuid

import numpy as np
import pytest
from phantom_rows import small_phantom_rows
from typer.testing import CliRunner

from tumor3d.errors import InputError
from tumor3d.flows import dask_runner, dask_workers
from tumor3d.flows.cli import app
from tumor3d.flows.cohort import run_cohort
from tumor3d.flows.dask_runner import ClusterError, DaskSpec
from tumor3d.storage.manifest import write_manifest
from tumor3d.storage.store import StoreError
from tumor3d.tasks.stages import STAGES

distributed = pytest.importorskip("distributed", reason="Dask extra not installed")
pytest.importorskip("prefect_dask", reason="prefect-dask not installed")


#: Generous Dask comm timeouts (30 s by default) for a loaded shared machine: restarting a
#: killed worker *process* imports numpy, numba and Prefect afresh; under a full test run
#: beside other jobs that has taken longer than the default 30 s connect timeout and
#: failed a fault test with a comm timeout (it passed when run alone). Nannies hand this
#: configuration to the worker processes they start.
GENEROUS_COMM_TIMEOUTS = {
    "distributed.comm.timeouts.connect": "180s",
    "distributed.comm.timeouts.tcp": "180s",
}


@pytest.fixture
def generous_comm_timeouts():
    import dask

    with dask.config.set(GENEROUS_COMM_TIMEOUTS):
        yield


@pytest.fixture(scope="module")
def process_cluster():
    """Two worker *processes* (a killed thread is not a killed worker), shared by the
    two fault tests: each new worker process imports numpy, numba and Prefect afresh, so
    one cluster for both saves two of them. The nannies restart a killed worker; each
    test waits until both are back before it starts."""
    import dask

    with dask.config.set(GENEROUS_COMM_TIMEOUTS), distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
    ) as cluster, distributed.Client(cluster) as client:  # fmt: skip
        yield cluster, client


def _rows(folder, seeds):
    return small_phantom_rows(folder, seeds, "dsk")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def not_a_scheduler():
    """Two local services that accept a connection but are no Dask scheduler: one stays
    silent (a dashboard's port as the handshake sees it), one answers garbage (whose
    length prefix numpy cannot allocate). Their addresses."""
    servers, addresses = [], {}
    for kind, reply in (("silent", b""), ("garbage", b"\xff" * 64 + b"HTTP/1.1 400\r\n" * 9)):
        srv = socket.socket()
        srv.bind(("127.0.0.1", 0))
        srv.listen(8)
        held = []

        def serve(srv=srv, reply=reply, held=held):
            while True:
                try:
                    conn, _ = srv.accept()
                except OSError:
                    return
                held.append(conn)  # kept open until the test ends
                if reply:
                    conn.sendall(reply)

        threading.Thread(target=serve, daemon=True).start()
        servers.append((srv, held))
        addresses[kind] = f"tcp://127.0.0.1:{srv.getsockname()[1]}"
    yield addresses
    for srv, held in servers:
        srv.close()
        for conn in held:
            conn.close()


def test_an_address_that_is_no_scheduler_is_one_line_not_a_hang(
    not_a_scheduler, tmp_path, monkeypatch
):
    """A user audit: the dashboard's port hung the cohort with no output for 10 minutes,
    and a non-Dask service's answer gave an 81-line traceback (a 3 EiB allocation) and
    exit 1. Both are one line, exit 3, within the timeout and its grace."""
    monkeypatch.setattr(dask_runner, "CONNECT_TIMEOUT_S", 1.0)
    monkeypatch.setattr(dask_runner, "CONNECT_GRACE_S", 2.0)
    expected = {
        "silent": "no answer as a Dask scheduler within 1 s",
        "garbage": "what answered is not a Dask scheduler",
    }
    for kind, address in not_a_scheduler.items():
        t0 = time.perf_counter()
        with pytest.raises(ClusterError) as exc:
            dask_runner.check_scheduler(address)
        assert time.perf_counter() - t0 < 60, kind
        text = str(exc.value)
        assert text.startswith(f"Dask scheduler {address}: {expected[kind]}"), text
        assert "\n" not in text and text.endswith("fix --dask-address")
    for address in ("nonsense", "tcp://127.0.0.1:99999"):  # at once, not after the timeout
        with pytest.raises(ClusterError, match=rf"^Dask scheduler {address}: not a scheduler add"):
            dask_runner.check_scheduler(address)
    rows = _rows(tmp_path / "in", [0])
    manifest = write_manifest(rows, tmp_path / "m.csv")
    out = tmp_path / "out"
    res = CliRunner().invoke(
        app, ["cohort", str(manifest), "--out", str(out), "--dask-address",
              not_a_scheduler["silent"]],
    )  # fmt: skip
    assert res.exit_code == 3, res.output
    assert "no answer as a Dask scheduler" in res.output and "Traceback" not in res.output
    assert not out.exists()


def test_unreachable_scheduler_is_one_line_before_any_patient(tmp_path, monkeypatch):
    # the refusal is the same at any timeout: wait 1 s, not the default 10 s, twice
    monkeypatch.setattr(dask_runner, "CONNECT_TIMEOUT_S", 1.0)
    rows = _rows(tmp_path / "in", [0])
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    out = tmp_path / "out"
    t0 = time.perf_counter()
    with pytest.raises(
        ClusterError, match=f"Dask scheduler {address}: cannot connect within 1 s"
    ) as exc:
        run_cohort(rows, out, workers=1, dask=DaskSpec(address=address))
    assert "\n" not in str(exc.value)
    assert time.perf_counter() - t0 < 30
    assert not out.exists()  # nothing started, nothing written
    manifest = write_manifest(rows, tmp_path / "m.csv")
    res = CliRunner().invoke(
        app, ["cohort", str(manifest), "--out", str(out), "--dask-address", address]
    )
    assert res.exit_code == 3, res.output  # an environment error
    assert "cannot connect" in res.output and "Traceback" not in res.output
    assert not out.exists()


def _probe_folders(root):
    return [p for p in root.rglob("*") if dask_workers.PROBE_DIR in p.parts]


def test_the_store_probe_is_read_where_it_was_written_and_removed_after(tmp_path):
    """What a worker is asked: the probe this process left in the store (a folder, or an
    fsspec URL: the memory file system stands for s3://), and its stage code."""
    for location in (str(tmp_path / "new" / "store"), f"memory://probe-{uuid.uuid4().hex}"):
        token = uuid.uuid4().hex
        remove = dask_workers._write_probe(location, token)
        seen = dask_workers.worker_view(location, token)
        assert seen["store"] == "ok", location
        assert seen["stages"] == {n: s.code_digest for n, s in STAGES.items()}
        assert seen["packages"]["numpy"] == np.__version__
        other = dask_workers.worker_view(location, uuid.uuid4().hex)  # another machine's view
        assert other["store"].startswith("FileNotFoundError"), other["store"]
        remove()
        assert dask_workers.worker_view(location, token)["store"].startswith("FileNotFoundError")
    assert not (tmp_path / "new").exists()  # the folders the probe made are gone with it
    afile = tmp_path / "afile"
    afile.write_text("not a store")
    with pytest.raises(InputError, match="must be a folder, but this is a file"):
        dask_workers._write_probe(str(afile), "t")
    with pytest.raises(StoreError, match=f"^{afile / 'sub'}: cannot write in the artifact store"):
        dask_workers._write_probe(str(afile / "sub"), "t")
    assert afile.read_text() == "not a store" and sorted(tmp_path.iterdir()) == [afile]


@pytest.mark.usefixtures("generous_comm_timeouts")
def test_a_worker_that_does_not_share_the_store_or_the_code_is_one_line_before_any_patient(
    tmp_path, monkeypatch
):
    """``--dask-address``: a worker on a machine that does not see the store (a path on
    this machine only), or that runs other stage code or other numerical packages, is
    named in one line, exit 3, before any patient starts; nothing is left behind. Thread
    workers of this process stand for the other machines: their answer is edited."""
    rows = _rows(tmp_path / "in", [0])
    out = tmp_path / "out"
    manifest = write_manifest(rows, tmp_path / "m.csv")
    real = dask_workers.worker_view
    elsewhere = str(tmp_path / "elsewhere")  # where the worker's machine looks

    def blind(location, token):
        return real(elsewhere, token)

    def other_code(location, token):
        seen = real(location, token)
        return {**seen, "stages": {**seen["stages"], "render-views": "0" * 64}}

    def other_numpy(location, token):
        seen = real(location, token)
        return {**seen, "packages": {**seen["packages"], "numpy": "1.0.0"}}

    def other_python(location, token):
        return {**real(location, token), "python": "3.99"}

    def older_tumor3d(location, token):
        raise ModuleNotFoundError("No module named 'tumor3d.flows.dask_workers'")

    def failing(location, token):
        raise RuntimeError("boom")

    def silent(location, token):  # stopped, or a task holding the GIL
        time.sleep(3)
        return real(location, token)

    here = ".".join(platform.python_version_tuple()[:2])
    cases = [
        (blind, f"does not see the artifact store {out / '.tumor3d-store'} (FileNotFoundError"),
        (other_python, f"runs Python 3.99 ({here} here)"),
        (other_code, "runs other tumor3d code (stages render-views differ"),
        (other_numpy, f"other numerical packages (numpy 1.0.0 there, {np.__version__} here)"),
        (older_tumor3d, "runs another version of tumor3d (ModuleNotFoundError: No module"),
        (failing, ": the check of what it shares with this machine failed (RuntimeError: boom)"),
        (silent, ": no answer within 0.5 s to the check of the artifact store and the code"),
    ]
    dask_workers._code()  # this process's stage digests, made once: the workers' are too
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0"
    ) as cluster:  # fmt: skip
        address = cluster.scheduler_address
        worker = next(iter(cluster.scheduler.workers))
        for view, message in cases:
            monkeypatch.setattr(dask_workers, "worker_view", view)
            # a silent worker is given up after 0.5 s (and so is the last, the CLI's)
            monkeypatch.setattr(
                dask_workers, "WORKER_CHECK_TIMEOUT_S", 0.5 if view is silent else 60
            )
            with pytest.raises(ClusterError) as exc:
                run_cohort(rows, out, workers=1, dask=DaskSpec(address=address))
            assert str(exc.value).startswith(f"Dask worker {worker}"), exc.value
            assert message in str(exc.value) and "\n" not in str(exc.value)
            assert not out.exists()  # no patient, no store, no probe
        res = CliRunner().invoke(
            app, ["cohort", str(manifest), "--out", str(out), "--dask-address", address]
        )
        assert res.exit_code == 3, res.output  # an environment error
        assert "no answer within 0.5 s" in res.output and "Traceback" not in res.output
        assert "Prefect" not in res.output  # refused before a Prefect server was started
    assert not out.exists() and not _probe_folders(tmp_path)


def test_dask_options_are_exclusive():
    with pytest.raises(InputError, match="either --dask-address or --dask-workers"):
        DaskSpec(address="tcp://127.0.0.1:8786", n_workers=2)


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness", "generous_comm_timeouts")
def test_cohort_on_a_two_worker_cluster_matches_the_local_runner(tmp_path):
    rows = _rows(tmp_path / "in", [0, 1])
    local = run_cohort(rows, tmp_path / "local", workers=2)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0"
    ) as cluster, distributed.Client(cluster) as client:  # fmt: skip
        with distributed.get_task_stream(client) as stream:
            on_dask = run_cohort(
                rows, tmp_path / "dask", dask=DaskSpec(address=cluster.scheduler_address)
            )
        workers = set(cluster.scheduler.workers)
    assert on_dask.workers == 2  # lanes = the cluster's workers
    assert on_dask.exit_code == 0
    # every stage of every patient ran on the cluster, spread over both workers
    assert len(stream.data) == len(STAGES) * len(rows)
    assert {t["worker"] for t in stream.data} == workers and len(workers) == 2
    for a, b in zip(local.patients, on_dask.patients, strict=True):
        assert a.patient_id == b.patient_id and b.status == "ok"
        assert a.metrics["volume_eq7_mm3"] == b.metrics["volume_eq7_mm3"]
        assert a.metrics["volume_mesh_mm3"] == b.metrics["volume_mesh_mm3"]
        assert [s.artifacts for s in a.stages] == [s.artifacts for s in b.stages]
        assert not any(s.cached for s in b.stages)  # its own store: computed afresh
    # the same store re-run with the local runner: every stage a cache hit
    again = run_cohort(rows, tmp_path / "dask", workers=1)
    assert all(s.cached for p in again.patients for s in p.stages)


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness", "generous_comm_timeouts")
def test_a_worker_killed_mid_stage_the_cohort_finishes_and_a_rerun_completes(
    tmp_path, process_cluster
):
    """SIGKILL the worker process running a render: Dask reruns the stage elsewhere.

    Worker *processes* here (a killed thread is not a killed worker); the
    nanny restarts the killed one. Whatever happens to the patient whose
    stage was lost (retried, or recorded as failed), the cohort ends, nothing
    is half-written, and a local re-run on the same store completes every
    patient with the stages that finished before the kill as cache hits.
    """
    import os
    import signal
    import threading

    from tumor3d.tasks.progress import use_reporter

    rows = _rows(tmp_path / "in", [0, 1])
    out = tmp_path / "out"
    killed: dict[str, object] = {}
    lock = threading.Lock()
    cluster, client = process_cluster
    client.wait_for_workers(2, timeout=180)
    pids = client.run(os.getpid)

    def reporter(event):
        if event.stage != "render-views" or event.status != "started":
            return
        with lock:
            if killed:
                return
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                busy = [a for a, keys in client.processing().items() if keys]
                if busy:
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.update(worker=busy[0], patient=event.patient_id)
                    return
                time.sleep(0.05)

    with use_reporter(reporter):
        result = run_cohort(rows, out, dask=DaskSpec(address=cluster.scheduler_address))
    assert killed, "no worker was killed: the test did not exercise anything"
    assert len(result.patients) == 2
    for p in result.patients:
        if p.status == "ok":  # published as a whole
            assert (out / p.patient_id / "metrics.parquet").is_file()
        else:
            assert p.error and "\n" not in p.error
            assert not (out / p.patient_id).exists()
    assert not [q for q in out.iterdir() if ".partial-" in q.name or ".old-" in q.name]
    objects = out / ".tumor3d-store" / "objects"
    assert not [f for f in objects.rglob("*") if f.name.startswith(".")]  # no temp files
    ok_before = {p.patient_id for p in result.patients if p.status == "ok"}

    again = run_cohort(rows, out, workers=1)
    assert again.exit_code == 0
    for p in again.patients:
        if p.patient_id in ok_before:
            assert all(s.cached for s in p.stages), p.patient_id
        else:  # the stages before the lost render come from the cache
            assert p.stages[0].cached, p.patient_id


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness", "generous_comm_timeouts")
def test_a_stage_that_kills_its_worker_every_time_fails_that_patient_only(
    tmp_path, process_cluster
):
    """Dask gives up after ``allowed-failures`` worker deaths with ``KilledWorker``.

    The limit is lowered from Dask's 3 to 1 for this test (on the shared cluster, and
    restored after it): Dask gives up at the second death instead of the fourth, two
    worker processes fewer to restart (each imports numpy, numba and Prefect afresh);
    the giving up is the same. A worker plugin
    (installed again on every restarted worker by the scheduler) wraps Prefect's
    ``run_task_sync`` (what prefect-dask runs on a worker) in each worker *process*: the
    ``preprocess`` task of patient dsk1 SIGKILLs its own worker, every time it runs.
    Expected: dsk1 is recorded as failed at ``preprocess`` with a one-line
    ``KilledWorker`` error and no folder; dsk0 is published; the cohort ends.
    """
    from distributed.diagnostics.plugin import WorkerPlugin

    class KillOnDoomedStage(WorkerPlugin):
        name = "tumor3d-test-killer"

        def setup(self, worker):
            import os
            import signal

            import prefect.task_engine as engine

            original = self.original = engine.run_task_sync

            def run_task_sync(*args, **kwargs):
                task = kwargs.get("task")
                if getattr(task, "task_run_name", None) == "preprocess-dsk1":
                    os.kill(os.getpid(), signal.SIGKILL)
                return original(*args, **kwargs)

            engine.run_task_sync = run_task_sync

        def teardown(self, worker):  # unregistered: the shared cluster's workers as before
            import prefect.task_engine as engine

            engine.run_task_sync = self.original

    rows = _rows(tmp_path / "in", [0, 1])
    out = tmp_path / "out"
    cluster, client = process_cluster
    client.wait_for_workers(2, timeout=180)
    before = cluster.scheduler.allowed_failures
    cluster.scheduler.allowed_failures = 1  # read by the scheduler at each worker death
    client.register_plugin(KillOnDoomedStage())
    try:
        t0 = time.perf_counter()
        result = run_cohort(rows, out, dask=DaskSpec(address=cluster.scheduler_address))
        wall = time.perf_counter() - t0
    finally:  # the shared cluster as it was: no killer, Dask's own limit
        client.unregister_worker_plugin(KillOnDoomedStage.name)
        cluster.scheduler.allowed_failures = before
    by_id = {p.patient_id: p for p in result.patients}
    assert by_id["dsk0"].status == "ok", by_id["dsk0"].error
    assert (out / "dsk0" / "metrics.parquet").is_file()
    doomed = by_id["dsk1"]
    assert doomed.status == "failed" and doomed.failed_stage == "preprocess", doomed
    assert "KilledWorker" in doomed.error and "\n" not in doomed.error, doomed.error
    assert not (out / "dsk1").exists()
    assert [s.stage for s in doomed.stages] == ["ingest-scan"]
    assert result.exit_code == 1 and wall < 600
    print(f"dsk1: {doomed.error} (cohort {wall:.0f} s)")
    again = run_cohort(rows, out, workers=1)  # no killer locally: completed from the cache
    assert again.exit_code == 0
    assert all(s.cached for s in again.patients[0].stages)
    assert again.patients[1].stages[0].cached and not again.patients[1].stages[1].cached


def test_a_local_clusters_workers_keep_prefect_run_records_off_the_console(monkeypatch):
    """A user audit: with --dask-workers, a failed patient's task run printed four Prefect
    tracebacks on stderr (the worker processes log to the command's stderr), where the
    command promises one line. The workers preload the console filter when the command's
    console is quiet; the hook, run in a fresh process, drops the run records only."""
    import subprocess
    import sys

    from tumor3d.flows.dask_runner import cohort_task_runner

    monkeypatch.setattr(dask_runner, "console_is_quiet", lambda: True)
    kwargs = cohort_task_runner(2, DaskSpec(n_workers=2)).cluster_kwargs
    assert kwargs["preload"] == ["tumor3d.flows.quiet_logs"]
    monkeypatch.setattr(dask_runner, "console_is_quiet", lambda: False)  # --verbose
    assert "preload" not in cohort_task_runner(2, DaskSpec(n_workers=2)).cluster_kwargs
    code = (
        "import logging\n"
        "from tumor3d.flows.quiet_logs import console_is_quiet, dask_setup\n"
        "assert not console_is_quiet()\n"
        "dask_setup(None)\n"
        "assert console_is_quiet()\n"
        "logging.getLogger('prefect.task_runs').error('TASK-RUN-FAILED')\n"
        "logging.getLogger('prefect.flow_runs').warning('FLOW-RUN-WARNED')\n"
        "logging.getLogger('prefect.client').warning('CLIENT-WARNED')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
        env={**os.environ, "PREFECT_LOGGING_LEVEL": "WARNING"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "CLIENT-WARNED" in done.stderr  # the console still works
    assert "TASK-RUN-FAILED" not in done.stderr and "FLOW-RUN-WARNED" not in done.stderr


def test_a_local_cluster_starts_while_another_holds_the_dashboard_port():
    # a user's own Dask cluster (or a second cohort) holds 8787: the cohort's LocalCluster
    # must still start, without the "Port 8787 is already in use" warning (an error here)
    from tumor3d.flows.dask_runner import cohort_task_runner

    holder = socket.socket()
    holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        holder.bind(("", 8787))
        holder.listen(1)
    except OSError:
        pass  # already held by another process: the same situation
    try:
        kwargs = dict(cohort_task_runner(2, DaskSpec(n_workers=1)).cluster_kwargs)
        kwargs["processes"] = False  # threads: the dashboard port is the scheduler's
        kwargs.pop("env", None)  # a worker process's environment: none for threads
        cluster = distributed.LocalCluster(**kwargs)
        try:
            assert len(cluster.scheduler_info["workers"]) == 1
        finally:
            cluster.close()
    finally:
        holder.close()


def test_a_scheduler_that_just_answered_is_not_asked_again(monkeypatch):
    """The command's preflight and the cohort it starts each checked --dask-address, a
    child process and a connection each (about 1 s): an answer serves the next check
    within half a minute, once (a notebook's next cohort asks again); a refusal serves
    none."""
    calls = []

    def connect(address, timeout_s, fix):
        calls.append(address)
        return {"workers": 3} if address.endswith(":8786") else {"error": "OSError", "text": "no"}

    monkeypatch.setattr(dask_runner, "_connect_in_child", connect)
    monkeypatch.setattr(dask_runner, "_answered", {})
    assert dask_runner.check_scheduler("tcp://10.0.0.1:8786") == 3
    assert dask_runner.check_scheduler("tcp://10.0.0.1:8786") == 3
    assert calls == ["tcp://10.0.0.1:8786"]
    assert dask_runner.check_scheduler("tcp://10.0.0.1:8786") == 3  # the third asks again
    assert calls == ["tcp://10.0.0.1:8786"] * 2
    calls.clear()
    assert dask_runner.check_scheduler("tcp://10.0.0.1:8786") == 3  # its answer serves one
    assert calls == []
    for _ in range(2):
        with pytest.raises(ClusterError, match="cannot connect"):
            dask_runner.check_scheduler("tcp://10.0.0.1:9999")
    assert calls == ["tcp://10.0.0.1:9999"] * 2
    assert dask_runner.check_scheduler("tcp://10.0.0.1:8786") == 3  # answered again: kept
    monkeypatch.setattr(dask_runner, "RECENT_CHECK_S", 0.0)  # an old answer: asked again
    assert dask_runner.check_scheduler("tcp://10.0.0.1:8786") == 3
    assert calls == ["tcp://10.0.0.1:9999"] * 2 + ["tcp://10.0.0.1:8786"] * 2

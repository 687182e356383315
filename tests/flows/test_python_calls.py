"""Flow runs made from Python (a notebook's ``run_patient``, ``run_cohort``): tagged with
their process, and the Running runs of a killed one set Crashed, as a command's are
(tumor3d.flows.stale_runs; the commands' case: tests/flows/test_cohort_interrupt.py);
on the background server, what they buffered sent before the call returns."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

from tumor3d.flows.stale_runs import PLACE_TAG, PROCESS_TAG, _start_ticks, process_tags

no_proc = pytest.mark.skipif(not process_tags(), reason="no /proc: nothing is tagged")


def _ended_process_tag() -> str:
    """The process tag of a process that has ended (a notebook's killed kernel)."""
    proc = subprocess.Popen(["sleep", "30"])
    ticks = _start_ticks(proc.pid)
    proc.kill()
    proc.wait()
    return f"{PROCESS_TAG}{proc.pid}:{ticks}"


@no_proc
@pytest.mark.usefixtures("prefect_harness")
def test_a_python_call_tags_its_runs_and_crashes_the_runs_of_a_killed_kernel(monkeypatch):
    from prefect import flow, tags
    from prefect.client.orchestration import get_client
    from prefect.context import FlowRunContext
    from prefect.states import Running

    from tumor3d.flows import api_use
    from tumor3d.flows.api_use import api_of_python_call

    monkeypatch.setattr(api_use, "_python_sweeps", {})  # this process has not swept yet

    @flow(name="notebook-call")
    def probe() -> list[str]:
        ctx = FlowRunContext.get()
        assert ctx is not None and ctx.flow_run is not None
        return sorted(ctx.flow_run.tags)

    place = process_tags()[0]
    with get_client(sync_client=True) as client:
        killed = client.create_flow_run(
            probe, name="killed-kernel", tags=[place, _ended_process_tag()], state=Running()
        )
        alive = client.create_flow_run(
            probe, name="live-kernel", tags=list(process_tags()), state=Running()
        )
    with api_of_python_call():
        tagged = probe()
    assert set(process_tags()) <= set(tagged)  # this process, where it is seen
    with get_client(sync_client=True) as client:
        state = client.read_flow_run(killed.id).state
        assert state is not None and state.is_crashed(), state
        assert state.message.startswith("its process ("), state.message
        assert client.read_flow_run(alive.id).state.is_running()  # its process lives
    # a loop of calls: the next within the minute tags its run but does not sweep again
    with get_client(sync_client=True) as client:
        later = client.create_flow_run(
            probe, name="killed-later", tags=[place, _ended_process_tag()], state=Running()
        )
    with api_of_python_call():
        assert set(process_tags()) <= set(probe())
    with get_client(sync_client=True) as client:
        assert client.read_flow_run(later.id).state.is_running()
    monkeypatch.setattr(api_use, "PYTHON_SWEEP_PERIOD_S", 0.0)  # ... and after it, does
    with api_of_python_call():
        probe()
    with get_client(sync_client=True) as client:
        assert client.read_flow_run(later.id).state.is_crashed()
    # inside a command (its runs tagged already): the same tags, once
    other = f"{PLACE_TAG}elsewhere:1"
    with tags(other), api_of_python_call():
        inner = probe()
    assert other in inner and not [t for t in inner if t.startswith(PLACE_TAG) and t != other]


@pytest.mark.usefixtures("prefect_harness")
def test_a_call_on_the_background_server_sends_its_logs_and_events_before_it_returns(
    monkeypatch, tmp_path
):
    """A notebook that stopped and started the background server between two calls sent
    the second call's events to the stopped one, and spent 4 min at exit retrying it:
    Prefect's log and event senders, made in a patient's stage threads for the API they
    first met, outlived the call. Each call on the background server now sends what it
    buffered and stops them, so the next call makes its own for the server of its time."""
    from phantom_rows import small_phantom_rows
    from prefect._internal.concurrency.services import _QueueServiceBase
    from prefect.settings import PREFECT_API_URL

    from tumor3d.config import PipelineConfig
    from tumor3d.flows import api_use, server
    from tumor3d.flows.patient import run_patient

    info = server.ServerInfo(pid=os.getpid(), port=0, api_url=PREFECT_API_URL.value())
    monkeypatch.setattr(api_use, "_configured_api_url", lambda: None)  # no PREFECT_API_URL
    monkeypatch.setattr(server, "server_status", lambda: server.ServerStatus("running", "", info))
    (row,) = small_phantom_rows(tmp_path / "in", [3], "nb")
    result = run_patient(  # a PipelineConfig, as tumor3d.reconstruct takes it
        row.image, tmp_path / "out", modality=row.modality, patient_id="nb3",
        config=PipelineConfig(),
    )  # fmt: skip
    assert result.metrics["status"] in ("ok", "check")
    senders = {type(w).__name__: w._stopped for w in _QueueServiceBase._instances.values()}
    assert all(senders.values()), f"left running after the call: {senders}"


def test_a_python_calls_mistakes_are_one_line_before_any_flow_run(tmp_path, monkeypatch):
    """What the commands refuse before Prefect starts, a Python call refuses too, as
    tumor3d's (or Python's) own one-line error: an input that does not exist (it took
    10 s, started a server and left a store folder behind), a misspelled keyword (was
    Prefect's ParameterBindError with the flow's whole signature), a configuration
    file's path where its text is asked (was "must be a mapping", no hint)."""
    from tumor3d.errors import ConfigError, InputError
    from tumor3d.flows import api_use
    from tumor3d.flows.cohort import run_cohort
    from tumor3d.flows.patient import run_patient

    def no_flow_run():
        raise AssertionError("a flow run (and a Prefect server) was started")

    monkeypatch.setattr(api_use, "api_of_python_call", no_flow_run)
    out = tmp_path / "out"
    missing = tmp_path / "nowhere.nii.gz"
    with pytest.raises(InputError, match="no such file or folder") as exc:
        run_patient(missing, out, modality="t2")
    assert str(missing) in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(TypeError, match="modalty") as bad:
        run_patient(missing, out, modalty="t2")
    assert type(bad.value) is TypeError  # Python's, not Prefect's ParameterBindError
    with pytest.raises(ConfigError, match="a file's name"):
        run_patient(missing, out, modality="t2", config="configs/paper.yaml")
    with pytest.raises(ConfigError, match="a file's path"):
        run_cohort([], out, config=tmp_path / "paper.yaml")
    assert not out.exists()


def test_an_unreachable_prefect_api_url_is_one_line_naming_it(tmp_path):
    """The commands refuse a PREFECT_API_URL that does not answer in one line; a Python
    call raised Prefect's bare RuntimeError ("Failed to reach API") after its retries."""
    from phantom_rows import small_phantom_rows
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from tumor3d.flows.patient import run_patient
    from tumor3d.flows.server import ServerError

    (row,) = small_phantom_rows(tmp_path / "in", [4], "nb")
    with socket.socket() as sock:  # a port nothing listens on
        sock.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{sock.getsockname()[1]}/api"
    with temporary_settings(updates={PREFECT_API_URL: url}):
        with pytest.raises(ServerError, match="PREFECT_API_URL") as exc:
            run_patient(row.image, tmp_path / "out", modality="t2")
    assert url in str(exc.value) and "\n" not in str(exc.value)
    assert not (tmp_path / "out").exists()


@pytest.mark.usefixtures("prefect_harness")
def test_a_failed_stage_is_one_line_on_the_console_without_a_serializer_warning(tmp_path):
    """A stage that fails (an unreadable input) is reported as failed, and a notebook's
    console shows it in one-line records:

    - Prefect's attempt to store its exception with the stage serializer, which refuses it
      on purpose, no longer logs "Failed to write result ... You can try a different
      serializer";
    - while the call runs, Prefect's console (the root logger's handlers) drops its two
      tracebacks of the InputError (task run, flow run: ~100 lines before the call's own
      one-line error) and keeps its one-line records and the traceback of any other
      exception; after the call, the user's own flows keep every traceback.
    """
    import logging

    from tumor3d.errors import InputError, MeshError
    from tumor3d.flows.patient import run_patient
    from tumor3d.flows.quiet_logs import NoOwnFailureTracebacks

    bad = tmp_path / "garbage.nii.gz"
    bad.write_bytes(b"not a NIfTI file at all")
    heard: list[tuple[logging.LogRecord, int, bool]] = []

    def ours() -> list[NoOwnFailureTracebacks]:
        return [f for h in logging.getLogger().handlers for f in h.filters
                if isinstance(f, NoOwnFailureTracebacks)]  # fmt: skip

    class Keep(logging.Handler):  # what the console would do with each record, as it comes
        def emit(self, record: logging.LogRecord) -> None:
            filters = ours()
            heard.append((record, len(filters), all(f.filter(record) for f in filters)))

    runs = [logging.getLogger("prefect.task_runs"), logging.getLogger("prefect.flow_runs")]
    keep = Keep(level=logging.DEBUG)
    for logger in runs:
        logger.addHandler(keep)
    try:
        with pytest.raises(InputError) as exc:
            run_patient(bad, tmp_path / "out", modality="t2")
    finally:
        for logger in runs:
            logger.removeHandler(keep)
    seen = [r.getMessage() for r, _, _ in heard]
    assert "garbage.nii.gz" in str(exc.value)
    assert any("garbage" in m or "ingest-scan" in m for m in seen), seen  # the logger was heard
    assert not [m for m in seen if m.startswith("Failed to write result")], seen

    console = logging.getLogger().handlers  # Prefect's console handler, as a notebook's
    assert console and all(n == len(console) for _, n, _ in heard)  # on each, during the call
    tracebacks = [
        (r, s) for r, _, s in heard if r.exc_info and isinstance(r.exc_info[1], InputError)
    ]
    assert {r.name for r, _ in tracebacks} == {"prefect.task_runs", "prefect.flow_runs"}, seen
    assert not [r.getMessage() for r, s in tracebacks if s]
    one_liners = [s for r, _, s in heard if not r.exc_info and r.levelno >= logging.ERROR]
    assert one_liners and all(one_liners), seen  # "Finished in state Failed"
    assert not ours()  # removed after the call: the user's own flows keep their tracebacks

    def record_of(error: Exception) -> logging.LogRecord:
        try:
            raise error
        except type(error):
            return logging.LogRecord("prefect.task_runs", logging.ERROR, __file__, 1, "x", (),
                                     sys.exc_info())  # fmt: skip

    for kept in (RuntimeError("a defect"), MeshError("not a bad input")):
        assert NoOwnFailureTracebacks().filter(record_of(kept))  # their tracebacks are kept

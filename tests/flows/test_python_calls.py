"""Flow runs made from Python (a notebook's ``run_patient``, ``run_cohort``): tagged with
their process, and the Running runs of a killed one set Crashed, as a command's are
(tumor3d.flows.stale_runs; the commands' case: tests/flows/test_cohort_interrupt.py);
on the background server, what they buffered sent before the call returns."""

from __future__ import annotations

import os
import subprocess

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

    from tumor3d.flows import server
    from tumor3d.flows.server import api_of_python_call

    monkeypatch.setattr(server, "_python_sweeps", {})  # this process has not swept yet

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
    monkeypatch.setattr(server, "PYTHON_SWEEP_PERIOD_S", 0.0)  # ... and after it, does
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

    from tumor3d.flows import server
    from tumor3d.flows.patient import run_patient

    info = server.ServerInfo(pid=os.getpid(), port=0, api_url=PREFECT_API_URL.value())
    monkeypatch.setattr(server, "_configured_api_url", lambda: None)  # no PREFECT_API_URL
    monkeypatch.setattr(server, "server_status", lambda: server.ServerStatus("running", "", info))
    (row,) = small_phantom_rows(tmp_path / "in", [3], "nb")
    result = run_patient(row.image, tmp_path / "out", modality=row.modality, patient_id="nb3")
    assert result.metrics["status"] in ("ok", "check")
    senders = {type(w).__name__: w._stopped for w in _QueueServiceBase._instances.values()}
    assert all(senders.values()), f"left running after the call: {senders}"

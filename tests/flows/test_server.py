"""`tumor3d server start|stop|status` and the temporary server that never outlives its command.

Issue 12: after ``kill -9`` of a run that started a temporary Prefect server,
that server kept running (re-parented to PID 1). These tests start real
servers (10-30 s each on a busy machine) with their own state folder
(``TUMOR3D_HOME``) and Prefect home.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

import tumor3d.flows.api_use as api_use
import tumor3d.flows.server as server
from tumor3d.flows.cli import app

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
STARTUP_S = 240


@pytest.fixture
def home(tmp_path, monkeypatch):
    """A private state folder and Prefect home; no configured API URL."""
    monkeypatch.setenv("TUMOR3D_HOME", str(tmp_path / "t3d-home"))
    monkeypatch.setenv("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", str(STARTUP_S))
    # the session's test harness may have set PREFECT_API_URL in Prefect's settings
    monkeypatch.setattr(api_use, "_configured_api_url", lambda: None)
    return tmp_path / "t3d-home"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split(") ")[-1].startswith("Z"))


def _kill_orphaned_servers_of(tmp_path: Path) -> None:
    """SIGKILL the re-parented server processes whose environment names ``tmp_path``."""
    for pid in _server_children(1):
        try:
            ours = str(tmp_path).encode() in Path(f"/proc/{pid}/environ").read_bytes()
        except OSError:
            continue
        if ours:
            os.kill(pid, signal.SIGKILL)


def _wait_gone(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not _alive(pid):
            return True
        time.sleep(0.2)
    return False


def test_a_stale_or_unreadable_state_file_is_said_as_it_is(home):
    """A state file naming a live process that is no server (its id reused) is stale,
    not "gone"; a file that is no server record is unreadable, not "absent" (a user
    audit); status and stop leave the live process alone."""
    home.mkdir(parents=True)
    (home / "server.json").write_text(
        json.dumps({"pid": os.getpid(), "port": 1, "api_url": "http://127.0.0.1:1/api"})
    )
    status = server.server_status()
    assert status.state == "stale"
    assert status.line.endswith(f"process {os.getpid()} is not its server")
    (home / "server.json").write_text('{"pid": ')
    status = server.server_status()
    assert status.state == "stopped" and "unreadable: not a server's record" in status.line
    (home / "server.json").unlink()
    assert server.server_status().line.endswith("server.json absent)")


def test_start_status_use_stop_and_a_stale_state_file(home):
    cli = CliRunner()
    assert server.server_status().state == "stopped"
    status = cli.invoke(app, ["server", "status"])
    assert status.exit_code == 1 and "no tumor3d Prefect server running" in status.output

    started = cli.invoke(app, ["server", "start"])
    assert started.exit_code == 0, started.output
    info = json.loads((home / "server.json").read_text())
    try:
        assert "started" in started.output and info["api_url"] in started.output
        assert server.healthy(info["api_url"])
        status = cli.invoke(app, ["server", "status"])
        assert status.exit_code == 0 and "running and healthy" in status.output
        assert str(info["pid"]) in status.output
        # a second start finds it
        again = cli.invoke(app, ["server", "start"])
        assert again.exit_code == 0 and "already running" in again.output
        assert json.loads((home / "server.json").read_text())["pid"] == info["pid"]
        # later commands use it, and say nothing about starting Prefect
        notes = []
        with api_use.prefect_api(on_temporary_start=lambda: notes.append("temporary")) as url:
            from prefect.settings import PREFECT_API_URL

            assert url == info["api_url"] == PREFECT_API_URL.value()
        assert notes == []
        # it survives the end of the command that started it (its own session)
        assert os.getsid(info["pid"]) == info["pid"]
    finally:
        stopped = cli.invoke(app, ["server", "stop"])
    assert stopped.exit_code == 0 and f"pid {info['pid']}" in stopped.output
    assert _wait_gone(info["pid"], 15)
    assert not (home / "server.json").exists()
    assert server.server_status().state == "stopped"

    # a state file naming a dead process: reported stale, removed by stop
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (home / "server.json").write_text(
        json.dumps({"pid": dead.pid, "port": 1, "api_url": "http://127.0.0.1:1/api"})
    )
    status = cli.invoke(app, ["server", "status"])
    assert status.exit_code == 1 and "stale state file" in status.output
    stopped = cli.invoke(app, ["server", "stop"])
    assert stopped.exit_code == 0 and "removed the stale state file" in stopped.output
    assert not (home / "server.json").exists()


def _server_children(pid: int) -> list[int]:
    """Live processes whose parent is ``pid`` and that run the server module."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            kids = (task / "children").read_text().split()
        except OSError:
            continue
        for kid in kids:
            try:
                cmd = Path(f"/proc/{kid}/cmdline").read_bytes()
            except OSError:
                continue
            if server.SERVER_MODULE.encode() in cmd.split(b"\0"):
                found.append(int(kid))
    return found


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc")
def test_kill_9_of_a_run_leaves_no_temporary_server(home, tmp_path, seed_prefect_home):
    import nibabel as nib
    import numpy as np

    image = tmp_path / "scan.nii.gz"
    data = np.random.default_rng(0).random((32, 32, 6)).astype(np.float32) + 1
    nib.save(nib.Nifti1Image(data, np.diag([1.0, 1.0, 5.0, 1.0])), image)
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(
        TUMOR3D_HOME=str(home),
        PREFECT_HOME=str(seed_prefect_home(tmp_path / "prefect-home")),
        PYTHONPATH=str(ROOT),
        PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS=str(STARTUP_S),
    )
    log = open(tmp_path / "run.log", "wb")  # noqa: SIM115
    run = subprocess.Popen(
        [sys.executable, "-m", "tumor3d.flows.cli", "run", str(image),
         "--out", str(tmp_path / "out")],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        cwd=str(ROOT),
    )
    try:
        deadline = time.monotonic() + STARTUP_S
        child = None
        while time.monotonic() < deadline and run.poll() is None:
            kids = _server_children(run.pid)
            if kids:
                child = kids[0]
                cmd = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
                port = int(cmd[cmd.index(b"--port") + 1])
                if server.healthy(f"http://127.0.0.1:{port}/api", timeout_s=1.0):
                    break
            time.sleep(0.3)
        assert child is not None, (tmp_path / "run.log").read_text()
        assert server.healthy(f"http://127.0.0.1:{port}/api"), "the server never came up"
        # the message is printed because a temporary server really started
        assert "starting Prefect" in (tmp_path / "run.log").read_text()
        run.send_signal(signal.SIGKILL)
        run.wait()
        assert _wait_gone(child, 20), f"temporary server {child} outlived its command"
    finally:
        if run.poll() is None:
            run.kill()
        log.close()
        _kill_orphaned_servers_of(tmp_path)  # never leave ours behind, even if it fails


def test_a_temporary_server_is_stopped_when_its_command_ends(home):
    notes = []
    with api_use.prefect_api(on_temporary_start=lambda: notes.append("temporary")) as url:
        assert notes == ["temporary"]
        assert server.healthy(url)
        port = int(url.rsplit(":", 1)[1].split("/")[0])
    assert not server.healthy(f"http://127.0.0.1:{port}/api", timeout_s=1.0)
    assert server.server_status().state == "stopped"  # no state file for a temporary one


def test_a_python_call_uses_the_background_server_when_none_is_configured(monkeypatch):
    """run_cohort & co. from a notebook: the running background server, as the commands
    (Prefect's own temporary server would open its database beside it: "database is
    locked"); a configured PREFECT_API_URL stays as it is; with neither, the process's own
    temporary server (the next test). The server a call used is the process's API from
    then on, never taken for one the user configured: two overlapping calls from threads,
    the background server stopped between them, restored each other's settings in the
    wrong order and the next call refused the stopped server's URL as PREFECT_API_URL."""
    import prefect.context
    from prefect.settings import PREFECT_API_URL, PREFECT_UI_URL, temporary_settings

    # no API set (a test harness of this process may have set one, in its context and
    # globally); the process's settings and this module's record of them, as they were,
    # after the test
    unset = [PREFECT_API_URL, PREFECT_UI_URL]
    context = prefect.context.GLOBAL_SETTINGS_CONTEXT
    monkeypatch.setattr(prefect.context, "GLOBAL_SETTINGS_CONTEXT", prefect.context.SettingsContext(
        profile=context.profile, settings=context.settings.copy_with_update(restore_defaults=unset)
    ))  # fmt: skip
    with temporary_settings(restore_defaults=unset):
        _calls_from_two_threads(monkeypatch)


def _calls_from_two_threads(monkeypatch):
    import contextlib
    import threading

    from prefect.settings import PREFECT_API_URL, PREFECT_UI_URL, temporary_settings

    monkeypatch.setattr(api_use, "_PROCESS_APIS", set())
    monkeypatch.setattr(api_use, "_PROCESS_API_BEFORE", {})
    background, own = "http://127.0.0.1:9/api", "http://127.0.0.1:7/api"
    state = {"bg": "running"}
    info = server.ServerInfo(pid=1, port=9, api_url=background)
    monkeypatch.setattr(server, "server_status", lambda: server.ServerStatus(
        state["bg"], "state.json", info if state["bg"] == "running" else None))  # fmt: skip
    monkeypatch.setattr(api_use, "python_call_server", lambda: own)
    monkeypatch.setattr(api_use, "check_configured_api", lambda: None)  # (test_python_calls.py)
    # no sweep of these made-up servers (test_python_calls.py checks the sweeps)
    monkeypatch.setattr(api_use, "_this_process_once", lambda url: contextlib.nullcontext())
    real_configured = api_use._configured_api_url
    before = PREFECT_API_URL.value()
    assert before not in (background, own)
    monkeypatch.setattr(api_use, "_configured_api_url", lambda: "http://configured:1/api")
    with api_use.api_of_python_call():
        assert PREFECT_API_URL.value() == before  # a configured API wins: nothing changed
    monkeypatch.setattr(api_use, "_configured_api_url", real_configured)

    inside: dict[str, str | None] = {}
    a_in, b_done = threading.Event(), threading.Event()

    def call_a():  # on the background server, still running while B calls
        with api_use.api_of_python_call():
            inside["a"] = PREFECT_API_URL.value()
            a_in.set()
            b_done.wait(30)

    def call_b():  # a notebook thread's call (no settings context of its own: the global),
        # inside the caller's own temporary settings, made while A's call runs
        with temporary_settings(updates={"logging.level": "INFO"}):
            with api_use.api_of_python_call():
                inside["b"] = PREFECT_API_URL.value()
                inside["b_ui"] = PREFECT_UI_URL.value()
        inside["after"] = PREFECT_API_URL.value()  # the process's API, as a next call reads it
        inside["configured"] = real_configured()  # ... and not taken for the user's

    a = threading.Thread(target=call_a)
    a.start()
    assert a_in.wait(30)
    state["bg"] = "stopped"  # `tumor3d server stop` between the two calls
    b = threading.Thread(target=call_b)
    b.start()
    b.join(30)
    b_done.set()
    a.join(30)
    # B did not take A's background server for a configured one; no UI link on its own
    # server; the process's API from then on is B's, not the stopped one's
    assert inside == {"a": background, "b": own, "b_ui": "", "after": own, "configured": None}


# A notebook's calls, neither API configured nor background server: a call from a thread
# that then ends; the same server asked for again from the main thread; then that server
# killed, and the next call's API.
CALL_FROM_A_THREAD = """
import sys, time
from concurrent.futures import ThreadPoolExecutor
from prefect.settings import PREFECT_API_URL, PREFECT_UI_URL
import tumor3d.flows.api_use as api_use
import tumor3d.flows.server as server
from tumor3d.flows.patient import run_patient

def call():
    result = run_patient(sys.argv[1], sys.argv[2], modality="t2")
    return result.patient_id, api_use.python_call_server()

with ThreadPoolExecutor(1) as pool:
    patient, first = pool.submit(call).result()
# the calling thread has ended: a server it had spawned would stop within a second or two
serving = []
for _ in range(8):
    serving.append(server.healthy(first, timeout_s=2.0))
    time.sleep(0.5)
again = api_use.python_call_server()
process_api = PREFECT_API_URL.value() == first and PREFECT_UI_URL.value() == ""
api_use._CALL_SERVER["proc"].kill()  # found dead by the next call: started again
api_use._CALL_SERVER["proc"].wait()
with api_use.api_of_python_call():
    restarted = PREFECT_API_URL.value()
print(patient, first, again, all(serving), process_api, restarted,
      server.healthy(restarted), api_use._CALL_SERVER["proc"].pid, flush=True)
time.sleep(600)
"""


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads /proc")
def test_a_python_calls_server_outlives_its_calling_thread_not_a_killed_process(
    home, tmp_path, seed_prefect_home
):
    """The temporary server of Python calls (no API configured, no background server) is
    the commands' own: a call made from a thread that then ends leaves it serving the
    next call (it is spawned from a thread that lasts: the kernel's parent-death signal
    follows the spawning thread); it is the process's Prefect API from then on, without
    a UI link (not per call: concurrent calls restored each other's settings in the wrong
    order); a server found dead is started again; and a ``kill -9`` of the process stops
    it (Prefect's own temporary server, used before, outlived a killed notebook kernel)."""
    import select

    from phantom_rows import small_phantom_rows

    row = small_phantom_rows(tmp_path / "in", [0], "call")[0]
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(
        TUMOR3D_HOME=str(home),
        PREFECT_HOME=str(seed_prefect_home(tmp_path / "prefect-home")),
        PYTHONPATH=str(ROOT),
    )
    script = tmp_path / "notebook.py"
    script.write_text(CALL_FROM_A_THREAD)
    log = open(tmp_path / "call.log", "wb")  # noqa: SIM115
    call = subprocess.Popen(
        [sys.executable, str(script), str(row.image), str(tmp_path / "out")],
        env=env, stdout=subprocess.PIPE, stderr=log, cwd=str(ROOT),
    )  # fmt: skip
    try:
        ready, _, _ = select.select([call.stdout], [], [], STARTUP_S)
        line = call.stdout.readline().decode().split() if ready else []
        assert len(line) == 8, (tmp_path / "call.log").read_text()
        patient, first, again, serving, process_api, restarted, healthy, pid = line
        assert (tmp_path / "out" / patient / "metrics.parquet").is_file()  # the call ran
        assert again == first and serving == "True"  # the same server, still serving
        assert process_api == "True"  # the process's API, no UI link
        assert restarted != first and healthy == "True"  # the dead one replaced
        assert server.healthy(restarted)
        assert _server_children(call.pid) == [int(pid)]  # the commands' server module
        assert "View at" not in (tmp_path / "call.log").read_text()
        call.send_signal(signal.SIGKILL)
        call.wait()
        assert _wait_gone(int(pid), 20), f"the calls' server {pid} outlived its process"
    finally:
        if call.poll() is None:
            call.kill()
        log.close()
        _kill_orphaned_servers_of(tmp_path)  # never leave ours behind, even if it fails


def test_the_temporary_server_of_serve_runs_the_scheduler_and_a_commands_does_not(
    monkeypatch, tmp_path
):
    """A temporary server is ephemeral (no services) unless asked for its services: the
    scheduler that makes a served deployment's cron runs. ``tumor3d serve`` asks for them;
    before, it served on an ephemeral server and its cron never fired."""
    from phantom_rows import small_phantom_rows

    import tumor3d.flows.serve
    from tumor3d.storage.manifest import write_manifest

    spawned: list[bool] = []

    class Stop(Exception):
        pass

    def spawn(port, *, parent, ephemeral, log):
        spawned.append(ephemeral)
        raise Stop

    monkeypatch.setattr(api_use, "_configured_api_url", lambda: None)
    monkeypatch.setattr(server, "server_status", lambda: server.ServerStatus("stopped", "s"))
    monkeypatch.setattr(server, "_spawn", spawn)
    for services in (False, True):
        with pytest.raises(Stop), api_use.prefect_api(services=services):
            pass
    assert spawned == [True, False]
    monkeypatch.setattr(tumor3d.flows.serve, "serve_cohort", lambda dep: None)
    manifest = write_manifest(small_phantom_rows(tmp_path, [0], "tmp"), tmp_path / "m.csv")
    args = ["serve", str(manifest), "--out", str(tmp_path / "o"), "--cron", "0 2 * * *"]
    CliRunner().invoke(app, args)
    assert spawned[2:] == [False]  # serve: with the scheduler

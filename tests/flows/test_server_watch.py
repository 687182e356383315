"""A Prefect server that goes away during a command ends it in one line, exit 3 (issue 29).

Prefect's clients retried a killed background server for about 170 s, then
failed with two tracebacks. :func:`tumor3d.flows.server_watch._watch_server` looks at the
server's port while the command runs; nothing listening there three times in
a row ends the command. Run in a child process (it ends with ``os._exit``),
against a plain TCP listener standing in for the server. When the command's own
temporary server stops because a Ctrl-C reached it (SIGINT: it shares the
terminal's process group), the watch leaves the ending to the command's Ctrl-C
handler (one line, exit 130), however late a busy main thread runs it: the server's
runner exits ``EXIT_CTRL_C`` for a SIGINT (run here around a small ASGI app).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = """
import socket, sys, time
import tumor3d.flows.server_watch as s
s._WATCH_PERIOD_S = 0.2
srv = socket.socket(); srv.bind(("127.0.0.1", 0)); srv.listen(8)
port = srv.getsockname()[1]
s.EXIT_HOOKS.append(lambda code: print(f"hook {code}", flush=True))
with s._watch_server(f"http://127.0.0.1:{port}/api"):
    time.sleep(1.5)            # the server answers: nothing happens
    if sys.argv[1] == "kill":
        srv.close()            # the server goes away
    time.sleep(3)              # 15 watch periods: 5x what ends a command
print("body finished", flush=True)
"""


SERVER_PROCESS = """
import signal, socket, subprocess, sys, time
import tumor3d.flows.server_watch as s
s._WATCH_PERIOD_S = 0.2
if len(sys.argv) > 3:
    s._WATCH_CTRL_C_GRACE_S = float(sys.argv[3])
sock = socket.socket(); sock.bind(("127.0.0.1", 0)); port = sock.getsockname()[1]; sock.close()
# the server: the temporary server's own uvicorn runner (tumor3d.flows.server._run_uvicorn)
# around a small ASGI app instead of Prefect's
child = subprocess.Popen([sys.executable, "-c", sys.argv[2], str(port)])
while s._refused(f"http://127.0.0.1:{port}/api"):
    time.sleep(0.05)
with s._watch_server(f"http://127.0.0.1:{port}/api", server=child):
    time.sleep(0.5)
    child.send_signal(signal.SIGINT if sys.argv[1] == "sigint" else signal.SIGKILL)
    time.sleep(2)              # 10 watch periods
print("server exit", child.wait(), flush=True)
print("body finished", flush=True)
"""
APP = """
import sys
import tumor3d.flows.server as s

async def app(scope, receive, send):
    await send({"type": "http.response.start", "status": 200, "headers": []})
    await send({"type": "http.response.body", "body": b"{}"})

s._run_uvicorn(app, int(sys.argv[1]), lifespan="off")
"""

RUN_CTRL_C = """
import contextlib, os, signal, time
import tumor3d.flows.cli.session as session
import tumor3d.flows.patient as patient
import tumor3d.flows.server_watch as server_watch
server_watch.EXIT_HOOKS.append(lambda code: print(f"hook {code}", flush=True))
session._prefect = contextlib.nullcontext  # no server: the command's Ctrl-C handling alone

def run_patient(**kwargs):
    os.kill(os.getpid(), signal.SIGINT)  # a Ctrl-C in the middle of a patient
    time.sleep(5)
    print("run finished", flush=True)

patient.run_patient = run_patient
session._run_with_progress(input_path="x")
print("returned", flush=True)
"""

#: Every command of this module: (script, arguments) by name.
COMMANDS = {
    "killed server": (SCRIPT, ["kill"]),
    "server kept": (SCRIPT, ["keep"]),
    "server ctrl-c": (SERVER_PROCESS, ["sigint", APP]),
    "server killed": (SERVER_PROCESS, ["kill", APP]),
    "server ctrl-c alone": (SERVER_PROCESS, ["sigint", APP, "1.0"]),
    "run ctrl-c": (RUN_CTRL_C, []),
}


@pytest.fixture(scope="module")
def ran():
    """Every command of the module, started together: each mostly sleeps through its watch
    periods, so running them one after another spent about 10 s of a test worker idle."""
    procs = {
        name: subprocess.Popen(
            [sys.executable, "-c", script, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=str(ROOT),
        )
        for name, (script, args) in COMMANDS.items()
    }
    results = {}
    try:
        for name, proc in procs.items():
            out, err = proc.communicate(timeout=60)
            results[name] = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    finally:
        for proc in procs.values():
            proc.kill()
    return results


def test_a_vanished_server_ends_the_command_in_one_line(ran):
    res = ran["killed server"]
    assert res.returncode == 3, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "stopped answering" in lines[0], res.stderr
    # ended by the watch (os._exit in the hook) before the body's own end
    assert "hook 3" in res.stdout and "body finished" not in res.stdout


def test_a_temporary_server_stopped_by_ctrl_c_leaves_the_ending_to_the_command(ran):
    res = ran["server ctrl-c"]
    # the server's runner exits EXIT_CTRL_C for a SIGINT (uvicorn alone: 0), the watch
    # stands down and the body runs on
    assert res.returncode == 0 and "body finished" in res.stdout, res.stderr
    assert "server exit 130" in res.stdout and "stopped answering" not in res.stderr
    killed = ran["server killed"]
    assert killed.returncode == 3 and "stopped answering" in killed.stderr, killed.stderr
    assert "body finished" not in killed.stdout
    # a SIGINT that reached the server alone: once the grace has passed without the
    # command's own Ctrl-C handling, the watch ends the command as for a crash
    alone = ran["server ctrl-c alone"]
    assert alone.returncode == 3 and "stopped answering" in alone.stderr, alone.stderr
    assert "body finished" not in alone.stdout


def test_a_server_that_stays_is_left_alone(ran):
    res = ran["server kept"]
    assert res.returncode == 0, res.stderr
    assert "body finished" in res.stdout and res.stderr.strip() == ""


def test_ctrl_c_during_run_ends_it_in_one_line_exit_130_after_the_exit_hooks(ran):
    """``run`` and ``demo`` (``_run_with_progress``) end at a Ctrl-C as ``cohort`` does: at
    once, one line, exit 130, the exit hooks called first (a background runner's child
    reports its exit code there). They waited for Prefect's engine instead, which retried
    the temporary server the same Ctrl-C had stopped, until the watch ended them with
    exit 3 and "stopped answering"."""
    res = ran["run ctrl-c"]
    assert res.returncode == 130, (res.returncode, res.stderr)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines == ["interrupted: Ctrl-C stopped the run; a re-run continues from the cache"]
    assert "hook 130" in res.stdout and "run finished" not in res.stdout

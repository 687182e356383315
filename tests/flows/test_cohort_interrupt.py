"""Ctrl-C during ``tumor3d cohort`` (issue 29): one line, exit code 130, nothing left behind.

The command runs in its own session with its own temporary Prefect server
(a terminal's Ctrl-C reaches the whole process group: the command and that
server). SIGINT is sent once the first stage has finished. Before the fix it
was still running 30 s later (the lanes and Prefect's services retrying
against the stopped server, printing tracebacks). It must end within seconds
with one line on stderr and exit code 130, leave no process of its own
running, and no staging folder once the cohort has run again.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.manifest import write_manifest
from tumor3d.storage.phantom_io import write_phantom_patient

# Small phantoms (128 x 128 pixels of 1.875 mm, the default field of view, 16 slices):
# what these tests check does not depend on the image size, and a run costs a third.
SMALL = {"n_slices": 16, "matrix_size": (128, 128)}

pytestmark = pytest.mark.slow


def _children(pid: int) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True)
    return [int(v) for v in out.stdout.split()]


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _cohort(manifest, out, home):
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}
    env.update(TUMOR3D_HOME=str(home / "t3d"), PREFECT_HOME=str(home / "prefect"))
    return subprocess.Popen(
        [sys.executable, "-m", "tumor3d.flows.cli", "cohort", str(manifest), "--out", str(out),
         "--workers", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip


@pytest.mark.usefixtures("prefect_harness")  # the re-run: in this process, the tests' server
def test_ctrl_c_during_a_cohort_is_one_line_exit_130_and_leaves_nothing(
    tmp_path, seed_prefect_home
):
    # two patients, one per lane: both are mid-flow when the Ctrl-C comes (the re-run
    # computes what they had not finished)
    rows = [
        write_phantom_patient(
            make_phantom_patient(s, patient_id=f"int{s}", **SMALL), tmp_path / "in" / f"{s}"
        )
        for s in range(2)
    ]
    manifest = write_manifest(rows, tmp_path / "in" / "manifest.csv")
    out = tmp_path / "out"
    seed_prefect_home(tmp_path / "prefect")
    proc = _cohort(manifest, out, tmp_path)
    assert proc.stdout is not None and proc.stderr is not None
    deadline = time.monotonic() + 120
    seen = []
    for line in proc.stdout:  # plain progress lines: patient<TAB>stage<TAB>seconds
        seen.append(line)
        if line.count("\t") == 2 or time.monotonic() > deadline:
            break
    assert any(line.count("\t") == 2 for line in seen), "".join(seen)
    children = _children(proc.pid)
    os.killpg(proc.pid, signal.SIGINT)
    t0 = time.monotonic()
    try:
        rest, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        rest, err = proc.communicate()
        pytest.fail(f"still running 30 s after Ctrl-C; stderr: {err[-2000:]}")
    waited = time.monotonic() - t0
    assert proc.returncode == 130, (proc.returncode, err[-3000:])
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "interrupted" in lines[0], err[-3000:]
    assert "Traceback" not in err and waited < 30
    # its temporary Prefect server shuts down (a few seconds), never outlives it
    end = time.monotonic() + 20
    while [c for c in children if _alive(c)] and time.monotonic() < end:
        time.sleep(0.5)
    assert not [c for c in children if _alive(c)], "a process of the command outlived it"
    # a staging folder of the killed lanes is removed by the next run (what `cohort` calls;
    # in this process, not a second command with a second temporary server)
    from tumor3d.flows.cohort import run_cohort

    again = run_cohort(rows, out, workers=2)
    assert again.exit_code == 0, [p.error for p in again.patients]
    left = [p.name for p in out.iterdir() if ".partial-" in p.name or ".old-" in p.name]
    assert not left, left


@pytest.mark.parametrize(
    ("signum", "code", "line"),
    [
        (signal.SIGINT, 130, "interrupted: Ctrl-C stopped the test; a re-run continues"),
        (signal.SIGTERM, 143, "terminated: SIGTERM stopped the test; a re-run continues"),
    ],
)
def test_sigterm_ends_a_command_as_ctrl_c_does_in_one_line(signum, code, line):
    """``timeout``, systemd and Kubernetes stop a job with SIGTERM: the command ends at
    once with one line on stderr and exit code 143 (it ended silently with 143 before,
    its last line a stage's "failed"), as Ctrl-C ends it with 130.

    The line stays the only one when another thread writes to stderr after it: a log
    record made before the signal (logging is off after it) and written as the command
    ends, as Prefect's events worker did once its server had stopped."""
    script = (
        "import logging, threading, time\n"
        "from tumor3d.flows.cli.errors import _ctrl_c_ends\n"
        "from tumor3d.flows.server_watch import EXIT_HOOKS\n"
        "made, written = threading.Event(), threading.Event()\n"
        "class Late(logging.StreamHandler):\n"
        "    def emit(self, record):\n"
        "        made.set(); written.wait(); super().emit(record)\n"
        "log = logging.getLogger('late'); log.addHandler(Late()); log.propagate = False\n"
        "late = threading.Thread(target=log.error, args=('a service failed',), daemon=True)\n"
        "EXIT_HOOKS.append(lambda code: (written.set(), late.join(10)))\n"
        "with _ctrl_c_ends('Ctrl-C stopped the test; a re-run continues'):\n"
        "    late.start(); made.wait()\n"
        "    print('ready', flush=True)\n"
        "    time.sleep(60)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code
    assert err.strip() == line


def test_the_last_line_is_written_once_and_in_stderrs_own_encoding():
    """A later call (a second Ctrl-C's handler) writes nothing, nor does anything written
    to stderr after the line, and a character stderr cannot encode is escaped as
    Python's stderr escapes it. (Two calls at the same instant, the server watch beside
    a Ctrl-C handler, are kept to one line by a lock this test does not reach.)"""
    script = (
        "import os, sys\n"
        "from tumor3d.flows.server_watch import last_line\n"
        "last_line('stopped: caf\\u00e9')\n"
        "last_line('a second caller')\n"
        "sys.stderr.write('later\\n'); sys.stderr.flush()\n"
        "os._exit(0)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, timeout=60,
        env={**os.environ, "PYTHONIOENCODING": "ascii"},
    )  # fmt: skip
    assert done.returncode == 0 and done.stderr == b"stopped: caf\\xe9\n", done.stderr


@pytest.mark.parametrize("ignored", [False, True])
def test_a_sigint_the_caller_ignored_stays_ignored(ignored):
    """A command started with SIGINT ignored (a shell script's ``tumor3d run ... &``) keeps
    ignoring it, as the warm runner's client did (a user audit: in-process the same run
    stopped); otherwise SIGINT ends it with its line and 130."""

    script = (
        "import os, signal, sys, time\n"
        "from tumor3d.flows.cli.errors import _ctrl_c_ends\n"
        "with _ctrl_c_ends('Ctrl-C stopped the test; a re-run continues'):\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    time.sleep(0.5)\n"
        "    print('went on', flush=True)\n"
        "print('handler back:', signal.getsignal(signal.SIGINT) is signal.SIG_IGN)\n"
    )

    def start() -> None:
        if ignored:
            signal.signal(signal.SIGINT, signal.SIG_IGN)

    done = subprocess.run([sys.executable, "-c", script], preexec_fn=start,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    if ignored:
        assert done.returncode == 0, done.stderr
        assert done.stdout.splitlines() == ["went on", "handler back: True"]
    else:
        assert done.returncode == 130 and "went on" not in done.stdout
        line = "interrupted: Ctrl-C stopped the test; a re-run continues"
        assert done.stderr.strip().endswith(line), done.stderr


def test_on_a_terminal_the_progress_bar_does_not_erase_the_ctrl_c_line():
    """On a terminal the live progress bar is redrawn by its own thread until the process
    exits, each redraw moving the cursor up over the bar: while the interrupted command
    still reported its runs to a persistent server (here an exit hook's 0.3 s) the redraws
    erased its line. Nothing may be written to the terminal after the line."""
    import pty
    import select

    script = (
        "import sys, time\n"
        "from tumor3d.flows.cli.errors import _ctrl_c_ends\n"
        "from tumor3d.flows.cli.output import _progress\n"
        "from tumor3d.flows.server_watch import EXIT_HOOKS\n"
        "EXIT_HOOKS.append(lambda code: time.sleep(0.3))\n"
        "with _ctrl_c_ends('Ctrl-C stopped the test; a re-run continues'):\n"
        "    with _progress() as bars:\n"
        "        for i in range(3):\n"
        "            bars.add_task(f'lane {i}', total=10)\n"
        "        print('ready', file=sys.stderr, flush=True)\n"
        "        time.sleep(60)\n"
    )
    pid, fd = pty.fork()
    if pid == 0:  # the child: a command on a terminal
        os.environ.update(COLUMNS="100", LINES="30", TERM="xterm")
        os.execv(sys.executable, [sys.executable, "-c", script])
    out = b""

    def read(seconds: float, until: bytes | None = None) -> None:
        nonlocal out
        end = time.monotonic() + seconds
        while time.monotonic() < end and (until is None or until not in out):
            if select.select([fd], [], [], 0.05)[0]:
                try:
                    data = os.read(fd, 65536)
                except OSError:  # the child has ended
                    return
                if not data:
                    return
                out += data

    try:
        read(60, until=b"ready")
        assert b"ready" in out, out[-500:]
        read(0.5)  # a few redraws of the bar
        os.kill(pid, signal.SIGINT)
        read(10)
    finally:
        _, status = os.waitpid(pid, 0)
        os.close(fd)
    assert os.waitstatus_to_exitcode(status) == 130, out[-500:]
    line = b"interrupted: Ctrl-C stopped the test; a re-run continues"
    assert line in out, out[-500:]
    assert out.split(line)[-1].strip() == b"", out.split(line)[-1][:300]


@pytest.mark.usefixtures("prefect_harness")
def test_an_interrupted_cohort_is_crashed_on_its_persistent_server(tmp_path):
    """A cohort on a persistent server (``PREFECT_API_URL``; here the tests' server)
    stopped by Ctrl-C: exit 130 in one line, and its flow run is Crashed with that line on
    the server, not Running for good (the runs send no heartbeats; a user audit found them
    Running). SIGTERM is crashed by Prefect's own engine ("Execution was aborted by a
    termination signal"), before the command's line."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterName
    from prefect.settings import PREFECT_API_URL

    rows = [
        write_phantom_patient(
            make_phantom_patient(7, patient_id="term7", **SMALL), tmp_path / "in" / "7"
        )
    ]
    manifest = write_manifest(rows, tmp_path / "in" / "manifest.csv")
    env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(),
           "TUMOR3D_HOME": str(tmp_path / "t3d")}  # fmt: skip
    proc = subprocess.Popen(
        [sys.executable, "-m", "tumor3d.flows.cli", "cohort", str(manifest), "--out",
         str(tmp_path / "termout"), "--workers", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    assert proc.stdout is not None
    for line in proc.stdout:  # plain progress lines: patient<TAB>stage<TAB>seconds
        if line.count("\t") == 2:
            break
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    assert err.strip().startswith("interrupted: Ctrl-C stopped the cohort"), err[-2000:]
    name = FlowRunFilterName(any_=["cohort-termout-1-patients"])
    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(name=name))
    assert len(runs) == 1 and runs[0].state is not None
    assert runs[0].state.is_crashed(), runs[0].state
    assert runs[0].state.message == err.strip()
    # kill -9 (the out-of-memory killer): no line, the run stays Running; the next
    # command on this machine (any entering prefect_api) sets it Crashed, saying why
    from tumor3d.flows.api_use import prefect_api

    proc = subprocess.Popen(
        [sys.executable, "-m", "tumor3d.flows.cli", "cohort", str(manifest), "--out",
         str(tmp_path / "killout"), "--workers", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.count("\t") == 2:
            break
    proc.kill()
    proc.communicate(timeout=60)
    killed = FlowRunFilter(name=FlowRunFilterName(any_=["cohort-killout-1-patients"]))
    with get_client(sync_client=True) as client:
        (run,) = client.read_flow_runs(flow_run_filter=killed)
    assert run.state is not None and run.state.is_running(), run.state
    # a Running run of a process in another pid namespace or boot (a container with the
    # same host name): its process cannot be seen from here, so it is left alone
    from prefect import flow
    from prefect.states import Running

    from tumor3d.flows.stale_runs import PLACE_TAG, PROCESS_TAG

    @flow(name="elsewhere")
    def elsewhere() -> None:  # never run: only its run record
        pass

    other_tags = [f"{PLACE_TAG}another-boot:4026531836", f"{PROCESS_TAG}999999:12345"]
    with get_client(sync_client=True) as client:
        other = client.create_flow_run(elsewhere, name="elsewhere-1", tags=other_tags,
                                       state=Running())  # fmt: skip
    with prefect_api():
        pass
    with get_client(sync_client=True) as client:
        (run,) = client.read_flow_runs(flow_run_filter=killed)
        (first,) = client.read_flow_runs(flow_run_filter=FlowRunFilter(name=name))
    assert run.state is not None and run.state.is_crashed(), run.state
    assert run.state.message.startswith(f"its process ({proc.pid} on "), run.state.message
    assert first.state is not None and first.state.message == err.strip()  # left as it was
    with get_client(sync_client=True) as client:
        assert client.read_flow_run(other.id).state.is_running()

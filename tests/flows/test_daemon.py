"""The warm command runner (issue 32 item 2): ``run``/``demo`` served by a forked copy.

A runner process (``python -m tumor3d.flows.daemon``) with its own state folder; the
console script (:func:`tumor3d.flows.daemon.main`) in separate processes. Checked:
a forwarded command keeps its one-line error and exit code on the client's
own stderr; a client whose environment differs, or that asks to stay
in-process, is not served (the runner's log says which commands it served);
the socket is private.
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tumor3d.flows.daemon import code_fingerprint, socket_path

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
CLIENT = "import sys; from tumor3d.flows.daemon import main; sys.argv[0] = 'tumor3d'; main()"


def _env(home: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("TUMOR3D_", "PREFECT_API"))}
    env.update(TUMOR3D_HOME=str(home), PYTHONPATH=str(ROOT), **extra)
    return env


@pytest.fixture(scope="module")
def runner(tmp_path_factory):
    home = tmp_path_factory.mktemp("home")
    log = open(home / "runner.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(
        [sys.executable, "-m", "tumor3d.flows.daemon"], env=_env(home), stdout=log,
        stderr=subprocess.STDOUT, cwd=str(ROOT),
    )  # fmt: skip
    sock = home / "run.sock"
    deadline = time.monotonic() + 180
    while not sock.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
    assert sock.exists(), (home / "runner.log").read_text()
    yield home
    proc.terminate()
    proc.wait(timeout=30)
    log.close()


def _client(home: Path, args: list[str], cwd: Path, **extra: str):
    return subprocess.run(
        [sys.executable, "-c", CLIENT, *args], env=_env(home, **extra), cwd=str(cwd),
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip


def _served(home: Path) -> int:
    return (home / "runner.log").read_text().count("served run")


def test_a_forwarded_command_keeps_its_error_line_and_exit_code(runner, tmp_path):
    before = _served(runner)
    res = _client(runner, ["run", "missing.nii.gz", "--out", "out"], tmp_path)
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "missing.nii.gz" in lines[0], res.stderr
    assert _served(runner) == before + 1
    assert not (tmp_path / "out").exists()
    # a relative path is the client's: found there (and refused for its content)
    (tmp_path / "junk.nii.gz").write_bytes(b"not a nifti")
    res = _client(runner, ["run", "junk.nii.gz", "--out", "out"], tmp_path)
    assert res.returncode == 2 and "no such file" not in res.stderr, res.stderr
    assert "junk.nii.gz" in res.stderr and _served(runner) == before + 2


def test_another_environment_or_no_daemon_runs_in_process(runner, tmp_path):
    before = _served(runner)
    res = _client(runner, ["run", "missing.nii.gz", "--out", "out"], tmp_path,
                  TUMOR3D_DATA_DIR="/elsewhere")  # fmt: skip
    assert res.returncode == 2
    assert "not used (another environment (TUMOR3D_DATA_DIR))" in res.stderr
    res = _client(runner, ["run", "missing.nii.gz", "--out", "out"], tmp_path,
                  TUMOR3D_NO_DAEMON="1")  # fmt: skip
    assert res.returncode == 2 and "runner" not in res.stderr
    assert _served(runner) == before


def test_the_socket_is_private(runner):
    mode = stat.S_IMODE((runner / "run.sock").stat().st_mode)
    assert mode & 0o077 == 0, oct(mode)


def test_the_fingerprint_follows_the_files(tmp_path, monkeypatch):
    pkg = tmp_path / "tumor3d"
    pkg.mkdir()
    f = pkg / "a.py"
    f.write_text("x = 1\n")
    first = code_fingerprint(tmp_path)
    os.utime(f, ns=(f.stat().st_atime_ns, f.stat().st_mtime_ns + 10**9))
    assert code_fingerprint(tmp_path) != first
    monkeypatch.setenv("TUMOR3D_HOME", str(tmp_path / "h"))
    assert socket_path() == tmp_path / "h" / "run.sock"


def test_a_client_without_stdin_runs_in_process(runner, tmp_path):
    """A scheduled job may have no standard input: not served, never a traceback."""
    before = _served(runner)
    res = subprocess.run(
        [sys.executable, "-c", "import sys; assert sys.stdin is None; " + CLIENT, "run",
         "missing.nii.gz", "--out", "out"],
        env=_env(runner), cwd=str(tmp_path), capture_output=True, text=True, timeout=300,
        preexec_fn=lambda: os.close(0),  # fd 0 closed: Python starts with sys.stdin None
    )  # fmt: skip
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert _served(runner) == before


def test_sigterm_to_the_client_ends_the_forwarded_command_in_one_line(runner, tmp_path):
    """``timeout`` or systemd stop the client with SIGTERM: it relays it to the forked
    command (in a session of its own, which the signal would not reach), which ends as
    in-process: one line, exit code 143. The client died silently with 143 before, the
    command going on without it."""
    import signal

    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_patient

    patient = make_phantom_patient(2, n_slices=8, matrix_size=(64, 64), patient_id="term")
    image = write_phantom_patient(patient, tmp_path / "in").image
    proc = subprocess.Popen(
        [sys.executable, "-c", CLIENT, "run", str(image), "--out", "out"],
        env=_env(runner), cwd=str(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    assert proc.stdout is not None
    for line in proc.stdout:  # the command is under way: its Prefect server is starting
        if "starting Prefect" in line:
            break
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("terminated: SIGTERM stopped"), err[-2000:]
    assert not (tmp_path / "out" / "term").exists()

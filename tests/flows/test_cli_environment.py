"""A failure inside the flow is one line on the console, with the environment exit code.

Issue 12: a full disk ended in a 228-line traceback. Prefect's flow engine
logs a failed run's exception with its traceback at ERROR; the command must
print only its own one-line error (the record still reaches the server).
The command runs in a child process (a real console), against the test
harness's Prefect server.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]

ROOT = Path(__file__).resolve().parents[2]

FULL_DISK = textwrap.dedent(
    """
    import errno, sys
    import tumor3d.storage.store as store

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    store.atomic_write_bytes = full  # the disk is full from the first artifact on
    from tumor3d.flows.cli import app
    sys.argv = ["tumor3d", *sys.argv[1:]]
    app()
    """
)


def test_full_disk_inside_the_flow_is_one_line_exit_3_and_no_traceback(tmp_path):
    from prefect.settings import PREFECT_API_URL

    image = tmp_path / "scan.nii.gz"
    data = np.random.default_rng(0).random((24, 24, 6)).astype(np.float32) + 1
    nib.save(nib.Nifti1Image(data, np.diag([1.0, 1.0, 5.0, 1.0])), image)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PREFECT_API_URL": PREFECT_API_URL.value()}
    env["TUMOR3D_HOME"] = str(tmp_path / "home")
    out = tmp_path / "out"
    res = subprocess.run(
        [sys.executable, "-c", FULL_DISK, "run", str(image), "--out", str(out)],
        env=env, capture_output=True, text=True, timeout=600, cwd=str(ROOT),
    )  # fmt: skip
    assert res.returncode == 3, res.stdout + res.stderr
    assert "Traceback" not in res.stderr and "Traceback" not in res.stdout
    errors = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(errors) == 1, res.stderr
    assert "cannot write the artifact (no space left on device (ENOSPC))" in errors[0]
    assert "starting Prefect" not in res.stdout  # the harness's server was used
    assert not (out / "scan").exists()


@pytest.mark.parametrize("command", ["run", "cohort"])
def test_a_prefect_api_url_pointing_at_nothing_is_one_line_exit_3(tmp_path, command):
    """Issue 29: 137 lines, three tracebacks and a .tumor3d-store left behind."""
    import socket

    image = tmp_path / "scan.nii.gz"
    data = np.random.default_rng(0).random((24, 24, 6)).astype(np.float32) + 1
    nib.save(nib.Nifti1Image(data, np.diag([1.0, 1.0, 5.0, 1.0])), image)
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        dead = f"http://127.0.0.1:{s.getsockname()[1]}/api"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PREFECT_API_URL": dead}
    env["TUMOR3D_HOME"] = str(tmp_path / "home")
    out = tmp_path / "out"
    target = image
    if command == "cohort":
        target = tmp_path / "m.csv"
        target.write_text(f"patient_id,image,modality\np1,{image},t2\n")
    res = subprocess.run(
        [sys.executable, "-m", "tumor3d.flows.cli", command, str(target), "--out", str(out)],
        env=env, capture_output=True, text=True, timeout=300, cwd=str(ROOT),
    )  # fmt: skip
    assert res.returncode == 3, res.stdout + res.stderr
    assert "Traceback" not in res.stdout + res.stderr
    errors = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and dead in errors[0] and "PREFECT_API_URL" in errors[0], res.stderr
    assert not (out / ".tumor3d-store").exists()

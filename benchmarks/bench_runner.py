"""Benchmark: `tumor3d run` through the warm runner against the same command in-process.

Both with the background server up (``tumor3d server start`` in a temporary
``TUMOR3D_HOME``), on one default phantom (31 x 256 x 256), each run a fresh
``tumor3d`` process timed from outside. First a cold run through the runner
and a cold run in-process (each into its own fresh store and output), then
``--repeats`` interleaved pairs of the same cached run (runner, then
``TUMOR3D_NO_DAEMON=1``). Reports the medians, their ratio and the load.

Usage::

    python benchmarks/bench_runner.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TUMOR3D = str(Path(sys.executable).with_name("tumor3d"))


def _timed(args: list[str], env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    res = subprocess.run([TUMOR3D, *args], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode not in (0, 4):
        raise SystemExit(f"tumor3d {' '.join(args)} failed ({res.returncode}): {res.stderr}")
    return wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_patient

    tmp = Path(tempfile.mkdtemp(prefix="bench-runner-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("TUMOR3D_", "PREFECT_API"))}
    env["TUMOR3D_HOME"] = str(tmp / "home")
    row = write_phantom_patient(make_phantom_patient(0, patient_id="bench"), tmp / "in")
    subprocess.run([TUMOR3D, "server", "start"], env=env, check=True, capture_output=True)
    try:
        sock = tmp / "home" / "run.sock"
        deadline = time.monotonic() + 180
        while not sock.exists() and time.monotonic() < deadline:
            time.sleep(0.5)
        load0 = os.getloadavg()[0]
        run = ["run", str(row.image), "--patient-id", "bench"]
        cold_runner = _timed([*run, "--out", str(tmp / "o1"), "--store", str(tmp / "s1")], env)
        off = {**env, "TUMOR3D_NO_DAEMON": "1"}
        cold_inproc = _timed([*run, "--out", str(tmp / "o2"), "--store", str(tmp / "s2")], off)
        warm, inproc = [], []
        for _ in range(args.repeats):
            warm.append(_timed([*run, "--out", str(tmp / "o1"), "--store", str(tmp / "s1")], env))
            inproc.append(_timed([*run, "--out", str(tmp / "o1"), "--store", str(tmp / "s1")], off))
        load1 = os.getloadavg()[0]
    finally:
        subprocess.run([TUMOR3D, "server", "stop"], env=env, capture_output=True)
    mw, mi = statistics.median(warm), statistics.median(inproc)
    print(f"load average {load0:.1f} -> {load1:.1f}, {os.cpu_count()} cores")
    print("| run | median wall (s) | all (s) |")
    print("|---|---|---|")
    print(f"| cold, runner | {cold_runner:.2f} | {cold_runner:.2f} |")
    print(f"| cold, in-process | {cold_inproc:.2f} | {cold_inproc:.2f} |")
    print(f"| cached, runner | {mw:.2f} | {', '.join(f'{v:.2f}' for v in warm)} |")
    print(f"| cached, in-process | {mi:.2f} | {', '.join(f'{v:.2f}' for v in inproc)} |")
    print(f"cached runner / in-process: {mw / mi:.2f}; cold: {cold_runner / cold_inproc:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

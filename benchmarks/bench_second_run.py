"""Wall time of `tumor3d run` as a user sees it: with the background server, and without.

    python benchmarks/bench_second_run.py [--repeat 3]

One default phantom patient (30 slices). Each run is a fresh ``tumor3d run``
process (imports, preflight, flow, publishing, exit), timed from outside:

* cold, server up: a new output folder and store (numba's on-disk cache warm);
* cached, server up: the same output again (every stage a cache hit, the
  published folder up to date: nothing rewritten);
* cached, republished: the same after deleting the folder's publish manifest
  (``.tumor3d-publish-key.json``), so the folder is written again as every
  cached run did before the up-to-date check;
* cached, temporary server: the same, after ``tumor3d server stop`` (each
  command starts and stops its own server).

The state folder and Prefect home are private temporary folders. Prints a
Markdown table with medians and the ratio of each to the temporary-server
run (the peer measured in the same script), and the machine's load.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tumor3d(*args: str, env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "tumor3d.flows.cli", *args],
        env=env, cwd=str(ROOT), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="tumor3d-bench-second-"))
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(
        TUMOR3D_HOME=str(tmp / "home"), PREFECT_HOME=str(tmp / "prefect"), PYTHONPATH=str(ROOT)
    )
    env.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "240")
    times: dict[str, list[float]] = {"cold": [], "cached": [], "republished": [], "temporary": []}
    try:
        _tumor3d("phantom", "--out", str(tmp / "in"), "--n", "1", env=env)
        image = str(tmp / "in" / "phantom000" / "phantom000_t2.nii.gz")
        load_before = os.getloadavg()
        start = _tumor3d("server", "start", env=env)
        _tumor3d("run", image, "--out", str(tmp / "warm"), env=env)  # numba cache, DB warm
        for i in range(args.repeat):
            times["cold"].append(_tumor3d("run", image, "--out", str(tmp / f"cold{i}"), env=env))
            times["cached"].append(_tumor3d("run", image, "--out", str(tmp / "warm"), env=env))
            (tmp / "warm" / "phantom000_t2" / ".tumor3d-publish-key.json").unlink()
            t = _tumor3d("run", image, "--out", str(tmp / "warm"), env=env)
            times["republished"].append(t)
        _tumor3d("server", "stop", env=env)
        for _ in range(max(1, args.repeat - 1)):
            t = _tumor3d("run", image, "--out", str(tmp / "warm"), env=env)
            times["temporary"].append(t)
        load_after = os.getloadavg()
    finally:
        subprocess.run(
            [sys.executable, "-m", "tumor3d.flows.cli", "server", "stop"], env=env, cwd=str(ROOT),
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        shutil.rmtree(tmp, ignore_errors=True)
    peer = statistics.median(times["temporary"])
    load = f"{load_before[0]:.1f} -> {load_after[0]:.1f}"
    print(f"server start-up: {start:.1f} s; load average {load}")
    print("| run | median wall (s) | all (s) | / cached with temporary server |")
    print("|---|---|---|---|")
    labels = {
        "cold": "cold, background server up",
        "cached": "cached, background server up",
        "republished": "cached, background server up, folder republished",
        "temporary": "cached, temporary server",
    }
    for key, label in labels.items():
        med = statistics.median(times[key])
        runs = ", ".join(f"{t:.1f}" for t in times[key])
        print(f"| {label} | {med:.1f} | {runs} | {med / peer:.2f} |")


if __name__ == "__main__":
    main()

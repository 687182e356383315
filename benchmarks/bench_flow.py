"""Benchmark: the single-patient flow on a 31-slice phantom, and Prefect's share.

Peers, run alternately in one process after a warm-up (numba compilation,
Open3D shader compilation):

* ``direct``: the nine stage functions called in order without Prefect
  (each task's undecorated function, ``task.fn``, through the flow's own
  wiring :func:`tumor3d.flows.patient.run_stages`), same store, same I/O;
* ``flow, cold``: ``run_patient`` into a fresh store (every stage computes);
* ``flow, cached``: ``run_patient`` again (every stage a cache hit).

Reported: median seconds per stage, the flow's wall time, the share of the
cold flow's wall time spent outside stage computation (Prefect's task
orchestration, result persistence, publishing), and ratios against the
direct peer. The Prefect server is started once beforehand and its start-up
is reported separately.

Usage::

    python benchmarks/bench_flow.py [--repeats 3] [--report reports/benchmarks.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.flows.patient import run_patient, run_stages_direct  # noqa: E402
from tumor3d.phantom import make_phantom_patient  # noqa: E402
from tumor3d.storage.phantom_io import write_phantom_patient  # noqa: E402
from tumor3d.tasks import stages  # noqa: E402

N_SLICES = 31


def run_direct(image_path: Path, store_root: Path) -> dict[str, float]:
    """All stages without Prefect (same wiring as the flow); seconds per stage."""
    return run_stages_direct(image_path, store_root, patient_id="bench").seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--report", type=Path, default=ROOT / "reports" / "benchmarks.md")
    args = parser.parse_args()

    from prefect.testing.utilities import prefect_test_harness

    work = Path(tempfile.mkdtemp(prefix="tumor3d-bench-"))
    os.environ["PREFECT_HOME"] = str(work / "prefect-home")
    patient = make_phantom_patient(0, n_slices=N_SLICES, patient_id="bench")
    image = write_phantom_patient(patient, work / "inputs").image
    print(f"phantom: {patient.scan.shape} (z, y, x), true volume {patient.true_volume_mm3:.0f} mm3")

    run_direct(image, work / "warmup-store")  # numba + Open3D warm-up
    t0 = time.perf_counter()
    with prefect_test_harness(server_startup_timeout=120):
        server_s = time.perf_counter() - t0
        direct, cold, cold_wall, cached_wall = [], [], [], []
        for i in range(args.repeats):
            direct.append(run_direct(image, work / f"direct-{i}"))
            t = time.perf_counter()
            res = run_patient(image, work / f"flow-{i}", patient_id="bench")
            cold_wall.append(time.perf_counter() - t)
            cold.append({s.stage: s.compute_seconds for s in res.stages})
            assert not any(res.cache_hits)
            t = time.perf_counter()
            res2 = run_patient(image, work / f"flow-{i}", patient_id="bench")
            cached_wall.append(time.perf_counter() - t)
            assert all(res2.cache_hits)
            print(
                f"repeat {i + 1}: direct {sum(direct[-1].values()):.2f} s, "
                f"flow cold {cold_wall[-1]:.2f} s, cached {cached_wall[-1]:.2f} s"
            )

    med = statistics.median
    names = list(stages.STAGES)
    direct_total = med(sum(d.values()) for d in direct)
    compute_total = med(sum(c.values()) for c in cold)
    cold_med, cached_med = med(cold_wall), med(cached_wall)
    overhead_share = 1.0 - compute_total / cold_med
    lines = [
        "## Single-patient flow, 31-slice phantom",
        "",
        f"Produced by `python benchmarks/bench_flow.py --repeats {args.repeats}` "
        f"(or `make bench`) on {time.strftime('%Y-%m-%d')}, {platform.machine()}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()}; "
        f"{subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True, text=True, cwd=ROOT).stdout.strip() or 'no git'}. "  # noqa: E501
        f"Phantom seed 0, {patient.scan.shape[0]} x {patient.scan.shape[1]} x "
        f"{patient.scan.shape[2]} (z, y, x), 2 mm slices + 3 mm gap. "
        f"Medians of {args.repeats} alternating repeats after a warm-up; the machine is shared, "
        "so read the ratios, not the seconds.",
        "",
        "| stage | direct (s) | in flow, computed (s) |",
        "|---|---:|---:|",
    ]
    for n in names:
        lines.append(f"| {n} | {med(d[n] for d in direct):.3f} | {med(c[n] for c in cold):.3f} |")
    lines += [
        f"| **sum of stages** | **{direct_total:.3f}** | **{compute_total:.3f}** |",
        "",
        "| measure | value |",
        "|---|---:|",
        f"| flow wall time, cold (s) | {cold_med:.2f} |",
        f"| flow wall time, all cache hits (s) | {cached_med:.2f} |",
        f"| share of cold wall time outside stage computation (Prefect + publishing) | "
        f"{100 * overhead_share:.0f} % |",
        f"| cold flow / direct stages | {cold_med / direct_total:.2f} x |",
        f"| cached flow / direct stages | {cached_med / direct_total:.2f} x |",
        f"| Prefect temporary server start-up, once per process (s) | {server_s:.1f} |",
        "",
    ]
    text = "\n".join(lines)
    args.report.parent.mkdir(parents=True, exist_ok=True)
    old = args.report.read_text() if args.report.exists() else "# Benchmarks\n"
    # replace this benchmark's own section only (bench_cohort.py writes another)
    pattern = re.compile(r"^## Single-patient flow.*?(?=^## |\Z)", re.S | re.M)
    if pattern.search(old):
        new = pattern.sub(lambda _: text + "\n", old)
    else:
        new = old.rstrip("\n") + "\n\n" + text + "\n"
    args.report.write_text(new)
    print(text)


if __name__ == "__main__":
    main()

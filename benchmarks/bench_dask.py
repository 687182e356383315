"""Benchmark: the cohort flow on Dask (1 and 2 workers) against the local thread runner.

Peers, in one process, one temporary Prefect server, every run cold (a fresh
output folder and store, so every stage computes):

* ``local, 1 lane`` / ``local, 2 lanes``: the default ``ThreadPoolTaskRunner``;
* ``dask, 1 worker`` / ``dask, 2 workers``: ``--dask-workers N``, a temporary
  ``distributed.LocalCluster`` of N worker *processes* (one thread each)
  started inside the run; its start-up and each worker's first-call numba
  compilation are part of the wall time, as a user sees it.

A warm-up run (one patient, local) compiles numba in this process first.
Reported: wall time of each, speed-up 1 -> 2 for both runners, Dask against
local at the same width, and the time each patient's lane spent outside its
stage tasks (preparing the input, publishing: work of the flow's own process,
which does not scale with Dask workers). The machine may be shared: read the
ratios.

Usage::

    python benchmarks/bench_dask.py [--n 20] [--report reports/benchmarks.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]
)  # Dask worker processes import this checkout

from _cohort_bench import replace_report_section, write_phantom_cohort  # noqa: E402

from tumor3d.flows.cohort import run_cohort  # noqa: E402
from tumor3d.flows.dask_runner import DaskSpec  # noqa: E402

SECTION = "## Dask runner scaling"


def _outside_stages_s(result) -> float:
    """Mean per patient of lane time outside its stage tasks (prepare + publish)."""
    # lane wall is not recorded per patient; the flow's wall x lanes minus stage walls
    stage_wall = sum(s.wall_seconds for p in result.patients for s in p.stages)
    return max(0.0, result.wall_seconds * result.workers - stage_wall) / len(result.patients)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20, help="phantom patients")
    parser.add_argument("--report", type=Path, default=ROOT / "reports" / "benchmarks.md")
    parser.add_argument(
        "--widths", type=int, nargs="+", default=[1, 2], help="lanes / Dask workers to compare"
    )
    args = parser.parse_args()

    from prefect.testing.utilities import prefect_test_harness

    work = Path(tempfile.mkdtemp(prefix="tumor3d-bench-dask-"))
    os.environ["PREFECT_HOME"] = str(work / "prefect-home")
    rows = write_phantom_cohort(args.n, "bd", work)

    peers = [(f"local, {w} lane{'s' if w > 1 else ''}", w, None) for w in args.widths] + [
        (f"dask, {w} worker{'s' if w > 1 else ''}", None, DaskSpec(n_workers=w))
        for w in args.widths
    ]
    width = {name: (lanes or dask.n_workers) for name, lanes, dask in peers}
    wall: dict[str, float] = {}
    outside: dict[str, float] = {}
    compute: dict[str, float] = {}
    with prefect_test_harness(server_startup_timeout=240):
        run_cohort(rows[:1], work / "warmup", workers=1)
        for i, (name, lanes, dask) in enumerate(peers):
            t = time.perf_counter()
            res = run_cohort(rows, work / f"out{i}", workers=lanes, dask=dask)
            wall[name] = time.perf_counter() - t
            assert res.exit_code == 0, [p.error for p in res.failed]
            assert not any(s.cached for p in res.patients for s in p.stages)
            outside[name] = _outside_stages_s(res)
            compute[name] = sum(s.compute_seconds or 0.0 for p in res.patients for s in p.stages)
            print(f"{name}: {wall[name]:.1f} s")

    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
    ).stdout.strip()
    lines = [
        SECTION,
        "",
        f"Produced by `python benchmarks/bench_dask.py --n {args.n} --widths "
        f"{' '.join(map(str, args.widths))}` on "
        f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores (shared "
        f"with other jobs: read the ratios; load average {os.getloadavg()[0]:.1f} at the end), "
        f"Python {platform.python_version()}; "
        f"{commit or 'no git'}. {args.n} default phantoms (30 slices of 256 x 256), every run "
        "cold (fresh store), one temporary Prefect server; Dask runs start a LocalCluster of "
        "worker processes (one thread each) inside the run, start-up included.",
        "",
        "| runner | wall time (s) | per patient (s) | lane time outside stages, per patient (s) "
        "| orchestration, 1 - compute / (width x wall) |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, _, _ in peers:
        share = 1.0 - compute[name] / (wall[name] * width[name])
        lines.append(
            f"| {name} | {wall[name]:.1f} | {wall[name] / args.n:.2f} | {outside[name]:.2f} "
            f"| {100 * share:.0f} % |"
        )
    w0 = args.widths[0]
    l0 = wall[next(n for n, lanes, _ in peers if lanes == w0)]
    d0 = wall[next(n for n, _, d in peers if d is not None and d.n_workers == w0)]
    lines += ["", "| ratio | value |", "|---|---:|"]
    for w in args.widths:
        lw = wall[next(n for n, lanes, _ in peers if lanes == w)]
        dw = wall[next(n for n, _, d in peers if d is not None and d.n_workers == w)]
        if w != w0:
            lines.append(f"| local speed-up, {w0} -> {w} lanes | {l0 / lw:.2f} x |")
            lines.append(f"| Dask speed-up, {w0} -> {w} workers | {d0 / dw:.2f} x |")
        lines.append(f"| Dask {w} / local {w} (wall) | {dw / lw:.2f} |")
    lines.append("")
    section = "\n".join(lines) + "\n"
    report = args.report
    report.parent.mkdir(parents=True, exist_ok=True)
    old = report.read_text() if report.exists() else "# Benchmarks\n"
    report.write_text(replace_report_section(old, SECTION, section))
    print(section)


if __name__ == "__main__":
    main()

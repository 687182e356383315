"""Benchmark: the cohort flow on N phantom patients with W workers, and where its time goes.

Peers, in one process after a warm-up (numba compilation, Open3D start):

* ``direct``: every patient's nine stages called in order without Prefect
  (:func:`tumor3d.flows.patient.run_stages_direct`), one patient after another;
* ``cohort, cold``: :func:`tumor3d.flows.cohort.run_cohort` into a fresh output folder
  and store (every stage computes), ``W`` patients at a time;
* ``cohort, cached``: the same call again (every stage a cache hit; the
  published folders already hold this result, so nothing is rewritten);
* ``cohort, cached, republished``: the same once more after deleting every
  patient's publish manifest (``.tumor3d-publish-key.json``), so each folder is
  written again, as every cached re-run did before the up-to-date check.

Reported:

* the share of the cold cohort's lane time outside stage computation,
  ``1 - sum(compute) / (W x wall)`` (``compute`` = each stage's own timing
  inside its task);
* the same against the direct peer, ``1 - (direct / W) / wall`` (the ideal
  wall time if the W lanes ran on W free cores);
* where the overhead goes, summed over the patients: per stage,
  submission-to-result wall time minus compute time (Prefect's task run,
  result persistence, and waiting for a worker: the cohort keeps one patient
  more in flight than it has workers, ``tumor3d.flows.cohort.EXTRA_LANES``);
  publishing (``PatientOutcome.publish_seconds``: the products read back, the
  files encoded and written); the rest of each lane (the input's digest, the
  runner's bookkeeping);
* the same share without publishing, ``1 - (compute + publish) / (W x wall)``;
* the cached re-run as a fraction of the cold time.

The temporary Prefect server is started once beforehand; its start-up is
reported separately and excluded. The machine may be shared: read ratios.

Usage::

    python benchmarks/bench_cohort.py [--n 20] [--workers 2] [--report reports/benchmarks.md]
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cohort_bench import replace_report_section, write_phantom_cohort  # noqa: E402

from tumor3d.flows.cohort import run_cohort  # noqa: E402
from tumor3d.flows.patient import run_stages_direct  # noqa: E402
from tumor3d.storage.publish import PUBLISH_MANIFEST  # noqa: E402
from tumor3d.tasks import stages  # noqa: E402

SECTION = "## Cohort flow"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20, help="phantom patients")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", type=Path, default=ROOT / "reports" / "benchmarks.md")
    args = parser.parse_args()

    from prefect.testing.utilities import prefect_test_harness

    work = Path(tempfile.mkdtemp(prefix="tumor3d-bench-cohort-"))
    os.environ["PREFECT_HOME"] = str(work / "prefect-home")
    rows = write_phantom_cohort(args.n, "bc", work)

    run_stages_direct(rows[0].image, work / "warmup", patient_id=rows[0].patient_id)
    t = time.perf_counter()
    for row in rows:
        run_stages_direct(row.image, work / "direct-store", patient_id=row.patient_id)
    direct_s = time.perf_counter() - t
    print(f"direct: {direct_s:.1f} s")

    t0 = time.perf_counter()
    with prefect_test_harness(server_startup_timeout=180):
        server_s = time.perf_counter() - t0
        t = time.perf_counter()
        cold = run_cohort(rows, work / "out", workers=args.workers)
        cold_s = time.perf_counter() - t
        assert cold.exit_code == 0, [p.error for p in cold.failed]
        print(f"cohort cold: {cold_s:.1f} s")
        t = time.perf_counter()
        cached = run_cohort(rows, work / "out", workers=args.workers)
        cached_s = time.perf_counter() - t
        assert all(s.cached for p in cached.patients for s in p.stages)
        print(f"cohort cached: {cached_s:.1f} s")
        for row in rows:
            (work / "out" / row.patient_id / PUBLISH_MANIFEST).unlink()
        t = time.perf_counter()
        again = run_cohort(rows, work / "out", workers=args.workers)
        republished_s = time.perf_counter() - t
        assert all(s.cached for p in again.patients for s in p.stages)
        print(f"cohort cached, republished: {republished_s:.1f} s")

    names = list(stages.STAGES)
    compute = {n: 0.0 for n in names}
    orchestration = {n: 0.0 for n in names}
    lane_stage_wall = 0.0
    for p in cold.patients:
        for s in p.stages:
            compute[s.stage] += s.compute_seconds
            orchestration[s.stage] += s.wall_seconds - s.compute_seconds
            lane_stage_wall += s.wall_seconds
    compute_total = sum(compute.values())
    lane_total = args.workers * cold_s
    outside_share = 1.0 - compute_total / lane_total
    direct_share = 1.0 - (direct_s / args.workers) / cold_s
    orch_total = sum(orchestration.values())
    publish_total = sum(p.publish_seconds for p in cold.patients)
    lane_busy = sum(p.lane_seconds for p in cold.patients)
    rest = lane_busy - lane_stage_wall  # publishing, input digests
    prepare_total = rest - publish_total
    no_publish_share = 1.0 - (compute_total + publish_total) / lane_total
    n = args.n
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
    ).stdout.strip()
    lines = [
        SECTION,
        "",
        f"Produced by `python benchmarks/bench_cohort.py --n {args.n} --workers {args.workers}` "
        f"(or `make bench-cohort`) on {time.strftime('%Y-%m-%d')}, {platform.machine()}, "
        f"{os.cpu_count()} cores (shared with other jobs: read the ratios), Python "
        f"{platform.python_version()}; {commit or 'no git'}. {args.n} default phantoms "
        "(seeds 0.., 30 slices of 256 x 256), one temporary Prefect server.",
        "",
        "| measure | value |",
        "|---|---:|",
        f"| direct stages, patients one after another (s) | {direct_s:.1f} |",
        f"| cohort wall time, cold, {args.workers} workers (s) | {cold_s:.1f} |",
        f"| cohort wall time, all cache hits (s) | {cached_s:.1f} |",
        f"| cached re-run / cold | {100 * cached_s / cold_s:.1f} % |",
        f"| cohort wall time, all cache hits, every folder republished (s) | {republished_s:.1f} |",
        f"| cached re-run republishing / cold | {100 * republished_s / cold_s:.1f} % |",
        f"| share of lane time outside stage computation, 1 - compute / (workers x wall) | "
        f"{100 * outside_share:.1f} % |",
        f"| same against the direct peer, 1 - (direct / workers) / wall | "
        f"{100 * direct_share:.1f} % |",
        "| Prefect per-task overhead and waiting for a worker (stage wall - compute), "
        f"summed (s) | {orch_total:.1f} |",
        f"| lane time outside stage tasks (prepare, publish), summed (s) | {rest:.1f} |",
        f"| of which publishing, summed (s; per patient) | {publish_total:.1f}; "
        f"{publish_total / n:.2f} |",
        f"| of which input digest and runner bookkeeping, summed (s; per patient) | "
        f"{prepare_total:.1f}; {prepare_total / n:.2f} |",
        f"| Prefect per-task overhead and waiting, per patient (s) | {orch_total / n:.2f} |",
        f"| share without publishing, 1 - (compute + publish) / (workers x wall) | "
        f"{100 * no_publish_share:.1f} % |",
        f"| Prefect temporary server start-up, excluded (s) | {server_s:.1f} |",
        "",
        "| stage | compute, all patients (s) | orchestration, all patients (s) |",
        "|---|---:|---:|",
    ]
    for n in names:
        lines.append(f"| {n} | {compute[n]:.2f} | {orchestration[n]:.2f} |")
    lines.append("")
    section = "\n".join(lines) + "\n"
    report = args.report
    report.parent.mkdir(parents=True, exist_ok=True)
    old = report.read_text() if report.exists() else "# Benchmarks\n"
    report.write_text(replace_report_section(old, SECTION, section))
    print(section)


if __name__ == "__main__":
    main()

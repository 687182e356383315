"""Benchmark: a cohort of N rows of one and the same file (issue 29, everyday).

Every row names the same phantom image under another patient id. Stage keys
that depend on content only compute the pipeline once (per concurrent lane)
and serve every other row from the cache; keys that depend on the patient id
compute it N times. Reported: the cohort's wall time, the stage results that
were cache hits, and the stages' summed compute time, all from a fresh store
and output folder, under one temporary Prefect server (its start-up excluded).

Usage::

    python benchmarks/bench_same_file_cohort.py [--n 20] [--workers 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cohort_bench import write_phantom_cohort  # noqa: E402

from tumor3d.flows.cohort import run_cohort  # noqa: E402
from tumor3d.flows.patient import run_stages_direct  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20, help="rows (patient ids) of the one file")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()

    from prefect.testing.utilities import prefect_test_harness

    work = Path(tempfile.mkdtemp(prefix="tumor3d-bench-same-file-"))
    os.environ["PREFECT_HOME"] = str(work / "prefect-home")
    (one,) = write_phantom_cohort(1, "same", work)
    rows = [dataclasses.replace(one, patient_id=f"row{i:03d}") for i in range(args.n)]
    run_stages_direct(one.image, work / "warmup", patient_id="warmup")  # numba compilation

    t0 = time.perf_counter()
    with prefect_test_harness(server_startup_timeout=180):
        server_s = time.perf_counter() - t0
        t = time.perf_counter()
        result = run_cohort(rows, work / "out", workers=args.workers)
        wall_s = time.perf_counter() - t
    assert not result.failed, [p.error for p in result.failed]
    runs = [s for p in result.patients for s in p.stages]
    hits = sum(s.cached for s in runs)
    computed = [s for s in runs if not s.cached]
    compute_s = sum(s.compute_seconds for s in computed)
    per_stage: dict[str, int] = {}
    for s in computed:
        per_stage[s.stage] = per_stage.get(s.stage, 0) + 1
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
    ).stdout.strip()
    print(f"commit {commit or 'no git'}, {args.n} rows of one file, {args.workers} workers")
    print(f"cohort wall time: {wall_s:.1f} s (server start-up {server_s:.1f} s excluded)")
    print(f"stage cache hits: {hits} of {len(runs)}")
    print(f"stages computed: {len(computed)}, their compute time summed: {compute_s:.1f} s")
    print("computed per stage: " + ", ".join(f"{k} {v}" for k, v in per_stage.items()))


if __name__ == "__main__":
    main()

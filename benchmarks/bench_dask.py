"""Benchmark: the cohort flow on Dask (1, 2, 4 workers) against the local thread runner.

Peers, in one process, one temporary Prefect server, every run cold (a fresh
output folder and store, so every stage computes):

* ``local, 1 worker`` / ``local, 2 workers``: the default ``ThreadPoolTaskRunner``
  of that many threads (the cohort keeps one patient more in flight,
  ``tumor3d.flows.cohort.EXTRA_LANES``, so a worker does not wait while a
  patient is published);
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

Memory per worker: the peak resident set (``VmHWM``) of the flow's own
process during each run (its high-water mark reset through
``/proc/self/clear_refs`` before the run; it holds the local lanes, and on Dask
the scheduler and the publishing) and of every Dask worker process (sampled
from ``/proc/<pid>/status`` every 0.2 s while the run lasts; ``VmHWM`` only
grows, so the last sample before the worker exits is its peak).

Each ``--n`` writes its own ``### <n> phantom patients`` subsection of the
report's section (``..., local runner only`` / ``..., Dask only`` with one
``--runners``); the other subsections and the hand-written reading
(``### Where Dask pays off``) are kept.

Usage::

    python benchmarks/bench_dask.py [--n 20] [--widths 1 2 4] [--runners local dask]
                                    [--report reports/benchmarks.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import tempfile
import threading
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

import psutil  # noqa: E402
from _cohort_bench import replace_report_section, write_phantom_cohort  # noqa: E402

from tumor3d.flows.cohort import run_cohort  # noqa: E402
from tumor3d.flows.dask_runner import DaskSpec  # noqa: E402

SECTION = "## Dask runner scaling"
RUNNERS = ("local", "dask")
MIB = 1024.0


def _vm_hwm_kib(pid: int | str = "self") -> float | None:
    """Peak resident set (``VmHWM``, KiB) of a process, None once it has gone."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1])
    except OSError:
        return None
    return None


class WorkerPeaks:
    """Peak RSS of the worker processes this process spawns while the block runs, and the load.

    A thread samples the ``VmHWM`` of every descendant started after entry
    whose command line is a multiprocessing spawn (Dask's worker processes;
    the Prefect server and the resource tracker are not counted).
    """

    def __init__(self, period_s: float = 0.2) -> None:
        self.period_s = period_s
        self.peak_kib: dict[int, float] = {}
        self.load: list[float] = []  # 1-minute load average, each sample
        self._stop = threading.Event()
        self._me = psutil.Process()
        self._before: set[int] = set()
        self._workers: set[int] = set()
        self._others: set[int] = set()

    def _sample(self) -> None:
        self.load.append(os.getloadavg()[0])
        for child in self._me.children(recursive=True):
            pid = child.pid
            if pid in self._before or pid in self._others:
                continue
            if pid not in self._workers:
                try:
                    cmd = " ".join(child.cmdline())
                except psutil.Error:
                    continue
                if "spawn_main" not in cmd and "forkserver" not in cmd:
                    self._others.add(pid)
                    continue
                self._workers.add(pid)
            hwm = _vm_hwm_kib(pid)
            if hwm is not None:
                self.peak_kib[pid] = max(hwm, self.peak_kib.get(pid, 0.0))

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            self._sample()

    def __enter__(self) -> WorkerPeaks:
        self._before = {c.pid for c in self._me.children(recursive=True)}
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def _outside_stages_s(result) -> float:
    """Mean per patient of lane time outside its stage tasks (input digest, publishing)."""
    outside = [p.lane_seconds - sum(s.wall_seconds for s in p.stages) for p in result.patients]
    return sum(outside) / len(outside)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20, help="phantom patients")
    parser.add_argument("--report", type=Path, default=ROOT / "reports" / "benchmarks.md")
    parser.add_argument(
        "--widths", type=int, nargs="+", default=[1, 2], help="lanes / Dask workers to compare"
    )
    parser.add_argument(
        "--runners", nargs="+", choices=RUNNERS, default=list(RUNNERS), help="which runners to run"
    )
    args = parser.parse_args()

    from prefect.testing.utilities import prefect_test_harness

    work = Path(tempfile.mkdtemp(prefix="tumor3d-bench-dask-"))
    os.environ["PREFECT_HOME"] = str(work / "prefect-home")
    rows = write_phantom_cohort(args.n, "bd", work)
    load_start = os.getloadavg()[0]

    peers = [
        (f"local, {w} worker{'s' if w > 1 else ''}", w, None)
        for w in args.widths
        if "local" in args.runners
    ] + [
        (f"dask, {w} worker{'s' if w > 1 else ''}", None, DaskSpec(n_workers=w))
        for w in args.widths
        if "dask" in args.runners
    ]
    width = {name: (lanes or dask.n_workers) for name, lanes, dask in peers}
    wall: dict[str, float] = {}
    outside: dict[str, float] = {}
    compute: dict[str, float] = {}
    flow_peak_mib: dict[str, float] = {}
    flow_start_mib: dict[str, float] = {}
    load_range: dict[str, tuple[float, float]] = {}
    worker_peaks_mib: dict[str, list[float]] = {}
    with prefect_test_harness(server_startup_timeout=240):
        run_cohort(rows[:1], work / "warmup", workers=1)
        for i, (name, lanes, dask) in enumerate(peers):
            with open("/proc/self/clear_refs", "w") as fh:
                fh.write("5")  # reset this process's VmHWM to its current RSS
            flow_start_mib[name] = psutil.Process().memory_info().rss / MIB / 1024.0
            t = time.perf_counter()
            with WorkerPeaks() as peaks:
                res = run_cohort(rows, work / f"out{i}", workers=lanes, dask=dask)
            wall[name] = time.perf_counter() - t
            flow_peak_mib[name] = (_vm_hwm_kib() or 0.0) / MIB
            worker_peaks_mib[name] = [v / MIB for v in peaks.peak_kib.values()]
            load_range[name] = (min(peaks.load, default=0.0), max(peaks.load, default=0.0))
            assert res.exit_code == 0, [p.error for p in res.failed]
            assert not any(s.cached for p in res.patients for s in p.stages)
            outside[name] = _outside_stages_s(res)
            compute[name] = sum(s.compute_seconds or 0.0 for p in res.patients for s in p.stages)
            print(
                f"{name}: {wall[name]:.1f} s, flow process peak {flow_peak_mib[name]:.0f} MiB, "
                f"workers {[round(v) for v in worker_peaks_mib[name]]} MiB",
                flush=True,
            )

    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
    ).stdout.strip()
    load = os.getloadavg()[0]
    only = "" if set(args.runners) == set(RUNNERS) else f" --runners {' '.join(args.runners)}"
    scope = "" if not only else ("local runner only" if "local" in args.runners else "Dask only")
    lines = [
        f"### {args.n} phantom patients" + (f", {scope}" if scope else ""),
        "",
        f"Produced by `nice -n 10 python benchmarks/bench_dask.py --n {args.n} --widths "
        f"{' '.join(map(str, args.widths))}{only}` on "
        f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores (shared "
        f"with other jobs: read the ratios; load average {load_start:.1f} at the start, "
        f"{load:.1f} at the end), Python {platform.python_version()}; {commit or 'no git'}.",
        "",
        "| runner | wall time (s) | per patient (s) | lane time outside stages, per patient (s) "
        "| orchestration, 1 - compute / (width x wall) | flow process peak RSS (at start) (MiB) "
        "| worker peak RSS, max / mean (MiB) | load average during the run, min - max |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, _, dask in peers:
        share = 1.0 - compute[name] / (wall[name] * width[name])
        wp = worker_peaks_mib[name]
        workers_cell = (
            f"{max(wp):.0f} / {sum(wp) / len(wp):.0f} ({len(wp)} processes)"
            if dask is not None and wp
            else ("not found" if dask is not None else "(threads of the flow process)")
        )
        lines.append(
            f"| {name} | {wall[name]:.1f} | {wall[name] / args.n:.2f} | {outside[name]:.2f} "
            f"| {100 * share:.0f} % | {flow_peak_mib[name]:.0f} ({flow_start_mib[name]:.0f}) "
            f"| {workers_cell} | {load_range[name][0]:.1f} - {load_range[name][1]:.1f} |"
        )
    local = {lanes: wall[n] for n, lanes, _ in peers if lanes is not None}
    dask_wall = {d.n_workers: wall[n] for n, _, d in peers if d is not None}
    w0 = args.widths[0]
    lines += ["", "| ratio | value |", "|---|---:|"]
    for w in args.widths:
        if w != w0 and local:
            lines.append(f"| local speed-up, {w0} -> {w} workers | {local[w0] / local[w]:.2f} x |")
        if w != w0 and dask_wall:
            lines.append(
                f"| Dask speed-up, {w0} -> {w} workers | {dask_wall[w0] / dask_wall[w]:.2f} x |"
            )
        if local and dask_wall:
            lines.append(f"| Dask {w} / local {w} (wall) | {dask_wall[w] / local[w]:.2f} |")
    lines.append("")
    subsection = "\n".join(lines) + "\n"
    report = args.report
    report.parent.mkdir(parents=True, exist_ok=True)
    old = report.read_text() if report.exists() else "# Benchmarks\n"
    report.write_text(
        replace_report_section(old, SECTION, _merged_section(old, subsection, args.n, scope))
    )
    print(subsection)


def _merged_section(report_text: str, subsection: str, n: int, only: str = "") -> str:
    """The report's Dask section with the ``### <n> phantom patients[, <only>]`` one replaced.

    ``only``: ``"local runner only"`` / ``"Dask only"`` for a one-runner run, which
    keeps its own subsection beside the size's two-runner one. Other subsections
    (other cohort sizes, the hand-written reading) are kept; a new one goes
    before the reading, in increasing order of size.
    """
    match = re.search(rf"^{re.escape(SECTION)}\n.*?(?=^## |\Z)", report_text, re.S | re.M)
    body = match.group(0) if match else f"{SECTION}\n\n"
    parts = re.split(r"(?=^### )", body, flags=re.M)
    head, subs = parts[0], parts[1:]
    sized: dict[tuple[int, str], str] = {}
    rest = []
    for part in subs:
        m = re.match(r"### (\d+) phantom patients(?:, (.+))?\n", part)
        if m:
            sized[(int(m.group(1)), m.group(2) or "")] = part
        else:
            rest.append(part)
    sized[(n, only)] = subsection + "\n"
    return head + "".join(sized[k] for k in sorted(sized)) + "".join(rest)


if __name__ == "__main__":
    main()

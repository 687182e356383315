"""Reads of the input per ``tumor3d run``: twice (check, then ingest) against once (handed over).

Before issue 31 item 4 the command line read the input to check it (one
line for a bad input before Prefect starts) and the ingest-scan stage read
it again. Now the check keeps its scan (:func:`read_and_keep`) and the stage
takes it (:func:`take_kept`), after checking the input's file-system
signature. This times, in one process, both paths on the same input:

* ``two reads``: ``read_scan`` (the check) + ``read_noting`` (the stage);
* ``one read``: ``read_and_keep`` + ``take_kept`` (signatures included).

Inputs: the demo patient's NIfTI (``tumor3d demo``'s phantom, seed 7), and,
with ``--size``, a larger synthetic volume (gzipped NIfTI). Run::

    nice -n 10 .venv/bin/python benchmarks/bench_read_once.py --repeats 5 --size 256 256 160
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import nibabel as nib
import numpy as np

from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.storage.readers import ReadOptions, read_scan
from tumor3d.storage.readers.handoff import read_and_keep, read_noting, take_kept


def _two_reads(path: Path, options: ReadOptions) -> float:
    t0 = time.perf_counter()
    read_scan(path, options)
    read_noting(path, options)
    return time.perf_counter() - t0


def _one_read(path: Path, options: ReadOptions) -> float:
    t0 = time.perf_counter()
    read_and_keep(path, options)
    kept = take_kept(path, options)
    assert kept is not None, "the kept scan was not handed over"
    return time.perf_counter() - t0


def _measure(name: str, path: Path, repeats: int) -> None:
    options = ReadOptions(modality="t2")
    read_scan(path, options)  # warm: imports, page cache
    two = [_two_reads(path, options) for _ in range(repeats)]
    one = [_one_read(path, options) for _ in range(repeats)]
    m2, m1 = statistics.median(two), statistics.median(one)
    size_mb = path.stat().st_size / 1e6
    print(
        f"| {name} | {size_mb:.1f} MB | {m2:.3f} s | {m1:.3f} s | {m2 - m1:.3f} s | "
        f"{m2 / m1:.2f}x |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--size", type=int, nargs=3, metavar=("X", "Y", "Z"), default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        row = write_phantom_patient(make_phantom_patient(7, patient_id="demo007"), Path(tmp))
        print("| input | file | two reads (median) | one read | saved | ratio |")
        print("|---|---|---|---|---|---|")
        _measure("demo phantom (seed 7)", row.image, args.repeats)
        if args.size:
            rng = np.random.default_rng(0)
            data = (rng.random(tuple(args.size), dtype=np.float32) * 1000).astype(np.int16)
            big = Path(tmp) / "big.nii.gz"
            nib.save(nib.Nifti1Image(data, np.diag([0.9, 0.9, 1.5, 1.0])), big)
            _measure("x".join(map(str, args.size)) + " int16", big, args.repeats)


if __name__ == "__main__":
    main()

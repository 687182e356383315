"""Benchmark: the NIfTI encoder's deflate, ISA-L (``isal.igzip``, level 1) against zlib level 6.

zlib at level 6 through Python's ``gzip`` module is the encoder before this change.
Both peers run in one process, alternately:

1. **Volumes.** The same uncompressed NIfTI bytes are deflated by both peers
   ``--repeat`` times (min and median ms, compressed size as a fraction of the raw
   bytes, and the inflate times); the inflated bytes are checked equal to the raw ones.
   Volumes: a default phantom's scan (float32, 3 % Rician noise) and its fine truth
   mask (uint8); with the real data (``TUMOR3D_DATA_DIR``, default ``../shared/data``),
   a BraTS 2018 FLAIR volume (240 x 240 x 155) and a clinical LGG FLAIR head as
   acquired.
2. **Every stage of a patient** without Prefect
   (:func:`tumor3d.flows.patient.run_stages_direct`, a fresh store each time, so every
   artifact is encoded; in one process the next stage takes a volume from the memo of
   decoded products, so nothing is inflated): the default phantom and, with the data,
   the LGG head, ``--pairs`` pairs, each peer first in every other pair (the first
   pair a warm-up, not counted).

Prints the figures; the machine may be shared: read the ratios.

Usage::

    python benchmarks/bench_nifti_gzip.py [--repeat 7] [--pairs 4]
"""

from __future__ import annotations

import argparse
import contextlib
import gzip
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace

import nibabel as nib
import numpy as np
from isal import igzip

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cohort_bench import write_phantom_cohort  # noqa: E402

from tumor3d.flows.patient import run_stages_direct  # noqa: E402
from tumor3d.phantom import make_phantom_patient  # noqa: E402
from tumor3d.storage import nifti  # noqa: E402

ZLIB_LEVEL = 6  # the encoder before: gzip.compress(raw, compresslevel=6, mtime=0)

#: The module ``tumor3d.storage.nifti`` deflates and inflates through, as each peer.
PEERS: dict[str, SimpleNamespace] = {
    "zlib level 6": SimpleNamespace(
        compress=lambda raw, compresslevel, mtime: gzip.compress(
            raw, compresslevel=ZLIB_LEVEL, mtime=mtime
        ),
        decompress=gzip.decompress,
    ),
    f"ISA-L level {nifti._GZIP_LEVEL}": igzip,
}


@contextlib.contextmanager
def deflate_with(peer: SimpleNamespace) -> Iterator[None]:
    """``tumor3d.storage.nifti`` encodes and decodes with ``peer`` inside the block."""
    before = nifti.igzip
    nifti.igzip = peer  # type: ignore[assignment]
    try:
        yield
    finally:
        nifti.igzip = before


def _ms(fn: Callable[[], object], repeat: int) -> tuple[float, float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(1000.0 * (time.perf_counter() - t0))
    return min(times), statistics.median(times), out


def volumes(data_dir: Path | None) -> dict[str, bytes]:
    """Uncompressed NIfTI bytes of the benchmark's volumes."""
    phantom = make_phantom_patient(0)
    scan = phantom.scan.image.astype(np.float32)
    out = {
        f"phantom scan, float32 {scan.shape}": nib.Nifti1Image(scan, np.eye(4)).to_bytes(),
        f"phantom fine truth mask, uint8 {phantom.fine_mask.shape}": nib.Nifti1Image(
            phantom.fine_mask.astype(np.uint8), np.eye(4)
        ).to_bytes(),
    }
    if data_dir is not None:
        brats = sorted((data_dir / "brats2018").glob("*/flair.nii.gz"))[0]
        lgg = sorted((data_dir / "lgg_flair").glob("*/flair.nii.gz"))[0]
        for label, path in (("BraTS 2018 FLAIR", brats), ("LGG FLAIR head", lgg)):
            img = nib.load(str(path))
            arr = np.asarray(img.dataobj, dtype=np.float32)
            out[f"{label} {path.parent.name}, float32 {arr.shape}"] = nib.Nifti1Image(
                arr, img.affine
            ).to_bytes()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--pairs", type=int, default=4)
    args = parser.parse_args()
    data_dir = Path(os.environ.get("TUMOR3D_DATA_DIR", ROOT.parent / "shared" / "data"))
    if not (data_dir / "brats2018").is_dir() or not (data_dir / "lgg_flair").is_dir():
        print(f"no real data under {data_dir}: the phantom only")
        data_dir = None

    print("## deflate of one volume (min / median ms over the repeats; size / raw size)")
    for name, raw in volumes(data_dir).items():
        cells = []
        for label, peer in PEERS.items():
            lo, med, packed = _ms(
                lambda peer=peer, raw=raw: peer.compress(
                    raw, compresslevel=nifti._GZIP_LEVEL, mtime=0
                ),
                args.repeat,
            )
            lo_in, _, unpacked = _ms(lambda p=packed, peer=peer: peer.decompress(p), args.repeat)
            assert unpacked == raw
            cells.append((label, lo, med, len(packed) / len(raw), lo_in))
        (la, a_lo, a_med, a_r, a_in), (lb, b_lo, b_med, b_r, b_in) = cells
        print(
            f"{name} ({len(raw) / 1e6:.1f} MB): {la} {a_lo:.0f} / {a_med:.0f} ms, {a_r:.3f}; "
            f"{lb} {b_lo:.0f} / {b_med:.0f} ms, {b_r:.3f}; deflate {a_lo / b_lo:.1f}x faster, "
            f"inflate {a_in:.0f} -> {b_in:.0f} ms"
        )

    work = Path(tempfile.mkdtemp(prefix="tumor3d-bench-nifti-"))
    try:
        inputs = [("default phantom", write_phantom_cohort(1, "gz", work)[0].image, "t2")]
        if data_dir is not None:
            lgg = sorted(data_dir.glob("lgg_flair/*/flair.nii.gz"))[0]
            inputs.append((f"LGG FLAIR head {lgg.parent.name}", lgg, "flair"))
        print("\n## every stage of one patient, without Prefect (s; first pair a warm-up)")
        for name, path, modality in inputs:
            walls: dict[str, list[float]] = {label: [] for label in PEERS}
            for i in range(args.pairs + 1):
                order = list(PEERS.items())
                for label, peer in order if i % 2 else order[::-1]:  # each first in turn
                    store = work / "store"
                    shutil.rmtree(store, ignore_errors=True)
                    with deflate_with(peer):
                        t0 = time.perf_counter()
                        run_stages_direct(path, store, patient_id="bench", modality=modality)
                        wall = time.perf_counter() - t0
                    if i:
                        walls[label].append(wall)
            (la, a), (lb, b) = walls.items()
            print(
                f"{name}: {la} median {statistics.median(a):.2f} s, {lb} median "
                f"{statistics.median(b):.2f} s: {statistics.median(a) / statistics.median(b):.2f}x "
                f"(pairs: {', '.join(f'{x / y:.2f}' for x, y in zip(a, b, strict=True))})"
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

"""Benchmark: encode_png against Pillow's PNG (level 6), on a phantom's overlays and renders.

One default phantom (seed 0) is run through the stages without Prefect
(:func:`tumor3d.flows.patient.run_stages_direct`); its two overlay mosaics (the
arrays :func:`tumor3d.storage.patient_outputs.overlay_png` encodes) and its eight
PNG renders are then encoded by both peers in one process, alternately,
``--repeat`` times (min and median reported, with the bytes; the pixels are
checked equal). Then publishing the patient (:func:`tumor3d.tasks.publish.
publish_results`, the folder rewritten each time) with either encoder,
``--pairs`` pairs alternated (the first pair is a warm-up). Prints the figures;
the machine may be shared: read the ratios.

Usage::

    python benchmarks/bench_png.py [--repeat 7] [--pairs 12]
"""

from __future__ import annotations

import argparse
import io
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cohort_bench import write_phantom_cohort  # noqa: E402

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.flows.patient import prepare_source, run_stages_direct  # noqa: E402
from tumor3d.segmentation.review import review_status  # noqa: E402
from tumor3d.storage import patient_outputs  # noqa: E402
from tumor3d.storage.derivatives import PatientProducts  # noqa: E402
from tumor3d.storage.formats import decode_png, encode_png  # noqa: E402
from tumor3d.storage.publish import PUBLISH_MANIFEST  # noqa: E402
from tumor3d.storage.store import ArtifactStore  # noqa: E402
from tumor3d.tasks.publish import metrics_row, publish_results, run_notes  # noqa: E402


def pillow_png(rgb: np.ndarray) -> bytes:
    """The peer: Pillow's PNG at its default zlib level (the encoder before 773236a)."""
    sink = io.BytesIO()
    Image.fromarray(rgb).save(sink, format="PNG", optimize=False)
    return sink.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--pairs", type=int, default=12)
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="tumor3d-bench-png-"))
    row = write_phantom_cohort(1, "png", work)[0]
    runner = run_stages_direct(row.image, work / "store", patient_id=row.patient_id)
    store = ArtifactStore(work / "store")
    outputs = runner.outputs
    products = PatientProducts(store, {k: o.artifacts for k, o in outputs.items()}, {}, {})

    overlays: list[np.ndarray] = []
    patient_outputs.encode_png = lambda rgb: overlays.append(rgb) or b""  # type: ignore[assignment]
    image, affine = products.volume("preprocess.enhanced")
    for name in ("overlay_tumor.png", "overlay_brain.png"):
        patient_outputs.overlay_png(
            name, image, affine, products.volume("preprocess.brain_mask")[0],
            products.volume("segment-tumor.tumor_mask_slices")[0], products.abnormal_slices,
        )  # fmt: skip
    renders = [
        decode_png(store.get_bytes(ref))
        for ref in outputs["render-views"].artifacts.values()
        if ref.relpath.endswith(".png")
    ]
    load = os.getloadavg()[0]
    print(f"load average {load:.1f}")
    for label, images in (("overlays", overlays), ("renders", renders)):
        shape = " x ".join(str(v) for v in images[0].shape)
        for peer in (pillow_png, encode_png):
            times = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                data = [peer(a) for a in images]
                times.append(time.perf_counter() - t)
            for a, d in zip(images, data, strict=True):
                assert np.array_equal(decode_png(d), a)
            kb = sum(map(len, data)) / 1e3
            print(
                f"{len(images)} {label} ({shape}), {peer.__name__}: {kb:.0f} kB, "
                f"min {min(times) * 1e3:.1f} ms, median {statistics.median(times) * 1e3:.1f} ms"
            )

    cfg = parse_config({})
    source = prepare_source(row.image, patient_id=row.patient_id)
    notes, doubts = run_notes(outputs)
    review = review_status(doubts, segmentation=outputs["segment-tumor"].values)
    metrics = metrics_row(outputs, runner.runs, row.patient_id, 1.0, notes, review)
    publish: dict[str, list[float]] = {"pillow_png": [], "encode_png": []}
    for k in range(args.pairs):
        for peer in (pillow_png, encode_png):
            patient_outputs.encode_png = peer  # type: ignore[assignment]
            out = work / f"out-{peer.__name__}"
            (out / row.patient_id / PUBLISH_MANIFEST).unlink(missing_ok=True)
            t = time.perf_counter()
            publish_results(store, out, source, outputs, runner.runs, metrics, cfg)
            if k:
                publish[peer.__name__].append(time.perf_counter() - t)
    old, new = (statistics.median(publish[p]) for p in ("pillow_png", "encode_png"))
    print(
        f"publishing one patient, {args.pairs - 1} pairs: pillow_png median {old:.3f} s, "
        f"encode_png median {new:.3f} s, ratio {new / old:.2f}; "
        f"load average {load:.1f} -> {os.getloadavg()[0]:.1f}"
    )


if __name__ == "__main__":
    main()

"""Speed of preprocess + detect + segment: the default and the robust method against the peer.

Runs the three configurations in the same process on the same 155 x 240 x 240
volume (``$TUMOR3D_DATA_DIR/brats2013_pat0003/flair.nii.gz`` when present,
else a smooth synthetic head of that size with a bright blob), ``--repeat``
times each, interleaved, and prints the median seconds per stage and the
ratios to the peer (the machine is shared and noisy: only the ratio is
meaningful). The default (``configs/default.yaml``) runs the learned method on FLAIR with
the shipped models (forest + U-Net ensemble, as the segment stage does); the robust method
is ``configs/robust.yaml`` (the rule-based lesion model, the default on FLAIR before the
learned one, issue 7's 2 s target); ``bench_learned.py`` times the learned inference
alone on 31 slices. Detect and segment get the scan's
voxel spacing and left-right axis, as the stage adapters pass them (so the lesion
model's depth and symmetry rules run, the mid-sagittal plane search included). Not a test.

Usage::

    TUMOR3D_DATA_DIR=/work/shared/data python benchmarks/bench_segmentation.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.imaging.preprocess import preprocess_volume  # noqa: E402
from tumor3d.segmentation.detect import detect_abnormal_slices  # noqa: E402
from tumor3d.segmentation.lesion import left_right_axis  # noqa: E402
from tumor3d.segmentation.patient import method_models  # noqa: E402
from tumor3d.segmentation.segment import segment_tumor  # noqa: E402
from tumor3d.storage.manifest import data_dir  # noqa: E402


def _volume() -> tuple[np.ndarray, tuple[float, float, float], int | None, str]:
    """(image, spacing_mm (z, y, x), left-right axis, description)."""
    f = data_dir() / "brats2013_pat0003" / "flair.nii.gz"
    if f.is_file():
        from tumor3d.storage.readers import read_scan

        scan = read_scan(f, modality="flair")
        spacing = (scan.slice_step_mm, *scan.pixel_spacing_mm)
        return scan.image, spacing, left_right_axis(scan.affine), str(f)
    rng = np.random.default_rng(0)
    z, y, x = np.mgrid[:155, :240, :240].astype(np.float32)
    r = np.sqrt(((z - 77) / 70) ** 2 + ((y - 120) / 95) ** 2 + ((x - 120) / 80) ** 2)
    vol = np.where(r < 1, 100.0, 0.0) + rng.normal(0, 5, r.shape) * (r < 1)
    vol[((z - 80) ** 2 + (y - 100) ** 2 + (x - 140) ** 2) < 20**2] = 200.0
    return vol.astype(np.float32), (1.0, 1.0, 1.0), 2, "synthetic 155x240x240 head"


def _run(image: np.ndarray, spacing_mm, lr_axis, cfg) -> dict[str, float]:
    t = {}
    geometry = {"spacing_mm": spacing_mm, "lr_axis": lr_axis}
    t0 = time.perf_counter()
    pre = preprocess_volume(image, **cfg.preprocess.model_dump(), spacing_mm=spacing_mm)
    t["preprocess"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    det = detect_abnormal_slices(
        pre.enhanced, pre.brain_mask, modality="flair", **geometry, **cfg.detect.model_dump()
    )
    t["detect"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # the default's learned method with the shipped models, as the segment stage gives them
    learned = method_models(
        cfg.segment.method, "flair", det, lambda: image, cfg.segment.learned_cnn
    )
    segment_tumor(
        pre.enhanced,
        pre.brain_mask,
        det,
        modality="flair",
        **geometry,
        **cfg.segment.model_dump(),
        **learned,
    )
    t["segment"] = time.perf_counter() - t0
    t["total"] = sum(t.values())
    return t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    image, spacing_mm, lr_axis, what = _volume()
    configs = {
        "default": parse_config((ROOT / "configs" / "default.yaml").read_text()),
        "robust": parse_config((ROOT / "configs" / "robust.yaml").read_text()),
        "peer": parse_config((ROOT / "configs" / "peer_multiotsu.yaml").read_text()),
    }
    times: dict[str, list[dict[str, float]]] = {k: [] for k in configs}
    for _ in range(max(1, args.repeat)):
        for name, cfg in configs.items():
            times[name].append(_run(image, spacing_mm, lr_axis, cfg))
    print(f"volume: {what}, shape {image.shape}, {args.repeat} repeats (median seconds)")
    med = {}
    for name, runs in times.items():
        med[name] = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        print(f"  {name:<8} " + "  ".join(f"{k}={v:.2f}" for k, v in med[name].items()))
    for name in ("default", "robust"):
        print(f"  ratio {name} / peer (total): {med[name]['total'] / med['peer']['total']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Invariances of the default pipeline on the labelled real cases (issue 7).

For every labelled case of ``benchmarks/real_segmentation.py`` (2 mm every 5 mm,
offset 2), the per-slab Dice of the segmented slabs against the slab reference
(``mean label >= 0.5``) for the image as given and for:

- **mirrored**: flipped along its left-right array axis, the resulting mask
  flipped back before scoring; the symmetry rule must not prefer a side: the
  masks should agree exactly (skipped when the affine gives no left-right
  array axis);
- **linear**: ``3 x + 100`` (a different scanner scale or z-scoring); the
  8-bit windowing works on foreground percentiles, so nothing should change;
- **bias y / bias z**: a smooth multiplicative field of +-15 % across the
  head along the in-plane axis that is not left-right (anterior-posterior on
  axial slices) / along the slices, on the intensities shifted
  to start at 0 (background kept): what an uncorrected receive-coil bias does;
- **reversed**: the slab stack in reverse order (the head upside down along the
  slices), the mask reversed back: nothing in the pipeline should prefer a slice
  direction, so the masks should agree exactly (column "reversed masks agree");
- **0.5 mm pixels**: every slab resampled in-plane to half the pixel size (linear
  interpolation, ``scipy.ndimage.zoom``) with the spacing halved, the mask averaged
  back over 2 x 2 pixels (>= 0.5) before scoring: the lesion model's lengths and
  areas are millimetres, so the result should stay close to the one at 1 mm;
- **noise 8 %**: Rician noise (two Gaussian components of SD 8 % of the brain's median
  gray, on the intensities shifted to start at 0, background kept): a clinical scan's
  lower signal-to-noise ratio than BraTS's;
- **5 mm slabs**: contiguous 5 mm slabs every 5 mm (each the mean of five 1 mm slices, so
  thicker partial volume than the paper's 2 mm), scored against the slab reference of the
  same five slices;
- **7 mm step**: 2 mm slabs every 7 mm instead of 5 (a coarser clinical protocol), scored
  against the slab reference of the same slices;
- **tumour slabs only**: the 1 mm volume cut to the slices that hold the reference's tumour
  before the emulation (a slab acquisition through the tumour alone, the rest of the brain
  not scanned), scored against the slab reference of the cut volume;
- **yaw -10 / +5 / +10**: the head turned in the slice plane by that many
  degrees (nearest-neighbour rotation of the 1 mm image and of its label about
  the volume's centre, so that no gray level is blurred and the masked
  background stays exact), scored against the turned label: a head not
  straight in the scanner; the symmetry rule mirrors about the estimated
  mid-sagittal plane (:func:`tumor3d.segmentation.lesion.symmetry_plane`).

A second table gives the tumour volume (Eq. 7, mL) of the volumes without an
expert tumour label (the tumour-free ones and the clinical T1c, whose label is
semi-automatic) as given and turned: a normal brain must stay at 0 mL.

The labelled cases are among the shipped learned models' training patients: with
``--oof-models DIR --cnn-folds DIR ...`` each is run by the cross-validation fold's models
that never saw it (``benchmarks/oof_models.py``).

Usage::

    TUMOR3D_DATA_DIR=/work/shared/data python benchmarks/real_robustness.py [--cases pat0003 ...] \
        [--oof-models DIR --cnn-folds DIR ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import real_segmentation as rs  # noqa: E402

from tumor3d.segmentation.lesion import left_right_axis  # noqa: E402

BIAS = 0.15  # +- share of the multiplicative field
NOISE = 0.08  # Rician noise: SD of each component, share of the brain's median gray
YAWS = {"yaw -10": -10.0, "yaw +5": 5.0, "yaw +10": 10.0}  # degrees, in-plane


def _turned(vol: np.ndarray, deg: float) -> np.ndarray:
    """``vol`` turned by ``deg`` in the (y, x) plane about its centre (nearest neighbour)."""
    lo = vol.min()
    return ndi.rotate(vol, deg, axes=(1, 2), reshape=False, order=0, cval=lo)


def _slabs_5mm(vol: np.ndarray) -> np.ndarray:
    """Slab ``i`` = mean of thin slices ``5 i + 2`` to ``5 i + 6`` (contiguous 5 mm slabs)."""
    n = (vol.shape[0] - 2 - rs.STEP) // rs.STEP + 1
    idx = 2 + rs.STEP * np.arange(n)
    return np.mean([vol[idx + j].astype(np.float64) for j in range(rs.STEP)], axis=0)


COARSE_STEP = 7  # thin slices (mm at 1 mm) between the slabs of the "7 mm step" column


def rician(img: np.ndarray, share: float, seed: int) -> np.ndarray:
    """``img`` with Rician noise: two Gaussian components of SD ``share`` x the median of its
    non-background voxels, on the intensities shifted to start at 0 (the background, at the
    image's minimum, kept)."""
    lo = float(img.min())
    a = img.astype(np.float64) - lo
    background = a <= 0
    sd = share * float(np.median(a[~background]))
    rng = np.random.default_rng(seed)
    noisy = np.hypot(a + rng.normal(0.0, sd, a.shape), rng.normal(0.0, sd, a.shape))
    return np.where(background, 0.0, noisy) + lo


def _variant(img: np.ndarray, name: str, lr_axis: int) -> np.ndarray:
    if name in YAWS:
        return _turned(img, YAWS[name])
    if name == "mirrored":
        return np.flip(img, axis=lr_axis)
    if name == "linear":
        return 3.0 * img + 100.0
    lo = img.min()
    background = img <= lo
    if name == "noise 8 %":
        return rician(img, NOISE, seed=0)
    axis = (3 - lr_axis if lr_axis in (1, 2) else 1) if name == "bias y" else 0
    coord = np.arange(img.shape[axis], dtype=np.float64)
    g = (coord - coord.mean()) / (coord.max() - coord.mean())
    shape = [1, 1, 1]
    shape[axis] = -1
    field = 1.0 + BIAS * g.reshape(shape)
    return np.where(background, lo, (img - lo) * field + lo)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=None, help="case names (substring match)")
    rs.add_config_argument(ap)
    rs.add_oof_arguments(ap)
    args = ap.parse_args(argv)
    oof = rs.oof_from_args(args)
    data = rs.real_data_or_skip()
    if data is None:
        return 0
    cfg = rs.default_config(args.config)
    variants = (
        "as given", "mirrored", "reversed", "linear", "bias y", "bias z", "noise 8 %",
        "0.5 mm pixels", "5 mm slabs", "7 mm step", "tumour slabs only", *YAWS,
    )  # fmt: skip
    print("| case | " + " | ".join(variants) + " | mirrored masks agree | reversed masks agree |")
    print("|---|" + "---|" * (len(variants) + 2))
    for case in rs._cases(data):
        if case.label is None or case.native_only:
            continue
        if args.cases and not any(c in case.name for c in args.cases):
            continue
        scan, ref = rs.read_case(case)
        models = rs.case_models(oof, case.image, case.modality, cfg)
        slab_ref = rs.emulate_thick(ref.astype(np.float64), 2) >= 0.5
        tz = np.flatnonzero(ref.any(axis=(1, 2)))
        cut = slice(int(tz[0]), int(tz[-1]) + 1)  # the thin slices that hold the tumour
        axis = left_right_axis(scan.affine)
        spacing = (rs.STEP * scan.slice_step_mm, *scan.pixel_spacing_mm)
        cells, masks = [], {}
        for name in variants:
            if name == "mirrored" and axis is None:
                cells.append("–")
                continue
            img = scan.image.astype(np.float64)
            plain = ("as given", "reversed", "0.5 mm pixels", "5 mm slabs", "7 mm step")
            if name not in plain + ("tumour slabs only",):
                img = _variant(img, name, axis)
            sp = spacing
            if name == "5 mm slabs":
                thick = _slabs_5mm(img)
            elif name == "7 mm step":
                thick = rs.emulate_thick(img, 2, COARSE_STEP)
                sp = (COARSE_STEP * scan.slice_step_mm, *spacing[1:])
            elif name == "tumour slabs only":
                thick = rs.emulate_thick(img[cut], 2)
            else:
                thick = rs.emulate_thick(img, 2)
            if name == "reversed":
                thick = thick[::-1]
            elif name == "0.5 mm pixels":
                thick = ndi.zoom(thick, (1, 2, 2), order=1)
                sp = (spacing[0], spacing[1] / 2, spacing[2] / 2)
            _, _, seg, _ = rs.run_pipeline(thick, cfg, case.modality, None, sp, axis, models)
            mask = seg.tumor_mask
            if name == "mirrored":
                mask = np.flip(mask, axis=axis)
            elif name == "reversed":
                mask = mask[::-1]
            elif name == "0.5 mm pixels":
                z, y, x = mask.shape
                mask = mask.reshape(z, y // 2, 2, x // 2, 2).mean(axis=(2, 4)) >= 0.5
            masks[name] = mask
            ref_v = slab_ref
            if name == "5 mm slabs":
                ref_v = _slabs_5mm(ref.astype(np.float64)) >= 0.5
            elif name == "7 mm step":
                ref_v = rs.emulate_thick(ref.astype(np.float64), 2, COARSE_STEP) >= 0.5
            elif name == "tumour slabs only":
                ref_v = rs.emulate_thick(ref[cut].astype(np.float64), 2) >= 0.5
            if name in YAWS:
                turned = _turned(ref.astype(np.uint8), YAWS[name])
                ref_v = rs.emulate_thick(turned.astype(np.float64), 2) >= 0.5
            cells.append(f"{rs.soft_dice(mask, ref_v):.3f}")
        agree = (
            f"{rs.soft_dice(masks['as given'], masks['mirrored']):.3f}"
            if "mirrored" in masks
            else "–"
        )
        agree_z = f"{rs.soft_dice(masks['as given'], masks['reversed']):.3f}"
        print(f"| {case.name} | " + " | ".join(cells) + f" | {agree} | {agree_z} |")
    _unlabelled_table(data, cfg, args.cases, oof)
    return 0


def _unlabelled_table(data: Path, cfg, only, oof=None) -> None:
    """Tumour volume (mL) of the volumes without an expert label, as given and turned."""
    turns = {"as given": 0.0, "yaw -10": -10.0, "yaw -5": -5.0, "yaw +5": 5.0, "yaw +10": 10.0}
    print()
    print("| volume (native slices) | " + " | ".join(turns) + " |")
    print("|---|" + "---|" * len(turns))
    for case in rs._cases(data):
        if case.label is not None and not case.native_only:
            continue
        if only and not any(c in case.name for c in only):
            continue
        scan, _ = rs.read_case(case)
        axis = left_right_axis(scan.affine)
        spacing = (scan.slice_step_mm, *scan.pixel_spacing_mm)
        # the clinical T1c has a (semi-automatic) label: a cross-validation case; the
        # tumour-free volumes have none and no model ever saw them
        models = rs.case_models(oof, case.image, case.modality, cfg) if case.label else None
        cells = []
        for deg in turns.values():
            img = scan.image.astype(np.float64)
            if deg:
                img = _turned(img, deg)
            _, _, seg, _ = rs.run_pipeline(img, cfg, case.modality, None, spacing, axis, models)
            cells.append(f"{float(seg.tumor_mask.sum()) * np.prod(spacing) / 1000.0:.1f}")
        print(f"| {case.name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    sys.exit(main())

"""Real FLAIR without tumour, and the smallest lesion found (issue 7, lesion step 3e).

``../shared/data`` has no tumour-free FLAIR: its tumour-free volumes are T1
heads. This benchmark makes one from each BraTS FLAIR case whose tumour does not
reach its own mirror image (pat0004, pat0005; pat0003 and the algoseg case cross
the midline, and their mirror holds tumour): the tumour, and a 5 mm margin, is
replaced by the mirror image of the other hemisphere (left-right array flip;
BraTS volumes are registered to an atlas, so the midline is about the array's
middle), replaced whole to 3 mm from the label and blended to the image from 3
to 5 mm; the replaced part takes the mirror's outline too. A case of which more
than 1 % of the tumour stays, or is brought in from the mirror side, is skipped.
What is left is the patient's own normal tissue, with the mass effect of the
tumour that was there. ``--modality t1c`` does the same to the cases' T1c (their
whole tumour replaced), without implants.

Reported, at the native 1 mm and at 2 mm every 5 mm (offset 2, as
``benchmarks/real_segmentation.py``):

- **pseudo-healthy**: slices flagged and tumour volume (Eq. 7, mL): a normal
  brain should give 0;
- **implanted spheres** at the removed tumour's centre (radius 3-15 mm, 0.1-14
  mL, partial volume by 3 x 3 x 3 supersampling), their gray that of the case's
  oedema (BraTS label 2) or half-way from the brain's median to it, the normal
  tissue's texture kept (the local deviation from a 5 mm mean added): soft Dice
  against the sphere's partial-volume fraction (on the slabs at 2 mm / 5 mm: the
  slab reference, as ``benchmarks/real_robustness.py``; not the 3-D Dice of the
  interpolated stack; a fractional reference keeps it below 1 for small spheres)
  and the volume error (Eq. 7). The smallest found tells the detection limit;
- **placements** (``--placements N``, default 4): 4.2 mL oedema-bright spheres at
  ``N`` random places in each of three depth classes off the midline, and deep on
  the midline (fixed seed): how the rules (depth, symmetry, satellites, a lesion
  straddling the midline) treat a lesion elsewhere in the brain.

Usage::

    TUMOR3D_DATA_DIR=/work/shared/data python benchmarks/pseudo_healthy.py [--cases pat0004 ...] \
        [--modality t1c]   # the same cases' T1c without tumour (no implants)
        [--oof-models DIR --cnn-folds DIR ...]   # the learned models that never saw the case

The default configuration runs the learned method on FLAIR and T1c; its shipped models
were trained on these patients (their normal tissue included): ``--oof-models``
(``benchmarks/oof_models.py``) runs each case with the fold's models that never saw it.
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
from tumor3d.segmentation.lesion.candidates import _depth_mm  # noqa: E402
from tumor3d.storage.readers import read_scan  # noqa: E402

MARGIN_MM = 5.0  # replaced beyond the label (the oedema's edge, the blend)
BLEND_MM = 2.0
RADII_MM = (3.0, 5.0, 7.5, 10.0, 15.0)
CONTRASTS = {"oedema": 1.0, "half": 0.5}  # share of (oedema median - brain median)


def pseudo_healthy(img: np.ndarray, label: np.ndarray, lr_axis: int) -> tuple[np.ndarray, dict]:
    """``img`` with the label replaced by its mirror, and what tumour is left or brought in.

    Replaced whole within ``MARGIN_MM - BLEND_MM`` of the label, blended to the image over
    the next ``BLEND_MM``; the replaced part takes the mirror's outline too (where the
    mirror is background, so is the result), so no tumour stays where the brains' outlines
    differ. Returns the volume and ``{"left": label voxels still in the image (weight of
    the image > 1/2), "brought": voxels of the mirrored label brought in (weight of the
    mirror > 1/2)}``.
    """
    flip = np.flip(img, axis=lr_axis)
    lo = img.min()
    d_out = ndi.distance_transform_edt(~label)  # mm: 1 mm voxels
    w = np.clip((MARGIN_MM - d_out) / BLEND_MM, 0.0, 1.0)
    out = (1.0 - w) * img + w * flip
    out = np.where(flip > lo, out, np.where(w >= 0.5, lo, img))  # the mirror's outline
    out[(img <= lo) & (w < 0.5)] = lo
    flip_label = np.flip(label, axis=lr_axis)
    return out, {
        "left": int((label & (w < 0.5)).sum()),
        "brought": int((flip_label & (w > 0.5)).sum()),
    }


def _where(mask: np.ndarray) -> str:
    """The mask's slice range and centroid (z, y, x), or "-"."""
    if not mask.any():
        return "-"
    zs = np.flatnonzero(mask.any(axis=(1, 2)))
    c = ndi.center_of_mass(mask)
    return f"slices {zs[0]}-{zs[-1]}, centre ({c[0]:.0f}, {c[1]:.0f}, {c[2]:.0f})"


def ball_fraction(shape, centre, radius: float, ss: int = 3) -> np.ndarray:
    """Partial-volume fraction of a ball (voxel units) in each voxel, by supersampling."""
    f = np.zeros(shape)
    lo = [max(0, int(np.floor(centre[i] - radius - 1))) for i in range(3)]
    hi = [min(shape[i], int(np.ceil(centre[i] + radius + 2))) for i in range(3)]
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    g = [(np.arange(lo[i], hi[i])[:, None] + sub[None]).ravel() for i in range(3)]
    zz, yy, xx = np.meshgrid(*g, indexing="ij")
    d2 = (zz - centre[0]) ** 2 + (yy - centre[1]) ** 2 + (xx - centre[2]) ** 2
    n = [hi[i] - lo[i] for i in range(3)]
    inside = (d2 <= radius * radius).astype(np.float64)
    f[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = inside.reshape(
        n[0], ss, n[1], ss, n[2], ss
    ).mean(axis=(1, 3, 5))
    return f


def _run(img, scan, cfg, lr_axis, thick: bool, modality: str = "flair", models=None):
    if thick:
        img, spacing = rs.emulate_thick(img, 2), (rs.STEP * scan.slice_step_mm, 1.0, 1.0)
    else:
        spacing = (scan.slice_step_mm, 1.0, 1.0)
    _, det, seg, _ = rs.run_pipeline(img, cfg, modality, None, spacing, lr_axis, models)
    return det, seg.tumor_mask, spacing


def _implanted(healthy, brain, texture, gray, centre, radius_mm, scan, cfg, axis, models=None):
    """A sphere implanted at ``gray`` (the texture kept), run at 2 mm / 5 mm and at 1 mm.

    Returns its volume (mL) and, for the thick then the thin run, ``(soft Dice, volume
    found in mL)``.
    """
    f = ball_fraction(healthy.shape, centre, radius_mm) * brain
    im = np.where(brain, (1.0 - f) * healthy + f * (gray + texture), healthy)
    runs = []
    for thick in (True, False):
        _, mask, spacing = _run(im, scan, cfg, axis, thick, models=models)
        ref = rs.emulate_thick(f, 2) if thick else f
        runs.append((rs.soft_dice(mask, ref), float(mask.sum()) * float(np.prod(spacing)) / 1000.0))
    return float(f.sum()) / 1000.0, runs


def _placements(healthy, brain, texture, gray, scan, cfg, axis, n: int, models=None) -> None:
    """Spheres of 10 mm radius at ``gray``, ``n`` per depth class, at random places.

    Depth classes by the 3-D distance to the brain's outside against the brain's
    median depth ``m``: deep (at least ``m + 8`` mm), middle (``m`` +- 2 mm), shallow
    (11-13 mm); centres at least 15 voxels from the array's middle column (the midline).
    A fourth class, midline: deep centres on the array's middle column (the sphere is
    its own mirror image: lesion step 3f).
    """
    depth = _depth_mm(brain, (1.0, 1.0, 1.0))
    med = float(np.median(depth[brain]))
    rng = np.random.default_rng(1)
    zc, yc, xc = np.nonzero(brain)
    far = np.abs(xc - brain.shape[2] / 2) > 15
    on_mid = np.abs(xc - (brain.shape[2] - 1) / 2) < 1
    d = depth[zc, yc, xc]
    # class: (depth range in mm, where); the midline class last, so that the random draws
    # of the other three are those of the benchmark before it had one
    classes = {
        "deep": ((med + 8, np.inf), far),
        "middle": ((med - 2, med + 2), far),
        "shallow": ((11, 13), far),
        "midline": ((med + 8, np.inf), on_mid),
    }
    print(f"\n| 4.2 mL sphere at (z, y, x), depth (brain median {med:.0f} mm) | 2 mm / 5 mm Dice"
          " | 1 mm Dice |")  # fmt: skip
    print("|---|---|---|")
    dice = {(t, m): [] for t in (True, False) for m in (False, True)}  # (thick, midline)
    for cname, ((lo_d, hi_d), where_ok) in classes.items():
        sel = np.flatnonzero((d >= lo_d) & (d < hi_d) & where_ok)
        for k in rng.choice(sel, n, replace=False):
            c = np.array([zc[k], yc[k], xc[k]], dtype=np.float64)
            _, runs = _implanted(healthy, brain, texture, gray, c, 10.0, scan, cfg, axis, models)
            for thick, (dc, _) in zip((True, False), runs, strict=True):
                dice[thick, cname == "midline"].append(dc)
            cells = [f"{dc:.2f}" for dc, _ in runs]
            where = f"({zc[k]}, {yc[k]}, {xc[k]}), {d[k]:.0f} mm"
            print(f"| {cname} {where} | {cells[0]} | {cells[1]} |")
    for mid, what in ((False, "deep, middle, shallow"), (True, "midline")):
        cells = [f"{np.mean(dice[t, mid]):.3f} ({min(dice[t, mid]):.2f})" for t in (True, False)]
        print(f"| mean (min), {what} | {cells[0]} | {cells[1]} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=["pat0004", "pat0005"])
    ap.add_argument(
        "--placements",
        type=int,
        default=4,
        help="oedema-bright 4.2 mL spheres per class (deep, middle, shallow; deep on the "
        "midline) at random (fixed seed) instead of where the tumour was; 0: none",
    )
    ap.add_argument(
        "--modality",
        choices=("flair", "t1c"),
        default="flair",
        help="t1c: the case's T1c, its whole tumour replaced the same way; no implants",
    )
    rs.add_config_argument(ap)
    rs.add_oof_arguments(ap)
    args = ap.parse_args(argv)
    oof = rs.oof_from_args(args)
    data = rs.real_data_or_skip()
    if data is None:
        return 0
    cfg = rs.default_config(args.config)
    all_cases = {c.name: c for c in rs._cases(data)}
    cases = {c.name: c for c in all_cases.values() if c.modality == "flair" and c.label}
    for name in args.cases:
        if name not in cases:
            raise SystemExit(f"unknown case {name!r}: expected one of {sorted(cases)}")
        case = cases[name]
        scan, label = rs.read_case(case)  # the whole tumour (FLAIR label)
        run_case = case
        if args.modality == "t1c":
            run_case = all_cases[f"{name}_t1c"]
            scan, _ = rs.read_case(run_case)
        models = rs.case_models(oof, run_case.image, args.modality, cfg)
        if tuple(scan.pixel_spacing_mm) != (1.0, 1.0) or scan.slice_step_mm != 1.0:
            raise SystemExit(f"{case.image}: expected 1 mm voxels (BraTS)")
        axis = left_right_axis(scan.affine)
        if axis is None:
            raise SystemExit(f"{case.image}: no left-right array axis in the affine")
        img = scan.image.astype(np.float64)
        healthy, tumour = pseudo_healthy(img, label, axis)
        labels = np.rint(read_scan(case.label).image)
        oedema = float(np.median(img[labels == 2]))
        brain = healthy > healthy.min()
        normal = float(np.median(healthy[brain]))
        share = {k: v / float(label.sum()) for k, v in tumour.items()}
        print(
            f"\n## {name}: label voxels left {tumour['left']}, mirrored label voxels brought"
            f" in {tumour['brought']} (of {int(label.sum())})"
        )
        if max(share.values()) > 0.01:
            print("skipped: more than 1 % of the tumour is left or brought in by the mirror")
            continue
        print("\n| volume | 2 mm / 5 mm: flagged, tumour (mL) | 1 mm: flagged, tumour (mL) |")
        print("|---|---|---|")
        cells, where = [], []
        for thick in (True, False):
            det, mask, spacing = _run(healthy, scan, cfg, axis, thick, args.modality, models)
            ml = float(mask.sum()) * float(np.prod(spacing)) / 1000.0
            cells.append(f"{int(det.abnormal.sum())} / {det.abnormal.size}, {ml:.2f}")
            where.append(_where(mask))
        print(f"| pseudo-healthy {args.modality} | {cells[0]} | {cells[1]} |")
        print(f"\nwhere (slab / 1 mm slice indices): {where[0]}; {where[1]}")
        if args.modality != "flair":
            continue  # the implants have the FLAIR oedema's gray
        print("\n| implanted sphere | 2 mm / 5 mm: Dice, volume (error) | 1 mm: the same |")
        print("|---|---|---|")
        centre = np.array(ndi.center_of_mass(label))
        texture = healthy - ndi.uniform_filter(healthy, 5)
        for cname, share in CONTRASTS.items():
            gray = normal + share * (oedema - normal)
            for r in RADII_MM:
                true_ml, runs = _implanted(
                    healthy, brain, texture, gray, centre, r, scan, cfg, axis, models
                )
                cells = [
                    f"{dc:.2f}, {ml:.2f} mL ({100.0 * (ml - true_ml) / true_ml:+.0f} %)"
                    for dc, ml in runs
                ]
                print(f"| {cname}, r {r:g} mm ({true_ml:.2f} mL) | {cells[0]} | {cells[1]} |")
        if args.placements > 0:
            _placements(healthy, brain, texture, oedema, scan, cfg, axis, args.placements, models)
    return 0


if __name__ == "__main__":
    sys.exit(main())

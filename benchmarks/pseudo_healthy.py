"""Real FLAIR without tumour, and the smallest lesion found (issue 7, lesion step 3e).

``../shared/data`` has no tumour-free FLAIR: its tumour-free volumes are T1
heads. This benchmark makes one from each BraTS FLAIR case whose tumour does
not reach its own mirror image (pat0004, pat0005; pat0003 and the algoseg
case cross the midline, and their mirror holds tumour): the tumour, and a
5 mm margin, is replaced by the mirror image of the other hemisphere
(left-right array flip; BraTS volumes are registered to an atlas, so the
midline is the array's middle), blended over 2 mm. What is left is the
patient's own normal tissue, with the mass effect of the tumour that was there.

Reported, at the native 1 mm and at 2 mm every 5 mm (offset 2, as
``benchmarks/real_segmentation.py``):

- **pseudo-healthy**: slices flagged and tumour volume (Eq. 7, mL): a normal
  brain should give 0;
- **implanted spheres** at the removed tumour's centre (radius 3-15 mm,
  0.1-14 mL, partial volume by 3 x 3 x 3 supersampling), their gray that of
  the case's oedema (BraTS label 2) or half-way from the brain's median to
  it, the normal tissue's texture kept (the local deviation from a 5 mm mean
  added): 3-D Dice against the sphere's partial-volume fraction and volume
  error. The smallest found tells the detection limit.

Usage::

    TUMOR3D_DATA_DIR=/work/shared/data python benchmarks/pseudo_healthy.py [--cases pat0004 ...]
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

from storage.readers import read_scan  # noqa: E402
from tumor3d.lesion import left_right_axis  # noqa: E402

MARGIN_MM = 5.0  # replaced beyond the label (the oedema's edge, the blend)
BLEND_MM = 2.0
RADII_MM = (3.0, 5.0, 7.5, 10.0, 15.0)
CONTRASTS = {"oedema": 1.0, "half": 0.5}  # share of (oedema median - brain median)


def pseudo_healthy(img: np.ndarray, label: np.ndarray, lr_axis: int) -> tuple[np.ndarray, float]:
    """``img`` with the label replaced by its mirror; and the label's share in its mirror."""
    flip = np.flip(img, axis=lr_axis)
    lo = img.min()
    d_out = ndi.distance_transform_edt(~label)  # mm: 1 mm voxels
    w = np.clip((MARGIN_MM - d_out) / BLEND_MM, 0.0, 1.0)
    out = np.where(flip > lo, (1.0 - w) * img + w * flip, img)
    out[img <= lo] = lo
    overlap = float((label & np.flip(label, axis=lr_axis)).sum() / label.sum())
    return out, overlap


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


def _run(img, scan, cfg, lr_axis, thick: bool):
    if thick:
        img, spacing = rs.emulate_thick(img, 2), (rs.STEP * scan.slice_step_mm, 1.0, 1.0)
    else:
        spacing = (scan.slice_step_mm, 1.0, 1.0)
    _, det, seg, _ = rs.run_pipeline(img, cfg, "flair", None, spacing, lr_axis)
    return det, seg.tumor_mask, spacing


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=["pat0004", "pat0005"])
    args = ap.parse_args(argv)
    data = rs.real_data_or_skip()
    if data is None:
        return 0
    cfg = rs.default_config()
    cases = {c.name: c for c in rs._cases(data) if c.modality == "flair" and c.label}
    for name in args.cases:
        case = cases[name]
        scan, label = rs.read_case(case)
        if tuple(scan.pixel_spacing_mm) != (1.0, 1.0) or scan.slice_step_mm != 1.0:
            raise SystemExit(f"{case.image}: expected 1 mm voxels (BraTS)")
        axis = left_right_axis(scan.affine)
        img = scan.image.astype(np.float64)
        healthy, overlap = pseudo_healthy(img, label, axis)
        labels = np.rint(read_scan(case.label).image)
        oedema = float(np.median(img[labels == 2]))
        brain = healthy > healthy.min()
        normal = float(np.median(healthy[brain]))
        print(f"\n## {name}: the label's share in its own mirror {overlap:.2f}")
        if overlap > 0.01:
            print("skipped: the mirror holds tumour")
            continue
        print("\n| volume | 2 mm / 5 mm: flagged, tumour (mL) | 1 mm: flagged, tumour (mL) |")
        print("|---|---|---|")
        cells = []
        for thick in (True, False):
            det, mask, spacing = _run(healthy, scan, cfg, axis, thick)
            ml = float(mask.sum()) * float(np.prod(spacing)) / 1000.0
            cells.append(f"{int(det.abnormal.sum())} / {det.abnormal.size}, {ml:.2f}")
        print(f"| pseudo-healthy | {cells[0]} | {cells[1]} |")
        print("\n| implanted sphere | 2 mm / 5 mm: Dice, volume (error) | 1 mm: the same |")
        print("|---|---|---|")
        centre = np.array(ndi.center_of_mass(label))
        texture = healthy - ndi.uniform_filter(healthy, 5)
        for cname, share in CONTRASTS.items():
            gray = normal + share * (oedema - normal)
            for r in RADII_MM:
                f = ball_fraction(healthy.shape, centre, r) * brain
                im = np.where(brain, (1.0 - f) * healthy + f * (gray + texture), healthy)
                true_ml = float(f.sum()) / 1000.0
                cells = []
                for thick in (True, False):
                    _, mask, spacing = _run(im, scan, cfg, axis, thick)
                    ref = rs.emulate_thick(f, 2) if thick else f
                    ml = float(mask.sum()) * float(np.prod(spacing)) / 1000.0
                    err = 100.0 * (ml - true_ml) / true_ml
                    cells.append(f"{rs.soft_dice(mask, ref):.2f}, {ml:.2f} mL ({err:+.0f} %)")
                print(f"| {cname}, r {r:g} mm ({true_ml:.2f} mL) | {cells[0]} | {cells[1]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

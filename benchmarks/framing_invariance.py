"""Does the U-Net's answer depend on how much air the slices hold? Fold nets, held-out cases.

The same scan stored with more air around the head (padded) or cropped close to
it is the same anatomy; a segmentation should not move. For each held-out FLAIR
case of the cross-validation (``benchmarks/cnn_cv.py``'s folds), each fold net
of ``--work`` (trained without that case) segments the case as prepared, padded
with ``--pad`` pixels of air on every side, and cropped to the tissue's box plus
``--crop-margin`` pixels (the variant a user's crop to the head gives); the
masks (``--threshold``, the U-Net alone, no forest) are compared with the
prepared one's on the same voxels: Dice and the change of the voxel count.

Usage (with the folds of a ``cnn_cv.py --work`` run; ``--framing`` as it was trained)::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/framing_invariance.py \\
        --cache /tmp/cv-cache --work /tmp/u_head --json head_inv.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _variants(image: np.ndarray, pad: int, margin: int):
    """(name, volume, (dy, dx)): where the prepared slices' pixel (0, 0) lies in it."""
    from tumor3d.imaging.preprocess import true_box
    from tumor3d.learned.features import tissue_foreground

    air = float(image.min())
    padded = np.pad(image, ((0, 0), (pad, pad), (pad, pad)), constant_values=air)
    _, ys, xs = true_box(tissue_foreground(image))
    y0, x0 = max(0, ys.start - margin), max(0, xs.start - margin)
    y1, x1 = min(image.shape[1], ys.stop + margin), min(image.shape[2], xs.stop + margin)
    cropped = image[:, y0:y1, x0:x1]
    return [("padded", padded, (pad, pad)), ("cropped", cropped, (-y0, -x0))]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=None, help="learned_cv.py's preparation cache")
    ap.add_argument("--work", required=True, help="a cnn_cv.py --work folder (unet_fold{k}.npz)")
    ap.add_argument("--groups", nargs="*", default=["lgg", "brats_flair"])
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--pad", type=int, default=20, help="pixels of air added on every side")
    ap.add_argument("--crop-margin", type=int, default=5, help="pixels kept around the tissue")
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    import learned_cv as L

    from tumor3d.evaluation.metrics import dice
    from tumor3d.learned.cnn import unet_from_bytes, unet_volume_probability

    cases = L.grouped_cases(args.config, args.folds, args.groups)
    if cases is None:
        return 0
    cfg, specs, folds = cases
    nets = {
        k: unet_from_bytes((Path(args.work) / f"unet_fold{k}.npz").read_bytes())
        for k in range(args.folds)
    }
    rows = []
    for s in specs:
        p = L.cached_prepare(s, cfg, False, args.cache)
        net = nets[folds[s.patient]]
        mm = tuple(float(v) for v in p.pixel_mm)
        base = unet_volume_probability(net, p.image, pixel_mm=mm) >= args.threshold
        for name, vol, (dy, dx) in _variants(p.image, args.pad, args.crop_margin):
            got = unet_volume_probability(net, vol, pixel_mm=mm) >= args.threshold
            h, w = p.image.shape[1:]
            # the prepared slices' pixels the variant holds: rows r0:r1, columns c0:c1
            r0, r1 = max(0, -dy), min(h, vol.shape[1] - dy)
            c0, c1 = max(0, -dx), min(w, vol.shape[2] - dx)
            ref = base[:, r0:r1, c0:c1]
            inside = got[:, r0 + dy : r1 + dy, c0 + dx : c1 + dx]
            n_ref = int(base.sum())
            row = {
                "case": s.name,
                "group": s.group,
                "variant": name,
                "framing": net.framing,
                "dice": float(dice(inside, ref)) if n_ref or inside.any() else 1.0,
                "voxels_change_pct": 100.0 * (int(got.sum()) - n_ref) / n_ref if n_ref else 0.0,
                "lost_outside_variant": int(base.sum() - ref.sum()),
            }
            rows.append(row)
            print(
                f"  {s.name} {name}: Dice {row['dice']:.3f}, voxels "
                f"{row['voxels_change_pct']:+.1f} %",
                flush=True,
            )
    print(f"\n{Path(args.work).name} ({rows[0]['framing'] if rows else '?'} framing)")
    print("| group | variant | n | Dice to the prepared mask, mean (min) | "
          "voxel change, mean abs (max abs) | cases changed > 5 % |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for g in args.groups:
        for v in ("padded", "cropped"):
            sel = [r for r in rows if r["group"] == g and r["variant"] == v]
            if not sel:
                continue
            d = np.array([r["dice"] for r in sel])
            c = np.abs([r["voxels_change_pct"] for r in sel])
            print(
                f"| {g} | {v} | {len(sel)} | {d.mean():.3f} ({d.min():.3f}) | "
                f"{c.mean():.1f} % ({c.max():.1f} %) | {int((c > 5).sum())} |"
            )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

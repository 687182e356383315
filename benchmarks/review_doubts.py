"""The status's doubts of out-of-fold rows, from their saved probability maps.

A run's ``needs_review`` (and status ``check``) is the learned method's own
review *or* any doubt the pipeline raises beside it
(:func:`tumor3d.segmentation.review.review_status`): the learned mask's caveats
(:func:`tumor3d.segmentation.segment.learned.learned_caveats`: a tumour on the
scan's first or last slice, or near the air outside a raw head), an empty
result, and the brain mask's notes where they doubt its volume.
``benchmarks/learned_cv.py`` rows carry the review's figures only; this
recomputes each case's lesion from its saved map as the run cut it (checked
against the row's volume), preprocesses as the pipeline does (the brain mask,
the air outside the head), and writes the rows with ``doubts``: the words that
would make the status ``check`` whatever the review's limits, except the doubt of
the voxel size, written apart as ``voxel_size_doubts`` (it doubts every volume in mL,
not the segmentation; the LGG heads are scored in voxel counts).
``benchmarks/review_cv.py`` flags a row with doubts as the run's status does.

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/review_doubts.py learned.json \\
        --prob prob/ --cache /tmp/cv-cache --out learned_doubts.json
    # the forest alone's rows: its maps are the --cnn-folds run's "forest" (FLAIR)
    python benchmarks/review_doubts.py forest.json --prob prob/ --key forest \\
        --cache /tmp/cv-cache --out forest_doubts.json
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

from learned_cv import add_recut_arguments, recut_rows, status_doubts  # noqa: E402

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.imaging.preprocess import preprocess_volume  # noqa: E402
from tumor3d.segmentation.segment.learned import learned_caveats  # noqa: E402


def doubts(p, mask: np.ndarray, cfg) -> tuple[list[str], list[str]]:
    """The doubts of learned mask ``mask`` on prepared case ``p``, as the learned method's
    run says them: its caveats (:func:`tumor3d.segmentation.segment.learned.learned_caveats`,
    with the air outside the head), then :func:`learned_cv.status_doubts`; and apart, the
    doubt of the voxel size (a slice step the head's shape contradicts), which the review's
    figures leave out (the LGG heads are scored by voxel counts)."""
    pre = preprocess_volume(p.image, **cfg.preprocess.model_dump(), spacing_mm=p.spacing_mm)
    exterior = pre.head_exterior
    caveats = learned_caveats(
        mask,
        spacing_mm=p.spacing_mm,
        head_exterior=exterior if exterior is not None and exterior.any() else None,
    )
    return status_doubts(pre, p.spacing_mm, mask, caveats, "learned")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", help="learned_cv.py --json rows")
    add_recut_arguments(ap)
    ap.add_argument(
        "--key",
        default="prob",
        help="the map the rows' lesions were cut from (prob; forest: the forest alone's, "
        "where a --cnn-folds run saved it beside the mean, else prob)",
    )
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    rows = json.loads(Path(args.rows).read_text())
    recut, n_doubted, n_voxel = recut_rows(rows, args, cfg, key=args.key), 0, 0
    try:
        for r, p, _, mask in recut:
            r["doubts"], r["voxel_size_doubts"] = doubts(p, mask, cfg)
            n_doubted += bool(r["doubts"])
            n_voxel += bool(r["voxel_size_doubts"])
            if r["doubts"]:
                said = "; ".join(d[:70] for d in r["doubts"])
                print(f"  {r['case']} ({r['vol_err']:+.0f} %): {said}")
    except ValueError as exc:
        print(exc)
        return 1
    Path(args.out).write_text(json.dumps(rows, indent=1))
    print(
        f"{len(rows)} rows, {n_doubted} with doubts (and {n_voxel} doubting the voxel size, "
        f"left apart); lesions within {recut.worst:.2%} of the rows' "
        f"volumes: wrote {args.out}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The review figures of out-of-fold rows, from their saved probability maps.

``benchmarks/learned_cv.py --save-prob DIR`` keeps each case's out-of-fold
probability (``prob``; with ``--cnn-folds``, also ``forest`` and ``cnn``, the
two it is the mean of). This recomputes the case's lesion from ``prob`` as the
run cut it (the model's threshold, keep fraction, least region, then
``segment.min_tumor_pixels``) and writes the rows with the figures of
:func:`tumor3d.learned.review.review_features` that they lack (a figure added
after the run, e.g. ``model_disagreement``), so that ``benchmarks/review_cv.py``
can choose its limit without training again. The maps are stored as float16:
the recomputed lesion's volume is checked against the row's (``--tolerance``).

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/review_figures.py learned.json \\
        --prob prob/ --cache /tmp/cv-cache --keep-fraction 1.0 --t1c-threshold 0.65 \\
        --out learned_review.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from learned_cv import add_recut_arguments, recut_rows  # noqa: E402

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.learned.review import review_features  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", help="learned_cv.py --json rows")
    add_recut_arguments(ap, keep_fraction=0.3, t1c_threshold=None)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    rows = json.loads(Path(args.rows).read_text())
    recut = recut_rows(rows, args, cfg)
    try:
        for r, p, maps, mask in recut:
            two = {}
            if "forest" in maps:
                two = {"forest_probability": maps["forest"], "cnn_probability": maps["cnn"]}
                two["cnn_members"] = maps.get("cnn_members")  # saved since the ensemble
            fig = review_features(maps["prob"], mask, p.spacing_mm, prior=p.prior, **two)
            r.update({k: v for k, v in fig.items() if k not in r})
    except ValueError as exc:
        print(exc)
        return 1
    Path(args.out).write_text(json.dumps(rows, indent=1))
    print(
        f"{len(rows)} rows, lesions within {recut.worst:.2%} of the rows' volumes: wrote {args.out}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

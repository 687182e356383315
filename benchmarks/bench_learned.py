"""Inference time of the learned segmentation beside the robust one, in one process.

A 31-slice 240 x 240 FLAIR phantom (the issue's reference size) is
preprocessed and its slices detected once; then, best of ``--repeat``
after a warm-up call (numba compiled), the segment stage's core call is
timed with the detect stage's (the lesion model runs there) for
``method="robust"`` and ``method="learned"`` (which adds the features,
the shipped forest and the post-processing to the robust prior), and the
learned method's parts alone.

Usage::

    python benchmarks/bench_learned.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.config import PipelineConfig  # noqa: E402
from tumor3d.imaging.preprocess import preprocess_volume  # noqa: E402
from tumor3d.learned.features import compute_features  # noqa: E402
from tumor3d.learned.forest import predict_proba  # noqa: E402
from tumor3d.learned.shipped import shipped_model  # noqa: E402
from tumor3d.phantom import make_phantom_patient  # noqa: E402
from tumor3d.segmentation.detect import detect_abnormal_slices  # noqa: E402
from tumor3d.segmentation.lesion import left_right_axis  # noqa: E402
from tumor3d.segmentation.segment import segment_tumor  # noqa: E402


def best_of(fn, repeat: int) -> float:
    fn()  # warm-up (numba compile or cache load)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    cfg = PipelineConfig()
    p = make_phantom_patient(0, modality="flair", n_slices=31, matrix_size=(240, 240))
    scan = p.scan
    sp = scan.spacing_zyx_mm
    lr = left_right_axis(scan.affine)
    pre = preprocess_volume(scan.image, **cfg.preprocess.model_dump(), spacing_mm=sp)
    model = shipped_model("flair")

    def seg(method: str):
        """The detect and segment stages' core calls (the lesion model runs in detect)."""
        d = detect_abnormal_slices(
            pre.enhanced,
            pre.brain_mask,
            modality="flair",
            spacing_mm=sp,
            lr_axis=lr,
            **cfg.detect.model_dump(),
        )
        kw = {**cfg.segment.model_dump(), "method": method}
        return segment_tumor(
            pre.enhanced,
            pre.brain_mask,
            d,
            modality="flair",
            spacing_mm=sp,
            lr_axis=lr,
            lesion=cfg.detect.lesion.model_dump(),
            image=scan.image,
            model=model,
            **kw,
        )

    feats = compute_features(scan.image, spacing_mm=sp, modality="flair", lr_axis=lr)
    t_robust = best_of(lambda: seg("robust"), args.repeat)
    t_learned = best_of(lambda: seg("learned"), args.repeat)
    t_feat = best_of(
        lambda: compute_features(scan.image, spacing_mm=sp, modality="flair", lr_axis=lr),
        args.repeat,
    )
    t_pred = best_of(lambda: predict_proba(model, feats.values), args.repeat)
    t_ctx = None
    if model.context is not None:  # auto-context: the second stage on the first's map
        import numpy as np

        from tumor3d.learned.context import context_features
        from tumor3d.learned.segment import keep_main_lesion

        def second() -> None:
            prob = np.zeros(feats.shape, np.float32)
            prob.ravel()[feats.index] = predict_proba(model, feats.values)
            first = keep_main_lesion(prob, float(model.meta["threshold"]), keep_fraction=1.0)
            ctx = context_features(
                prob, first, candidates=feats.candidates, index=feats.index, spacing_mm=sp
            )
            predict_proba(model.context, np.hstack([feats.values, ctx]))

        t_ctx = best_of(second, args.repeat) - t_pred
    print(
        f"31 x 240 x 240 FLAIR phantom, {os.cpu_count()} cores, load "
        f"{os.getloadavg()[0]:.1f}; {feats.values.shape[0]} tissue pixels, "
        f"{model.roots.size} trees"
    )
    print(f"| step | seconds (best of {args.repeat}) | vs robust |")
    print("|---|---|---|")
    print(f"| detect + segment, robust | {t_robust:.2f} | 1.00 |")
    print(
        f"| detect + segment, learned (robust prior + features + forest + lesion) | "
        f"{t_learned:.2f} | {t_learned / t_robust:.2f} |"
    )
    print(
        f"| learned inference alone (the difference) | {t_learned - t_robust:.2f} | "
        f"{(t_learned - t_robust) / t_robust:.2f} |"
    )
    print(f"| features alone | {t_feat:.2f} | {t_feat / t_robust:.2f} |")
    print(f"| forest alone | {t_pred:.2f} | {t_pred / t_robust:.2f} |")
    if t_ctx is not None:
        print(
            f"| auto-context: context features + second forest | {t_ctx:.2f} | "
            f"{t_ctx / t_robust:.2f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

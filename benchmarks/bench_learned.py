"""Inference time of the learned segmentation beside the robust one, in one process.

A 31-slice 240 x 240 FLAIR phantom (the issue's reference size) is
preprocessed and its slices detected once; then, best of ``--repeat``
after a warm-up call (numba compiled), the segment stage's core call is
timed with the detect stage's (the lesion model runs there) for
``method="robust"``, ``method="learned"`` with the forest alone
(``learned_cnn="off"``: the features, the shipped forest and the
post-processing on the robust prior) and with the mean of the forest's and
the shipped U-Net ensemble's probability (``learned_cnn="auto"``: the two nets,
one pass each, in a thread beside the forest), and the learned
method's parts alone (one net's, where the step is per net): wall seconds
and the process's CPU seconds, with the load average before and after.

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
from tumor3d.learned.cnn import unet_probability, unet_volume_probability  # noqa: E402
from tumor3d.learned.cnn_data import case_input, frame_of, upsample  # noqa: E402
from tumor3d.learned.features import compute_features  # noqa: E402
from tumor3d.learned.forest import predict_proba  # noqa: E402
from tumor3d.learned.shipped import shipped_cnn, shipped_model  # noqa: E402
from tumor3d.phantom import make_phantom_patient  # noqa: E402
from tumor3d.segmentation.detect import detect_abnormal_slices  # noqa: E402
from tumor3d.segmentation.lesion import left_right_axis  # noqa: E402
from tumor3d.segmentation.segment import segment_tumor  # noqa: E402


def best_of(fn, repeat: int) -> float:
    """Best wall seconds of ``repeat`` calls after a warm-up (numba compile or cache load)."""
    return best_of_cpu(fn, repeat)[0]


def best_of_cpu(fn, repeat: int) -> tuple[float, float]:
    """Best wall seconds and best process CPU seconds of ``repeat`` calls after a warm-up."""
    fn()
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return min(wall), min(cpu)


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
    cnn = shipped_cnn("flair")  # the ensemble (tuple of nets)
    net = cnn[0]  # one of them, for the per-net steps
    load_before = os.getloadavg()[0]

    def seg(method: str, learned_cnn: str = "off"):
        """The detect and segment stages' core calls (the lesion model runs in detect)."""
        d = detect_abnormal_slices(
            pre.enhanced,
            pre.brain_mask,
            modality="flair",
            spacing_mm=sp,
            lr_axis=lr,
            **cfg.detect.model_dump(),
        )
        kw = {**cfg.segment.model_dump(), "method": method, "learned_cnn": learned_cnn}
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
            cnn=cnn,
            **kw,
        )

    feats = compute_features(scan.image, spacing_mm=sp, modality="flair", lr_axis=lr)
    t_robust, c_robust = best_of_cpu(lambda: seg("robust"), args.repeat)
    t_learned, c_learned = best_of_cpu(lambda: seg("learned", "off"), args.repeat)
    t_mean, c_mean = best_of_cpu(lambda: seg("learned", "auto"), args.repeat)
    pixel_mm = sp[1:]
    frame = frame_of(scan.image, net.framing, pixel_mm)  # the net's window on each slice
    x = case_input(scan.image, net.size, net.context, frame)
    small = unet_probability(net, x)
    t_frame, c_frame = best_of_cpu(lambda: frame_of(scan.image, net.framing, pixel_mm), args.repeat)
    t_in, c_in = best_of_cpu(
        lambda: case_input(scan.image, net.size, net.context, frame), args.repeat
    )
    t_net, c_net = best_of_cpu(lambda: unet_probability(net, x), args.repeat)
    t_mir, c_mir = best_of_cpu(lambda: unet_probability(net, x, mirror=True), args.repeat)
    t_up, c_up = best_of_cpu(lambda: upsample(small, scan.image.shape, frame), args.repeat)
    t_cnn, c_cnn = best_of_cpu(
        lambda: unet_volume_probability(cnn, scan.image, pixel_mm=pixel_mm), args.repeat
    )
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
        f"31 x 240 x 240 FLAIR phantom, {os.cpu_count()} cores, load (1 min) "
        f"{load_before:.1f} before, {os.getloadavg()[0]:.1f} after; "
        f"{feats.values.shape[0]} tissue pixels, {model.roots.size} trees; {len(cnn)} U-Nets "
        f"{net.size} x {net.size}, {net.levels} levels, {sum(a.size for a in net.arrays.values())} "
        f"weights each, framing {net.framing!r}"
    )
    inf_forest, inf_mean = t_learned - t_robust, t_mean - t_robust
    cpu_forest, cpu_mean = c_learned - c_robust, c_mean - c_robust
    print(f"| step | wall s (best of {args.repeat}) | CPU s | wall vs forest alone |")
    print("|---|---|---|---|")
    print(f"| detect + segment, robust | {t_robust:.2f} | {c_robust:.2f} | |")
    print(
        f"| detect + segment, learned, forest alone (robust prior + features + forest + "
        f"lesion) | {t_learned:.2f} | {c_learned:.2f} | |"
    )
    print(f"| detect + segment, learned, forest + U-Net mean | {t_mean:.2f} | {c_mean:.2f} | |")
    print(
        f"| **learned inference, forest alone** (the difference against robust) | "
        f"{inf_forest:.2f} | {cpu_forest:.2f} | 1.00 |"
    )
    print(
        f"| **learned inference, forest + U-Net mean** (the difference against robust) | "
        f"{inf_mean:.2f} | {cpu_mean:.2f} | {inf_mean / inf_forest:.2f} |"
    )
    print(f"| features alone | {t_feat:.2f} | | {t_feat / inf_forest:.2f} |")
    print(f"| forest alone | {t_pred:.2f} | | {t_pred / inf_forest:.2f} |")
    if t_ctx is not None:
        print(
            f"| auto-context: context features + second forest | {t_ctx:.2f} | | "
            f"{t_ctx / inf_forest:.2f} |"
        )
    print(
        f"| U-Net ensemble alone, in the calling thread (input + {len(cnn)} networks, one pass "
        f"each, framed + upsample) | {t_cnn:.2f} | "
        f"{c_cnn:.2f} | {t_cnn / inf_forest:.2f} |"
    )
    for name, t, c in (
        (f"U-Net window (frame_of, {net.framing!r}: the tissue's box)", t_frame, c_frame),
        ("U-Net input (case_input)", t_in, c_in),
        ("U-Net network (numpy, one BLAS thread), one net, one pass", t_net, c_net),
        ("U-Net network with its mirrored pass (not run by the pipeline), one net", t_mir, c_mir),
        ("U-Net upsample to 240 x 240", t_up, c_up),
    ):
        print(f"| {name} | {t:.2f} | {c:.2f} | {t / inf_forest:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Cross-validation by patient of the segmentation methods on the labelled real cases.

Every labelled case of ``$TUMOR3D_DATA_DIR`` (default ``../shared/data``) in
four groups:

- ``brats_flair`` (BraTS 2018 x7, BraTS 2013 x3, the algoseg case's FLAIR),
- ``brats_t2`` (BraTS 2018 x7, algoseg T2w; the algoseg label is an algorithm's),
- ``brats_t1c`` (the same patients' T1c; reference = tumour core, labels 1 + 4,
  algoseg 1 + 3),
- ``lgg`` (45 clinical FLAIR heads, skull on, native slices; ``thick_t1c_brain2``
  is reported alone as ``clinical_t1c``).

The BraTS volumes are cut to the paper's acquisition as the evaluation does
(slab ``i`` = mean of 1 mm slices ``5 i + 2`` and ``5 i + 3``; slab reference
= mean label >= 0.5); the 3-D Dice compares the interpolated stack with the
1 mm label (``benchmarks/real_segmentation.py`` documents it). ``--eval-offset k``
scores the cut whose slab ``i`` is 1 mm slices ``5 i + k`` and ``5 i + k + 1``
instead, while the models still train on ``--train-offsets`` (a cut they never saw). The LGG heads
run at their native slices (voxel size unknown: voxel Dice, voxel-count
error).

Folds: 5, patients dealt round-robin per source (a patient's FLAIR, T2 and
T1c are always in the same fold), seed-free. ``--method learned`` trains on
the other four folds' patients (one model for FLAIR + T2, one for T1c) and
scores the held-out fold; ``--method robust`` / ``multiotsu`` / ``paper``
run a configured method (nothing trained: every case is held out);
``--method reference`` scores the reference's own slices (a perfect per-slice
segmentation): the ceiling that the slab cut, the interpolation and Eq. 7 leave.

Usage::

    TUMOR3D_DATA_DIR=/work/shared/data python benchmarks/learned_cv.py --method learned
    python benchmarks/learned_cv.py --method robust --config configs/default.yaml
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from real_segmentation import emulate_thick  # noqa: E402

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.evaluation.metrics import dice  # noqa: E402
from tumor3d.geometry.interpolate import interpolate_stack  # noqa: E402
from tumor3d.imaging.preprocess import preprocess_volume  # noqa: E402
from tumor3d.learned.cnn import unet_from_bytes  # noqa: E402
from tumor3d.learned.context import context_features  # noqa: E402
from tumor3d.learned.features import compute_features  # noqa: E402
from tumor3d.learned.forest import predict_proba  # noqa: E402
from tumor3d.learned.review import review_features  # noqa: E402
from tumor3d.learned.segment import (  # noqa: E402
    keep_main_lesion,
    region_preference,
    segment_learned,
)
from tumor3d.learned.shipped import CNN_MODELS  # noqa: E402
from tumor3d.learned.training import (  # noqa: E402
    TrainingRows,
    sample_indices,
    sample_rows,
    train_forest,
)
from tumor3d.segmentation.lesion import left_right_axis  # noqa: E402
from tumor3d.storage.manifest import data_dir  # noqa: E402
from tumor3d.storage.readers import read_scan  # noqa: E402

STEP = 5
OFFSET = 2
GROUPS = ("brats_flair", "brats_t2", "brats_t1c", "lgg", "clinical_t1c", "phantom")


@dataclass
class CaseSpec:
    name: str
    patient: str
    source: str
    group: str
    image: str
    label: str
    modality: str
    labels: tuple[int, ...] | None = None
    native: bool = False


def case_specs(data: Path, brats2013_t1c_labels: tuple[int, ...] = (1, 4)) -> list[CaseSpec]:
    out: list[CaseSpec] = []
    for d in sorted((data / "brats2018").glob("*")):
        if not (d / "seg.nii.gz").is_file():
            continue
        p = d.name
        out.append(
            CaseSpec(
                f"{p}/flair",
                p,
                "brats2018",
                "brats_flair",
                str(d / "flair.nii.gz"),
                str(d / "seg.nii.gz"),
                "flair",
            )
        )
        out.append(
            CaseSpec(
                f"{p}/t2",
                p,
                "brats2018",
                "brats_t2",
                str(d / "t2.nii.gz"),
                str(d / "seg.nii.gz"),
                "t2",
            )
        )
        out.append(
            CaseSpec(
                f"{p}/t1c",
                p,
                "brats2018",
                "brats_t1c",
                str(d / "t1c.nii.gz"),
                str(d / "seg.nii.gz"),
                "t1c",
                labels=(1, 4),
            )
        )
    for p in ("pat0003", "pat0004", "pat0005"):
        d = data / f"brats2013_{p}"
        if not d.is_dir():
            continue
        out.append(
            CaseSpec(
                f"{p}/flair",
                p,
                "brats2013",
                "brats_flair",
                str(d / "flair.nii.gz"),
                str(d / "seg.nii.gz"),
                "flair",
            )
        )
        out.append(
            CaseSpec(
                f"{p}/t1c",
                p,
                "brats2013",
                "brats_t1c",
                str(d / "t1c.nii.gz"),
                str(d / "seg.nii.gz"),
                "t1c",
                # BraTS 2013: 1 necrosis, 3 non-enhancing, 4 enhancing; the core as T1c
                # shows it, 1 + 4 (--brats2013-t1c-labels; reports/learned_cv.md, last section)
                labels=brats2013_t1c_labels,
            )
        )
    d = data / "brats_t2_algoseg"
    if d.is_dir():
        lab = str(d / "seg_algorithm.nii.gz")
        out.append(
            CaseSpec(
                "algoseg/flair",
                "algoseg",
                "algoseg",
                "brats_flair",
                str(d / "t2f.nii.gz"),
                lab,
                "flair",
            )
        )
        out.append(
            CaseSpec(
                "algoseg/t2", "algoseg", "algoseg", "brats_t2", str(d / "t2w.nii.gz"), lab, "t2"
            )
        )
        out.append(
            CaseSpec(
                "algoseg/t1c",
                "algoseg",
                "algoseg",
                "brats_t1c",
                str(d / "t1c.nii.gz"),
                lab,
                "t1c",
                labels=(1, 3),
            )
        )
    d = data / "thick_t1c_brain2"
    if d.is_dir():
        out.append(
            CaseSpec(
                "brain2/t1c",
                "brain2",
                "clinical",
                "clinical_t1c",
                str(d / "image.nii.gz"),
                str(d / "label.nii.gz"),
                "t1c",
                native=True,
            )
        )
    for d in sorted((data / "lgg_flair").glob("*")):
        if (d / "seg.nii.gz").is_file():
            out.append(
                CaseSpec(
                    f"lgg/{d.name}",
                    d.name,
                    "lgg",
                    "lgg",
                    str(d / "flair.nii.gz"),
                    str(d / "seg.nii.gz"),
                    "flair",
                    native=True,
                )
            )
    return out


def assign_folds(specs: list[CaseSpec], k: int) -> dict[str, int]:
    """Patients dealt round-robin into ``k`` folds, source by source (sorted names)."""
    folds: dict[str, int] = {}
    i = 0
    for source in ("brats2018", "brats2013", "algoseg", "clinical", "lgg", "phantom"):
        for p in sorted({s.patient for s in specs if s.source == source}):
            folds[p] = i % k
            i += 1
    return folds


def grouped_cases(config: str, k: int, groups) -> tuple | None:
    """(configuration, the cases of ``groups``, their patients' folds of every case's
    dealing into ``k``); None, said once, when there is no real data."""
    data = data_dir()
    if not data.is_dir():
        print(f"skipped: no real data at {data} (set TUMOR3D_DATA_DIR)")
        return None
    cfg = parse_config(Path(config).read_text(), source=config)
    specs = case_specs(data)
    folds = assign_folds(specs, k)  # on every case, as learned_cv.py
    return cfg, [s for s in specs if s.group in groups], folds


@dataclass
class Prepared:
    spec: CaseSpec
    image: np.ndarray  # the slices the method sees (z, y, x)
    ref: np.ndarray  # bool reference on those slices
    label: np.ndarray  # bool full-resolution label (3-D Dice, volumes)
    brain: np.ndarray
    spacing_mm: tuple[float, float, float]
    pixel_mm: tuple[float, float]
    thin_mm: float
    lr_axis: int | None
    head_exterior: np.ndarray | None
    raw: np.ndarray | None = None  # the 1 mm volume (BraTS), for other training offsets
    prior: np.ndarray | None = None  # the robust method's mask (a feature of the model)
    offset: int = OFFSET  # the slab offset of ``image`` and ``ref`` (BraTS)


#: Seeds of the synthetic training patients (the tests' phantoms use seeds below 100).
PHANTOM_SEED0 = 1000


def phantom_specs(n: int) -> list[CaseSpec]:
    """``n`` FLAIR and ``n`` T2 phantoms (``tumor3d.phantom``), a source of their own."""
    out = []
    for i in range(n):
        seed = PHANTOM_SEED0 + i
        for mod in ("flair", "t2"):
            out.append(
                CaseSpec(
                    f"phantom/{seed}/{mod}",
                    f"phantom{seed}",
                    "phantom",
                    "phantom",
                    f"phantom:{seed}",
                    "",
                    mod,
                    native=True,
                )
            )
    return out


def _read(spec: CaseSpec):
    """The scan and the boolean reference of one case."""
    if spec.source == "phantom":
        from tumor3d.phantom import make_phantom_patient

        p = make_phantom_patient(int(spec.image.split(":")[1]), modality=spec.modality)
        return p.scan, np.asarray(p.slice_masks) > 0.5
    scan = read_scan(spec.image, modality=spec.modality)
    lab = read_scan(spec.label).image
    return scan, (np.isin(np.rint(lab), spec.labels) if spec.labels else lab > 0.5)


def prepare(spec: CaseSpec, cfg, with_prior: bool = False, offset: int = OFFSET) -> Prepared:
    scan, label = _read(spec)
    px = tuple(float(v) for v in scan.pixel_spacing_mm)
    if spec.native:
        img, ref, step = scan.image.astype(np.float32), label, scan.slice_step_mm
    else:
        img = emulate_thick(scan.image, offset).astype(np.float32)
        ref = emulate_thick(label, offset) >= 0.5
        step = STEP * scan.slice_step_mm
    sp = (float(step), *px)
    pre = preprocess_volume(img, **cfg.preprocess.model_dump(), spacing_mm=sp)
    lr = left_right_axis(scan.affine)
    prior = None
    if with_prior:
        prior = robust_mask(pre, spec.modality, sp, lr, cfg)
    return Prepared(
        spec,
        img,
        ref,
        label,
        pre.brain_mask,
        sp,
        px,
        scan.slice_step_mm,
        lr,
        pre.head_exterior,
        None if spec.native else scan.image,
        prior,
        offset,
    )


def _prepare_config_json(cfg) -> str:
    """The configuration :func:`prepare` reads (preprocess, detect, segment), as JSON.

    The cache key: sections the preparation never reads (interpolation, mesh,
    rendering) and ``segment.learned_cnn`` (the learned method's option, not
    the robust prior's) do not move it.
    """
    seg = cfg.segment.model_dump()
    seg.pop("learned_cnn", None)
    return json.dumps(
        {
            "preprocess": cfg.preprocess.model_dump(),
            "detect": cfg.detect.model_dump(),
            "segment": seg,
        },
        sort_keys=True,
    )


def cached_prepare(
    spec: CaseSpec, cfg, with_prior: bool, cache: str | None, offset: int = OFFSET
) -> Prepared:
    """:func:`prepare`, kept as arrays in ``cache`` (``np.load`` without pickle)."""
    if spec.native:
        offset = OFFSET  # a native case has no slab offset
    if cache is None:
        return prepare(spec, cfg, with_prior, offset)
    import hashlib

    # the reference's labels too: the same image scored against another label set; a
    # slab offset other than the scored cut's (OFFSET keeps the tags cached before)
    labels = "" if spec.labels is None else f"labels={list(spec.labels)}"
    cut = "" if offset == OFFSET else f"offset={offset}"
    tag = hashlib.sha256((_prepare_config_json(cfg) + labels + cut).encode()).hexdigest()[:10]
    path = Path(cache) / f"{spec.name.replace('/', '__')}-{tag}-{int(with_prior)}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        lr = int(a["lr_axis"])
        return Prepared(
            spec,
            a["image"],
            a["ref"],
            a["label"],
            a["brain"],
            tuple(a["spacing_mm"]),
            tuple(a["pixel_mm"]),
            float(a["thin_mm"]),
            None if lr < 0 else lr,
            None,
            a.get("raw"),
            a.get("prior"),
            offset,
        )
    p = prepare(spec, cfg, with_prior, offset)
    path.parent.mkdir(parents=True, exist_ok=True)
    extra = {k: v for k, v in (("raw", p.raw), ("prior", p.prior)) if v is not None}
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")  # renamed when whole: runs share it
    np.savez(
        tmp,
        image=p.image,
        ref=p.ref,
        label=p.label,
        brain=p.brain,
        spacing_mm=np.array(p.spacing_mm),
        pixel_mm=np.array(p.pixel_mm),
        thin_mm=p.thin_mm,
        lr_axis=-1 if p.lr_axis is None else p.lr_axis,
        **extra,
    )
    os.replace(tmp, path)
    return p


def robust_mask(pre, modality: str, spacing_mm, lr_axis, cfg) -> np.ndarray:
    """The robust method's segmentation (detect + segment) of preprocessed slices."""
    from tumor3d.segmentation.detect import detect_abnormal_slices
    from tumor3d.segmentation.segment import segment_tumor

    det = detect_abnormal_slices(
        pre.enhanced,
        pre.brain_mask,
        modality=modality,
        spacing_mm=spacing_mm,
        lr_axis=lr_axis,
        **cfg.detect.model_dump(),
    )
    seg_cfg = {**cfg.segment.model_dump(), "method": "robust"}  # the learned method's prior
    seg = segment_tumor(
        pre.enhanced,
        pre.brain_mask,
        det,
        modality=modality,
        spacing_mm=spacing_mm,
        lr_axis=lr_axis,
        **seg_cfg,
    )
    return seg.tumor_mask


def score(prep: Prepared, mask: np.ndarray, cfg) -> dict:
    """Per-slice Dice, slice recall/specificity, 3-D Dice and volume error of one mask."""
    ref = prep.ref
    row: dict = {"case": prep.spec.name, "group": prep.spec.group}
    ref_sl = ref.any(axis=(1, 2))
    found = mask.any(axis=(1, 2))
    row["recall"] = float(found[ref_sl].mean()) if ref_sl.any() else float("nan")
    row["spec"] = float((~found[~ref_sl]).mean()) if (~ref_sl).any() else float("nan")
    zs = np.flatnonzero(ref_sl)
    row["slice_dice"] = float(np.mean([dice(mask[z], ref[z]) for z in zs])) if zs.size else np.nan
    px_mm2 = prep.pixel_mm[0] * prep.pixel_mm[1]
    ref_mm3 = float(prep.label.sum()) * px_mm2 * prep.thin_mm
    est_mm3 = float(mask.sum()) * px_mm2 * prep.spacing_mm[0]  # Eq. 7 (native: voxel volume)
    row["ref_ml"] = ref_mm3 / 1000.0
    row["est_ml"] = est_mm3 / 1000.0
    row["vol_err"] = 100.0 * (est_mm3 - ref_mm3) / ref_mm3 if ref_mm3 > 0 else float("nan")
    if prep.spec.native:
        row["dice3d"] = dice(mask, prep.label)
    else:
        ci = cfg.interpolate
        st = interpolate_stack(
            mask,
            method=ci.method,
            slices_between=STEP - 1,
            slice_step_mm=prep.spacing_mm[0],
            pixel_spacing_mm=prep.pixel_mm,
            end_caps=ci.end_caps,
        )
        fine = st.mask
        lab = prep.label.astype(np.float64)
        off = prep.offset
        n = min(fine.shape[0], lab.shape[0] - off - 1)
        mid = 0.5 * (lab[off : off + n] + lab[off + 1 : off + 1 + n])
        inter = float((fine[:n] * mid).sum())
        denom = float(fine[:n].sum()) + float(lab.sum())
        row["dice3d"] = 2.0 * inter / denom if denom else 1.0
        row["vol_interp_err"] = (
            100.0 * (float(fine.sum()) * px_mm2 * prep.thin_mm - ref_mm3) / ref_mm3
        )
    return row


def summarise(rows: list[dict]) -> str:
    lines = [
        "| group | n | per-slice Dice mean ± sd | slice recall | slice spec. | 3-D Dice mean ± sd "
        "(median) | volume error mean abs (median) | within 10 % / beyond 25 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in GROUPS:
        rs = [r for r in rows if r["group"] == g]
        if not rs:
            continue
        a = {
            k: np.array([r[k] for r in rs], float)
            for k in ("slice_dice", "recall", "spec", "dice3d", "vol_err")
        }
        err = np.abs(a["vol_err"])
        lines.append(
            f"| {g} | {len(rs)} | {np.nanmean(a['slice_dice']):.3f}"
            f" ± {np.nanstd(a['slice_dice']):.3f}"
            f" | {np.nanmean(a['recall']):.3f} | {np.nanmean(a['spec']):.3f}"
            f" | {np.nanmean(a['dice3d']):.3f} ± {np.nanstd(a['dice3d']):.3f}"
            f" ({np.nanmedian(a['dice3d']):.3f})"
            f" | {np.nanmean(err):.1f} % ({np.nanmedian(a['vol_err']):+.1f} %)"
            f" | {int(np.sum(err <= 10))} / {int(np.sum(err > 25))} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--method",
        default="learned",
        help="learned, reference (the reference's own slices), or a segment.method",
    )
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument(
        "--brats2013-t1c-labels",
        type=int,
        nargs="+",
        default=[1, 4],
        help="the BraTS 2013 T1c reference's labels (1 necrosis, 3 non-enhancing, 4 enhancing)",
    )
    ap.add_argument("--groups", nargs="*", default=None)
    ap.add_argument("--limit-lgg", type=int, default=None)
    ap.add_argument(
        "--phantoms",
        type=int,
        default=0,
        help="add this many FLAIR and T2 phantoms (seeds 1000 on) as a group",
    )
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument(
        "--t1c-threshold",
        type=float,
        default=None,
        help="the T1c model's threshold (default: --threshold)",
    )
    ap.add_argument("--keep-fraction", type=float, default=0.3)
    ap.add_argument(
        "--train-offsets",
        type=int,
        nargs="*",
        default=[2],
        help="BraTS slab offsets sampled for training (evaluation: --eval-offset)",
    )
    ap.add_argument(
        "--forest-seed",
        type=int,
        default=None,
        metavar="S",
        help="learned: train the forests with another seed (the rows' sampling and "
        "LightGBM's bagging and feature sampling); the default is the shipped training's "
        "(rows seeded 0, LightGBM's own default seeds): how much a retraining alone moves "
        "the figures",
    )
    ap.add_argument(
        "--eval-offset",
        type=int,
        choices=range(STEP),
        default=OFFSET,
        help=f"the BraTS slab offset scored (default {OFFSET}, the cut every figure of "
        "reports/learned_cv.md is scored at): another one scores the cases at a cut the "
        "models were not trained on (training still samples --train-offsets)",
    )
    ap.add_argument(
        "--no-prior",
        dest="prior",
        action="store_false",
        help="learned: without the robust method's mask as a feature",
    )
    ap.add_argument(
        "--cache",
        default=None,
        help="folder keeping the prepared cases between runs (scratch, not an input)",
    )
    ap.add_argument("--json", default=None, help="write the per-case rows here")
    ap.add_argument(
        "--cv-rows",
        default=None,
        help="learned --final: take the cross-validation rows from this --json of "
        "an earlier run instead of running it again",
    )
    ap.add_argument(
        "--final",
        default=None,
        help="learned: also train on every case and write hyper.npz and t1c.npz "
        "here (the shipped models: tumor3d/learned/models)",
    )
    ap.add_argument("--save-prob", default=None, help="folder for out-of-fold probabilities")
    ap.add_argument(
        "--save-models",
        default=None,
        metavar="DIR",
        help="learned: write each fold's forests (DIR/<family>_fold<k>.npz, as the shipped "
        "files, their metadata naming the fold and its held-out patients) and DIR/folds.json "
        "(patient -> fold, image file -> patient): the models that never saw a case, for the "
        "real-data benchmarks' --oof-models (benchmarks/oof_models.py)",
    )
    ap.add_argument(
        "--cnn-folds",
        default=None,
        nargs="+",
        metavar="DIR",
        help="learned: score fold k through the pipeline's segment_learned with the U-Net "
        "DIR/unet_fold{k}.npz (benchmarks/cnn_cv.py, same folds; trained without fold k) "
        "on the sequences that ship one (tumor3d.learned.shipped.CNN_MODELS: FLAIR), "
        "its probability averaged with the forest's; the other sequences: the forest alone. "
        "Several DIRs (fold nets of other seeds): fold k's ensemble of their nets, as shipped",
    )
    ap.add_argument(
        "--cnn-sequences",
        default=",".join(CNN_MODELS),
        metavar="SEQ[,SEQ]",
        help="--cnn-folds: the sequences whose forest probability is averaged with the "
        "fold U-Net's (default: those that ship a net, tumor3d.learned.shipped.CNN_MODELS); "
        "e.g. flair,t2 to measure the FLAIR net on T2",
    )
    ap.add_argument(
        "--score-groups",
        nargs="*",
        default=None,
        metavar="GROUP",
        help="learned: score only these groups' cases; the forests still train on every "
        "case of the families they need (unlike --groups, which also drops training cases)",
    )
    ap.add_argument(
        "--auto-context",
        action="store_true",
        help="learned: a second forest on the features plus context features of the "
        "first's out-of-fold probability (tumor3d.learned.context); inner folds = the "
        "other outer folds; --json gets the second stage's rows, <json>.stage1.json the first's",
    )
    args = ap.parse_args(argv)
    args.cnn_sequences = tuple(
        s.strip().lower() for s in args.cnn_sequences.split(",") if s.strip()
    )
    if args.score_groups and (args.final or args.cv_rows or args.auto_context):
        ap.error(
            "--score-groups scores part of the cases: not with --final, --cv-rows, --auto-context"
        )
    if args.eval_offset != OFFSET and (
        args.final or args.cv_rows or args.auto_context or args.save_prob
    ):
        ap.error(
            "--eval-offset scores another cut: not with --final, --cv-rows, --auto-context, "
            "--save-prob (its maps would be named as the default cut's)"
        )
    if not args.train_offsets:
        ap.error("--train-offsets needs at least one offset")
    if args.forest_seed is not None and args.auto_context:
        ap.error("--forest-seed does not apply to --auto-context")
    data = data_dir()
    if not data.is_dir():
        print(f"skipped: no real data at {data} (set TUMOR3D_DATA_DIR)")
        return 0
    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    specs = case_specs(data, tuple(args.brats2013_t1c_labels))
    if args.groups:
        specs = [s for s in specs if s.group in args.groups]
    specs += phantom_specs(args.phantoms)
    if args.limit_lgg is not None:
        lgg = [s for s in specs if s.group == "lgg"][: args.limit_lgg]
        specs = [s for s in specs if s.group != "lgg"] + lgg
    folds = assign_folds(specs, args.folds)
    if args.save_models:
        if args.method != "learned" or args.auto_context:
            ap.error("--save-models writes the learned method's fold forests (not auto-context)")
        write_fold_map(Path(args.save_models) / "folds.json", specs, folds)
    t0 = time.perf_counter()
    preps = []
    want_prior = args.method == "learned" and args.prior
    for s in specs:
        preps.append(cached_prepare(s, cfg, want_prior, args.cache, args.eval_offset))
    print(f"prepared {len(preps)} cases in {time.perf_counter() - t0:.0f} s", flush=True)
    rows: list[dict] = []
    if args.method == "learned":
        if args.auto_context:
            if args.cv_rows or args.train_offsets != [OFFSET]:
                ap.error("--auto-context runs its own cross-validation at offset 2 only")
            rows = run_auto_context_cv(preps, folds, args, cfg)
        elif args.cnn_folds and (args.cv_rows or args.final):
            ap.error("--cnn-folds scores the fold nets: without --cv-rows and --final")
        elif args.cv_rows:  # the cross-validation of an earlier run of the same command
            rows = json.loads(Path(args.cv_rows).read_text())
        else:
            rows = run_learned_cv(preps, folds, args, cfg)
        if args.final and not args.auto_context:
            write_final_models(preps, rows, args, cfg)
    elif args.method == "reference":  # the ceiling of the scoring itself
        rows = [{**score(p, p.ref, cfg), "fold": -1} for p in preps]
    else:
        rows = run_configured(preps, args.method, cfg)
    print(summarise(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


def _features(p: Prepared):
    return compute_features(
        p.image, spacing_mm=p.spacing_mm, modality=p.spec.modality, lr_axis=p.lr_axis, prior=p.prior
    )


def run_learned_cv(preps: list[Prepared], folds: dict[str, int], args, cfg) -> list[dict]:
    t0 = time.perf_counter()
    # every case's rows (one random stream: a subset would sample other rows)
    rows_of = _training_rows(preps, args, cfg)
    print(f"sampled rows in {time.perf_counter() - t0:.0f} s", flush=True)
    groups = getattr(args, "score_groups", None)
    scored = [p for p in preps if not groups or p.spec.group in groups]
    needed = {_family(p) for p in scored}  # the families whose forests score a case
    out = []
    for k in range(args.folds):
        held = [p for p in scored if folds[p.spec.patient] == k]
        train = [p for p in preps if folds[p.spec.patient] != k]
        models = {}
        for fam, mods in FAMILIES:
            parts = [rows_of[p.spec.name] for p in train if p.spec.modality in mods]
            if parts and fam in needed:
                t1 = time.perf_counter()
                models[fam] = train_forest(
                    TrainingRows.concatenate(parts),
                    params=_forest_params(args),
                    meta=_fold_meta(fam, mods, k, folds, args) if args.save_models else None,
                )
                if args.save_models:
                    d = Path(args.save_models)
                    d.mkdir(parents=True, exist_ok=True)
                    (d / f"{fam}_fold{k}.npz").write_bytes(models[fam].to_bytes())
                print(
                    f"fold {k} {fam}: {sum(len(r.y) for r in parts)} rows, "
                    f"{time.perf_counter() - t1:.0f} s",
                    flush=True,
                )
        cnn = _fold_cnn(args.cnn_folds, k) if args.cnn_folds else None
        for p in held:
            fam = "t1c" if p.spec.modality == "t1c" else "hyper"
            parts = {}
            if args.cnn_folds:  # the pipeline's own call (tumor3d/segmentation/segment/learned.py)
                seg = segment_learned(
                    p.image,
                    model=models[fam],
                    spacing_mm=p.spacing_mm,
                    modality=p.spec.modality,
                    lr_axis=p.lr_axis,
                    threshold=_threshold(args, fam),
                    keep_fraction=args.keep_fraction,
                    prior=p.prior,
                    cnn=cnn if p.spec.modality in args.cnn_sequences else None,
                )
                prob, mask = seg.probability, seg.mask.copy()
                if seg.cnn_probability is not None:
                    parts = {"forest": seg.forest_probability, "cnn": seg.cnn_probability}
                    if seg.cnn_members is not None and len(seg.cnn_members) > 1:
                        parts["cnn_members"] = seg.cnn_members
            else:
                prob = forest_probability(p, models[fam])
                mask = _final_mask(p, prob, args, cfg)
            if args.save_prob:
                d = Path(args.save_prob)
                d.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(
                    case_file(d, p.spec.name),
                    prob=prob.astype(np.float16),
                    **{k: v.astype(np.float16) for k, v in parts.items()},
                )
            # as the pipeline (segment.min_tumor_pixels): small slice masks are cleared
            mask[mask.sum(axis=(1, 2)) < cfg.segment.min_tumor_pixels] = False
            row = score(p, mask, cfg)
            row["fold"] = k
            # as the pipeline: with a U-Net, the two probabilities (the models' disagreement)
            two = (
                {
                    "forest_probability": parts["forest"],
                    "cnn_probability": parts["cnn"],
                    "cnn_members": parts.get("cnn_members"),
                }
                if parts
                else {}
            )
            row.update(review_features(prob, mask, p.spacing_mm, prior=p.prior, **two))
            out.append(row)
            print(
                f"  {row['case']}: slice {row['slice_dice']:.3f} 3d {row['dice3d']:.3f} "
                f"vol {row['vol_err']:+.1f}% rec {row['recall']:.2f} spec {row['spec']:.2f}",
                flush=True,
            )
    return out


FAMILIES = (("hyper", ("flair", "t2")), ("t1c", ("t1c",)))


def _fold_meta(fam: str, mods, k: int, folds: dict[str, int], args) -> dict:
    """A fold forest's metadata: as a shipped model's cut, plus the fold and who it never saw."""
    return {
        "name": f"tumor3d-{fam}-fold{k}",
        "family": fam,
        "modalities": list(mods),
        "threshold": _threshold(args, fam),
        "keep_fraction": args.keep_fraction,
        "prior": "robust" if args.prior else None,
        "fold": k,
        "held_out_patients": sorted(p for p, f in folds.items() if f == k),
    }


def write_fold_map(path: Path, specs: list[CaseSpec], folds: dict[str, int]) -> None:
    """``folds.json``: each patient's fold, and each case's image file's patient."""
    path.parent.mkdir(parents=True, exist_ok=True)
    images = {str(Path(s.image).resolve()): s.patient for s in specs}
    path.write_text(json.dumps({"folds": folds, "images": images}, indent=1, sort_keys=True))


def _fold_cnn(folders: list[str], k: int):
    """Fold ``k``'s U-Net ensemble (``unet_fold{k}.npz`` of each folder), read as the
    pipeline reads its own."""
    nets = []
    for folder in folders:
        path = Path(folder) / f"unet_fold{k}.npz"
        nets.append(unet_from_bytes(path.read_bytes(), source=str(path)))
        print(f"fold {k}: U-Net {path} (SHA-256 {nets[-1].sha256[:12]}...)", flush=True)
    return tuple(nets)


def _family(p: Prepared) -> str:
    return "t1c" if p.spec.modality == "t1c" else "hyper"


def add_saved_run_arguments(
    ap, *, keep_fraction: float = 1.0, t1c_threshold: float | None = 0.65
) -> None:
    """The options of a script that reads a run's saved maps (``--save-prob``) and cuts
    each lesion again as the run cut it (:func:`_final_mask`): ``--prob``, ``--cache``,
    ``--config``, ``--threshold``, ``--keep-fraction``, ``--t1c-threshold``."""
    ap.add_argument("--prob", required=True, help="the run's --save-prob folder")
    ap.add_argument("--cache", required=True, help="learned_cv.py's prepared-case cache")
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--keep-fraction", type=float, default=keep_fraction)
    ap.add_argument("--t1c-threshold", type=float, default=t1c_threshold)


def saved_lesion(spec: CaseSpec, args, cfg) -> tuple[Prepared, np.ndarray]:
    """A case prepared (``args.cache``) and its lesion cut again, as the run cut it
    (:func:`_final_mask`), from the run's saved probability (``args.prob``)."""
    p = cached_prepare(spec, cfg, True, args.cache)
    with np.load(case_file(args.prob, spec.name)) as z:
        prob = z["prob"].astype(np.float32)
    return p, _final_mask(p, prob, args, cfg)


def add_recut_arguments(ap, **saved) -> None:
    """:func:`add_saved_run_arguments` (``saved`` its keywords) and ``--tolerance``: the
    options of a script that recuts a run's rows from their saved maps
    (:func:`recut_rows`)."""
    add_saved_run_arguments(ap, **saved)
    ap.add_argument(
        "--tolerance",
        type=float,
        default=0.01,
        help="largest relative volume difference between the recomputed lesion and the row's",
    )


class recut_rows:  # noqa: N801 (used as a function that keeps a figure)
    """Each row's prepared case, saved maps and lesion cut again from map ``key`` (``prob``
    where the case has no such map) as the run cut it (:func:`_final_mask`), checked
    against the row's Eq. 7 volume within ``args.tolerance``: iterating yields ``(row,
    prepared, maps, mask)``; ``worst`` is the largest relative difference so far.

    Raises ``ValueError`` naming the first case whose lesion is not the row's.
    """

    def __init__(self, rows: list[dict], args, cfg, key: str = "prob") -> None:
        self.rows, self.args, self.cfg, self.key = rows, args, cfg, key
        self.worst = 0.0

    def __iter__(self):
        rows, args, cfg = self.rows, self.args, self.cfg
        n_phantoms = sum(r["case"].startswith("phantom/") for r in rows) // 2
        specs = {s.name: s for s in case_specs(data_dir()) + phantom_specs(n_phantoms)}
        for r in rows:
            p = cached_prepare(specs[r["case"]], cfg, True, args.cache)
            with np.load(case_file(args.prob, r["case"])) as z:
                maps = {k: z[k].astype(np.float32) for k in z.files}
            mask = _final_mask(p, maps[self.key if self.key in maps else "prob"], args, cfg)
            est_ml = float(mask.sum()) * float(np.prod(p.spacing_mm)) / 1000.0  # Eq. 7
            diff = abs(est_ml - r["est_ml"]) / max(r["est_ml"], 1e-9) if r["est_ml"] else est_ml
            self.worst = max(self.worst, diff)
            if diff > args.tolerance:
                raise ValueError(
                    f"{r['case']}: lesion {est_ml:.2f} mL, the row's {r['est_ml']:.2f} mL"
                )
            yield r, p, maps, mask


def case_file(folder: str | Path, case: str) -> Path:
    """A case's ``.npz`` in ``folder`` (``--save-prob`` maps, feature scratch): the case name
    (``patient/sequence``) with ``/`` as ``__``."""
    return Path(folder) / (case.replace("/", "__") + ".npz")


def forest_probability(p: Prepared, model) -> np.ndarray:
    """The forest's probability of every voxel of ``p``'s slices (0 outside the tissue)."""
    f = _features(p)
    prob = np.zeros(f.shape, np.float32)
    prob.ravel()[f.index] = predict_proba(model, f.values)
    return prob


def _min_voxels(p: Prepared) -> int:
    return max(1, int(round(20.0 / float(np.prod(p.spacing_mm)))))


def _final_mask(p: Prepared, prob: np.ndarray, args, cfg) -> np.ndarray:
    mask = keep_main_lesion(
        prob,
        _threshold(args, _family(p)),
        keep_fraction=args.keep_fraction,
        min_voxels=_min_voxels(p),
        **region_preference(p.spec.modality, p.prior),
    )
    mask[mask.sum(axis=(1, 2)) < cfg.segment.min_tumor_pixels] = False
    return mask


def _context_rows(p: Prepared, feats, sel: np.ndarray, prob: np.ndarray, args) -> np.ndarray:
    """Stage-2 feature rows (features + context of ``prob``) of the row numbers ``sel``."""
    lesion = keep_main_lesion(
        prob,
        _threshold(args, _family(p)),
        keep_fraction=args.keep_fraction,
        min_voxels=_min_voxels(p),
    )
    ctx = context_features(
        prob, lesion, candidates=feats.candidates, index=feats.index[sel], spacing_mm=p.spacing_mm
    )
    return np.hstack([feats.values[sel], ctx])


def run_auto_context_cv(preps: list[Prepared], folds: dict[str, int], args, cfg) -> list[dict]:
    """Two-stage (auto-context) cross-validation; returns the second stage's rows.

    Outer fold ``k``: stage 1 is trained on the folds other than ``k``; stage 2
    on the features plus the context of the stage-1 probability that each
    training patient (fold ``j``) gets from a stage-1 model trained on the
    folds other than ``j`` and ``k`` (out-of-fold inside the training set).
    The held-out patients get stage 1 (folds other than ``k``), then stage 2.
    With ``--final``: stage 1 on every case, stage 2 on the context of every
    case's out-of-fold stage-1 probability, both in ``<family>.npz``
    (:func:`write_two_stage`).
    """
    import tempfile

    k_folds = args.folds
    scratch = tempfile.TemporaryDirectory(dir=args.cache, prefix="ac-features-")
    fdir = Path(scratch.name)

    def fpath(p: Prepared) -> Path:
        return case_file(fdir, p.spec.name)

    def load(p: Prepared):
        from tumor3d.learned.features import PatientFeatures

        with np.load(fpath(p), allow_pickle=False) as z:
            return PatientFeatures(
                z["values"], z["index"], tuple(int(v) for v in z["shape"]), z["candidates"]
            )

    t0 = time.perf_counter()
    rng = np.random.default_rng(0)  # as _training_rows: the same stage-1 rows
    rows1: dict[str, TrainingRows] = {}
    sel_of: dict[str, np.ndarray] = {}
    for p in preps:
        f = _features(p)
        sel, y, w = sample_indices(f, p.ref, rng=rng)
        rows1[p.spec.name] = TrainingRows(f.values[sel], y, w)
        sel_of[p.spec.name] = sel
        np.savez(
            fpath(p),
            values=f.values,
            index=f.index,
            shape=np.array(f.shape),
            candidates=f.candidates,
        )
    print(f"features and rows in {time.perf_counter() - t0:.0f} s", flush=True)

    def fit(parts: list[TrainingRows], label: str):
        t1 = time.perf_counter()
        m = train_forest(TrainingRows.concatenate(parts))
        print(
            f"{label}: {sum(len(r.y) for r in parts)} rows, {time.perf_counter() - t1:.0f} s",
            flush=True,
        )
        return m

    def fam_train(exclude: set[int], fam: str, mods) -> list[Prepared]:
        return [
            p for p in preps if folds[p.spec.patient] not in exclude and p.spec.modality in mods
        ]

    stage1: dict[tuple[int, ...], dict[str, object]] = {}
    for k in range(k_folds):
        for j in range(k + 1, k_folds):
            stage1[(j, k)] = {
                fam: fit(
                    [rows1[p.spec.name] for p in fam_train({j, k}, fam, mods)], f"s1 -{j}{k} {fam}"
                )
                for fam, mods in FAMILIES
            }
        stage1[(k,)] = {
            fam: fit([rows1[p.spec.name] for p in fam_train({k}, fam, mods)], f"s1 -{k} {fam}")
            for fam, mods in FAMILIES
        }
    rows2: dict[tuple[str, int], TrainingRows] = {}
    rows_final: dict[str, TrainingRows] = {}
    prob1_of: dict[str, np.ndarray] = {}
    out1: list[dict] = []
    t0 = time.perf_counter()
    for p in preps:
        j = folds[p.spec.patient]
        fam = _family(p)
        f = load(p)
        sel = sel_of[p.spec.name]
        r1 = rows1[p.spec.name]
        for k in range(k_folds):
            model = stage1[(k,) if k == j else (max(j, k), min(j, k))][fam]
            prob = np.zeros(f.shape, np.float32)
            prob.ravel()[f.index] = predict_proba(model, f.values)
            if k != j:
                rows2[(p.spec.name, k)] = TrainingRows(
                    _context_rows(p, f, sel, prob, args), r1.y, r1.w
                )
                continue
            prob1_of[p.spec.name] = prob
            if args.final:
                rows_final[p.spec.name] = TrainingRows(
                    _context_rows(p, f, sel, prob, args), r1.y, r1.w
                )
            row = score(p, _final_mask(p, prob, args, cfg), cfg)
            row["fold"] = j
            out1.append(row)
    print(
        f"stage-1 out-of-fold maps and context rows in {time.perf_counter() - t0:.0f} s", flush=True
    )
    out: list[dict] = []
    for k in range(k_folds):
        models2 = {
            fam: fit([rows2[(p.spec.name, k)] for p in fam_train({k}, fam, mods)], f"s2 -{k} {fam}")
            for fam, mods in FAMILIES
        }
        for p in preps:
            if folds[p.spec.patient] != k:
                continue
            f = load(p)
            prob1 = prob1_of[p.spec.name]
            x2 = _context_rows(p, f, np.arange(f.index.size), prob1, args)
            prob = np.zeros(f.shape, np.float32)
            prob.ravel()[f.index] = predict_proba(models2[_family(p)], x2)
            if args.save_prob:
                d = Path(args.save_prob)
                d.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(
                    case_file(d, p.spec.name),
                    prob=prob.astype(np.float16),
                    prob1=prob1.astype(np.float16),
                )
            mask = _final_mask(p, prob, args, cfg)
            row = score(p, mask, cfg)
            row["fold"] = k
            row.update(review_features(prob, mask, p.spacing_mm, prior=p.prior))
            out.append(row)
            r1 = next(r for r in out1 if r["case"] == row["case"])
            print(
                f"  {row['case']}: 3d {r1['dice3d']:.3f} -> {row['dice3d']:.3f} "
                f"vol {r1['vol_err']:+.1f}% -> {row['vol_err']:+.1f}% "
                f"rec {row['recall']:.2f} spec {row['spec']:.2f}",
                flush=True,
            )
    if args.json:
        Path(args.json).with_suffix(".stage1.json").write_text(json.dumps(out1, indent=1))
    print("stage 1 (the same run):")
    print(summarise(out1))
    if args.final:
        dest = Path(args.final)
        dest.mkdir(parents=True, exist_ok=True)
        for fam, mods in FAMILIES:
            train = [p for p in preps if p.spec.modality in mods]
            meta = _model_meta(fam, mods, train, out, args)
            m1 = fit([rows1[p.spec.name] for p in train], f"final s1 {fam}")
            m2 = fit([rows_final[p.spec.name] for p in train], f"final s2 {fam}")
            write_two_stage(dest / f"{fam}.npz", m1, m2, meta)
            print(f"wrote {dest}/{fam}.npz ({len(train)} cases, two stages)")
    scratch.cleanup()
    return out


def _forest_params(args) -> dict | None:
    """LightGBM's seed with ``--forest-seed`` (None: the shipped training's own defaults)."""
    seed = getattr(args, "forest_seed", None)
    return None if seed is None else {"seed": int(seed)}


def _training_rows(preps: list[Prepared], args, cfg) -> dict[str, TrainingRows]:
    seed = getattr(args, "forest_seed", None)
    rng = np.random.default_rng(0 if seed is None else seed)  # the rows' sampling
    out = {}
    for p in preps:
        # the scored cut's own rows: the default cut's always (as before --eval-offset),
        # another cut's only if it is a training offset
        own = p.spec.native or p.offset == OFFSET or p.offset in args.train_offsets
        parts = [sample_rows(_features(p), p.ref, rng=rng)] if own else []
        if not p.spec.native:
            for off in args.train_offsets:
                if off == p.offset:
                    continue
                img = emulate_thick(p.raw, off).astype(np.float32)
                prior = None
                if p.prior is not None:  # the robust mask of these slabs, as at inference
                    pre = preprocess_volume(
                        img, **cfg.preprocess.model_dump(), spacing_mm=p.spacing_mm
                    )
                    prior = robust_mask(pre, p.spec.modality, p.spacing_mm, p.lr_axis, cfg)
                q = Prepared(
                    p.spec,
                    img,
                    emulate_thick(p.label, off) >= 0.5,
                    p.label,
                    p.brain,
                    p.spacing_mm,
                    p.pixel_mm,
                    p.thin_mm,
                    p.lr_axis,
                    None,
                    None,
                    prior,
                    off,
                )
                parts.append(sample_rows(_features(q), q.ref, rng=rng))
        out[p.spec.name] = TrainingRows.concatenate(parts)
    return out


def write_final_models(preps: list[Prepared], cv_rows: list[dict], args, cfg) -> None:
    """Train each family on every case and write ``<family>.npz`` with its model card data."""
    rows_of = _training_rows(preps, args, cfg)
    out = Path(args.final)
    out.mkdir(parents=True, exist_ok=True)
    for fam, mods in FAMILIES:
        train = [p for p in preps if p.spec.modality in mods]
        if not train:  # --groups left this family no case: its file is not written
            print(f"no case of {fam}: {out / f'{fam}.npz'} not written")
            continue
        meta = _model_meta(fam, mods, train, cv_rows, args)
        model = train_forest(
            TrainingRows.concatenate([rows_of[p.spec.name] for p in train]),
            params=_forest_params(args),
            meta=meta,
        )
        (out / f"{fam}.npz").write_bytes(model.to_bytes())
        print(f"wrote {out / f'{fam}.npz'}: {len(train)} cases, {model.roots.size} trees")


def _model_meta(fam: str, mods, train: list[Prepared], cv_rows: list[dict], args) -> dict:
    """The shipped model's card data: cut, training cases, cross-validated figures, command."""
    import datetime

    groups = sorted({p.spec.group for p in train})
    cv = {g: _group_figures([r for r in cv_rows if r["group"] == g]) for g in groups}
    return {
        "name": f"tumor3d-{fam}-{datetime.date.today().isoformat()}",
        "family": fam,
        "modalities": list(mods),
        "threshold": _threshold(args, fam),
        "keep_fraction": args.keep_fraction,
        "prior": "robust" if args.prior else None,
        "auto_context": bool(getattr(args, "auto_context", False)),
        "training_cases": [p.spec.name for p in train],
        "cross_validation": cv,
        "command": "python benchmarks/learned_cv.py --method learned " + " ".join(sys.argv[1:]),
    }


def write_two_stage(path: Path, stage1, stage2, meta: dict) -> None:
    """One ``.npz``: the stage-1 forest with ``meta``, the auto-context stage as its context."""
    from dataclasses import replace

    m2 = replace(stage2, meta={**stage2.meta, "stage": "auto-context"})
    model = replace(stage1, meta={**stage1.meta, **meta}, context=m2)
    Path(path).write_bytes(model.to_bytes())


def _threshold(args, family: str) -> float:
    if family == "t1c" and args.t1c_threshold is not None:
        return args.t1c_threshold
    return args.threshold


def _group_figures(rs: list[dict]) -> dict:
    if not rs:
        return {}
    a = {
        k: np.array([r[k] for r in rs], float)
        for k in ("slice_dice", "recall", "spec", "dice3d", "vol_err")
    }
    err = np.abs(a["vol_err"])
    return {
        "n": len(rs),
        "slice_dice": float(np.nanmean(a["slice_dice"])),
        "dice3d_mean": float(np.nanmean(a["dice3d"])),
        "dice3d_median": float(np.nanmedian(a["dice3d"])),
        "within_10pct": int(np.sum(err <= 10)),
        "beyond_25pct": int(np.sum(err > 25)),
    }


def status_doubts(
    pre, spacing_mm, mask: np.ndarray, caveats, method: str, seg_values=None
) -> tuple[list[str], list[str]]:
    """What would make a run's status ``check`` beside a learned review's limits, as
    ``tumor3d.api.reconstruct_scan`` says it: no tumour found, ``caveats``, the brain
    mask's notes of preprocessing ``pre`` (doubting where ``method``'s mask lies inside the
    brain mask), and a segmentation that flags itself (``seg_values``: its
    ``needs_review`` and reasons, ``tumor3d.api.segmentation_values``).

    Returns those doubts, and apart from them the doubt of the voxel size (a slice step
    the head's shape contradicts, ``scale_notes``): it doubts every volume in mm3 and mL,
    not the segmentation, and the scoring here counts the LGG heads' voxels, which their
    unknown voxel size does not change (``reports/learned_cv.md``, "A slice step the
    head's shape contradicts"), so the review's figures leave it out and say it apart."""
    from tumor3d.imaging.preprocess import brain_mask_figures
    from tumor3d.segmentation.review import brain_mask_run_notes, run_notes, segmentation_review

    figures = brain_mask_figures(
        pre.brain_mask, spacing_mm, str(pre.brain_extraction), pre.original_u8
    )
    kw = brain_mask_run_notes(figures, method)
    voxel_size = list(kw.pop("scale_notes"))
    _, doubts = run_notes(tumour_found=bool(mask.any()), caveats=caveats, **kw)
    flagged, reasons, _ = segmentation_review(seg_values)
    return doubts + (list(reasons) if flagged else []), voxel_size


def run_configured(preps: list[Prepared], method: str, cfg) -> list[dict]:
    from tumor3d.api import segmentation_values
    from tumor3d.segmentation.detect import detect_abnormal_slices
    from tumor3d.segmentation.segment import segment_tumor

    out = []
    seg_cfg = cfg.segment.model_dump()
    seg_cfg["method"] = method if method != "default" else seg_cfg["method"]
    for p in preps:
        pre = preprocess_volume(p.image, **cfg.preprocess.model_dump(), spacing_mm=p.spacing_mm)
        det = detect_abnormal_slices(
            pre.enhanced,
            pre.brain_mask,
            modality=p.spec.modality,
            spacing_mm=p.spacing_mm,
            lr_axis=p.lr_axis,
            **cfg.detect.model_dump(),
        )
        exterior = pre.head_exterior  # as the segment stage passes it (scalp caveat)
        seg = segment_tumor(
            pre.enhanced,
            pre.brain_mask,
            det,
            modality=p.spec.modality,
            spacing_mm=p.spacing_mm,
            lr_axis=p.lr_axis,
            head_exterior=exterior if exterior is not None and exterior.any() else None,
            **seg_cfg,
        )
        row = score(p, seg.tumor_mask, cfg)
        row["fold"] = -1
        row["method"] = seg.method  # "auto" resolved (without a model: never "learned")
        # a rule-based method's review, judged by review_cv.py --default-rows; the caveats
        # said, doubting or not (learned_report.py weighs the midline caveat on them)
        row["caveats"] = list(seg.caveats)
        row["doubts"], row["voxel_size_doubts"] = status_doubts(
            pre, p.spacing_mm, seg.tumor_mask, seg.caveats, seg.method, segmentation_values(seg)
        )
        out.append(row)
        print(
            f"  {row['case']}: slice {row['slice_dice']:.3f} 3d {row['dice3d']:.3f} "
            f"vol {row['vol_err']:+.1f}% rec {row['recall']:.2f} spec {row['spec']:.2f}",
            flush=True,
        )
    return out


if __name__ == "__main__":
    raise SystemExit(main())

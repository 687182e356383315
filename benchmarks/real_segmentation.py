"""Real-data dev harness: preprocess -> detect -> segment -> interpolate, in-process.

For every labelled case of ``$TUMOR3D_DATA_DIR`` (default ``../shared/data``
relative to the repository root):

- ``brats2013_pat000{3,4,5}/flair.nii.gz`` with the **expert** label
  ``seg.nii.gz`` (whole tumour = label > 0), modality FLAIR;
- ``brats_t2_algoseg/t2w.nii.gz`` with ``seg_algorithm.nii.gz`` (an
  **algorithm's** label, not an expert's), modality T2;
- the same case's FLAIR (``t2f.nii.gz``, labels 1-3) and T1c (``t1c.nii.gz``,
  labels 1 + 3, necrosis and enhancing), added after the lesion model's rules
  were chosen on the other cases: the FLAIR is **held out** (nothing was
  changed after seeing it); the T1c was, until it exposed step 3b's depth
  percentile (``reports/segmentation.md``);
- the BraTS pat0003-0005 T1c volumes (labels 1 + 4, the necrotic core and
  the enhancing rim) and the clinical 6.5 mm T1c ``thick_t1c_brain2`` (its
  semi-automatic label, at its own slices);
- ``no_tumor/*`` (no label: slices flagged and tumour volume only), run at
  their native slices as T1c, the evaluation manifest's modality
  (``--no-tumor-modality`` for another).

Detect and segment get the scan's voxel spacing and left-right axis
(:func:`tumor3d.segmentation.lesion.left_right_axis` of its affine), as the stage adapters
pass them.

Thick-slice emulation (the paper's 2 mm slices every 5 mm): slab ``i`` is the
mean of the two adjacent 1 mm slices ``5 i + o`` and ``5 i + o + 1``
(``o = --offset``, default 2), so it is centred at thin position
``5 i + o + 0.5``. The reference of slab ``i`` is the label linearly
interpolated at that position, ``Lbar = (L[5i+o] + L[5i+o+1]) / 2`` (values
0, 1/2, 1), and every Dice is the soft Dice ``2 sum(P Lbar) / (sum P +
sum Lbar)``; a slab is a reference tumour slab when ``sum Lbar > 0``. The
interpolated stack (``slices_between`` automatic: 4 at 1 mm pixels) has
slices at thin positions ``o + 0.5 + j``; the 3-D Dice compares fine slice
``j`` with ``(L[o+j] + L[o+j+1]) / 2`` and counts every label voxel outside
the stack's extent as missed. Eq. 7 volume = 5 mm x sum of tumour pixel
areas of the acquired slabs; the reference volume = label voxel count x
voxel volume. Native mode runs all 1 mm slices (no interpolation).

Also printed, when ``tumor3d.evaluation`` is importable: recall, specificity
and mean per-slice Dice with the evaluation flow's rules (binary slab
reference = mean label of its two thin slices >= 0.5, i.e. their union;
binary Dice), so that both agree.

Printed per case and configuration: abnormal-slice recall and specificity
(the detector's flag vs reference tumour slabs), recall of the final masks
(slab with a non-empty tumour mask), mean per-slice Dice over reference
tumour slabs (0 where missed), 3-D Dice, Eq. 7 volume error and seconds per
stage.

Usage::

    TUMOR3D_DATA_DIR=/work/shared/data python benchmarks/real_segmentation.py \
        [--config configs/default.yaml ...] [--cases pat0003 ...] [--native] [--brain-mask] \
        [--oof-models DIR --cnn-folds DIR ...]

The default configuration runs the learned method (FLAIR, T1c) with the shipped models,
which were trained on these labelled cases: their figures are not accuracy. With
``--oof-models`` (``learned_cv.py --save-models``) and ``--cnn-folds`` each case is run by
the models of the cross-validation fold that held its patient out (``oof_models.py``).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.geometry.interpolate import interpolate_stack  # noqa: E402
from tumor3d.imaging.preprocess import preprocess_volume  # noqa: E402
from tumor3d.segmentation.detect import detect_abnormal_slices  # noqa: E402
from tumor3d.segmentation.lesion import left_right_axis  # noqa: E402
from tumor3d.segmentation.patient import method_models  # noqa: E402
from tumor3d.segmentation.segment import segment_tumor  # noqa: E402
from tumor3d.storage.manifest import data_dir  # noqa: E402  (re-exported: rs.data_dir)
from tumor3d.storage.readers import read_scan  # noqa: E402

STEP = 5  # slab step, thin slices (5 mm at 1 mm)


@dataclass
class Case:
    name: str
    image: str
    label: str | None
    modality: str
    brainmask: str | None = None
    labels: tuple[int, ...] | None = None  # reference labels that count (None: every label > 0)
    native_only: bool = False  # acquired thick: never emulated


def _cases(data: Path, no_tumor_modality: str = "t1c") -> list[Case]:
    out = []
    for p in ("pat0003", "pat0004", "pat0005"):
        d = data / f"brats2013_{p}"
        out.append(Case(p, str(d / "flair.nii.gz"), str(d / "seg.nii.gz"), "flair",
                        str(d / "brainmask.nii.gz")))
    d = data / "brats_t2_algoseg"
    out.append(Case("t2_algoseg", str(d / "t2w.nii.gz"), str(d / "seg_algorithm.nii.gz"), "t2"))
    # the same case's FLAIR and T1c, added late (the FLAIR held out; see the docstring)
    out.append(Case("flair_algoseg", str(d / "t2f.nii.gz"), str(d / "seg_algorithm.nii.gz"),
                    "flair"))
    # T1c: the enhancing rim (label 4) with its necrotic core (label 1)
    for p in ("pat0003", "pat0004", "pat0005"):
        d = data / f"brats2013_{p}"
        out.append(Case(f"{p}_t1c", str(d / "t1c.nii.gz"), str(d / "seg.nii.gz"), "t1c",
                        str(d / "brainmask.nii.gz"), labels=(1, 4)))
    d = data / "brats_t2_algoseg"  # its labels: 1 necrosis, 2 oedema, 3 enhancing
    out.append(Case("algoseg_t1c", str(d / "t1c.nii.gz"), str(d / "seg_algorithm.nii.gz"), "t1c",
                    labels=(1, 3)))
    d = data / "thick_t1c_brain2"  # clinical 6.5 mm T1c, semi-automatic label
    out.append(Case("brain2_t1c", str(d / "image.nii.gz"), str(d / "label.nii.gz"), "t1c",
                    native_only=True))
    for f in ("KmeansTest_T1UCharRaw.nii.gz", "aniso_vox.nii.gz"):
        out.append(Case("no_tumor/" + f.split(".")[0], str(data / "no_tumor" / f), None,
                        no_tumor_modality))
    return out


def real_data_or_skip() -> Path | None:
    """The real-data folder (:func:`data_dir`), or None after saying why the run is skipped."""
    data = data_dir()
    if not data.is_dir():
        print(f"skipped: no real data at {data} (set TUMOR3D_DATA_DIR)")
        return None
    return data


def default_config(path: str | Path | None = None):
    """``path`` (default ``configs/default.yaml``), read by the project's own loader."""
    path = Path(path) if path else ROOT / "configs" / "default.yaml"
    return parse_config(path.read_text(), source=str(path))


def add_config_argument(ap) -> None:
    """``--config``: one configuration (``configs/robust.yaml``: the rule-based method)."""
    ap.add_argument("--config", default=None, metavar="YAML",
                    help="the configuration (default configs/default.yaml: the learned method "
                         "on FLAIR and T1c; configs/robust.yaml: the rule-based lesion model)")


def read_case(case: Case):
    """The case's scan and its reference (bool, the case's labels; None without a label)."""
    scan = read_scan(case.image, modality=case.modality)
    label = None
    if case.label:
        lab = read_scan(case.label).image
        label = np.isin(np.rint(lab), case.labels) if case.labels else lab > 0.5
    return scan, label


def soft_dice(pred: np.ndarray, ref: np.ndarray) -> float:
    """``2 sum(P R) / (sum P + sum R)`` with ``R`` in [0, 1]; 1 when both are empty."""
    p = pred.astype(np.float64)
    denom = p.sum() + ref.sum()
    return float(2.0 * (p * ref).sum() / denom) if denom > 0 else 1.0


def emulate_thick(vol: np.ndarray, offset: int, step: int = STEP) -> np.ndarray:
    """Slab ``i`` = mean of thin slices ``step i + offset`` and ``step i + offset + 1``."""
    n = (vol.shape[0] - offset - 2) // step + 1
    idx = offset + step * np.arange(n)
    return 0.5 * (vol[idx].astype(np.float64) + vol[idx + 1].astype(np.float64))


def run_pipeline(image, cfg, modality, brain_mask=None, spacing_mm=None, lr_axis=None,
                 models=None):
    """Preprocess, detect and segment ``image`` as the pipeline's stages do.

    Where the configuration's method is the learned one, ``models`` (``segment_tumor``'s
    ``model`` and ``cnn``: the out-of-fold ones of ``benchmarks/oof_models.py``) or else
    the shipped models.
    """
    t = {}
    t0 = time.perf_counter()
    pre = preprocess_volume(image, **cfg.preprocess.model_dump(), brain_mask=brain_mask,
                            spacing_mm=spacing_mm)
    t["preprocess"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    det = detect_abnormal_slices(pre.enhanced, pre.brain_mask, modality=modality,
                                 spacing_mm=spacing_mm, lr_axis=lr_axis, **cfg.detect.model_dump())
    t["detect"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # the learned method (the default on FLAIR and T1c) with its models, as the segment
    # stage gives them: without them segment_tumor would fall back to the robust method
    learned = method_models(
        cfg.segment.method, modality, det, lambda: image, cfg.segment.learned_cnn, models
    )
    seg = segment_tumor(pre.enhanced, pre.brain_mask, det, modality=modality,
                        spacing_mm=spacing_mm, lr_axis=lr_axis, **cfg.segment.model_dump(),
                        **learned)
    t["segment"] = time.perf_counter() - t0
    return pre, det, seg, t


def evaluate(case: Case, cfg, *, native: bool, offset: int, use_mask: bool, oof=None) -> dict:
    scan, label = read_case(case)
    bm = read_scan(case.brainmask).image > 0.5 if (use_mask and case.brainmask) else None
    return evaluate_volume(case.name, scan.image, label, scan, cfg, case.modality,
                           native=native or case.native_only, offset=offset, brain_mask=bm,
                           models=case_models(oof, case.image, case.modality, cfg))


def add_oof_arguments(ap) -> None:
    """``--oof-models`` and ``--cnn-folds``: the learned method's out-of-fold models."""
    ap.add_argument("--oof-models", default=None, metavar="DIR",
                    help="the learned method's fold forests of learned_cv.py --save-models: "
                         "each case run by the fold that held its patient out "
                         "(benchmarks/oof_models.py); default: the shipped models, which "
                         "were trained on these cases")
    ap.add_argument("--cnn-folds", nargs="+", default=None, metavar="DIR",
                    help="with --oof-models: the fold U-Nets (cnn_cv.py; one folder a seed)")


def oof_from_args(args):
    """The :class:`oof_models.OutOfFold` of ``--oof-models``, or None (the shipped models)."""
    if not args.oof_models:
        if args.cnn_folds:
            raise SystemExit("--cnn-folds needs --oof-models (the fold forests)")
        return None
    from oof_models import OutOfFold

    return OutOfFold(args.oof_models, args.cnn_folds)


def case_models(oof, image: str, modality: str, cfg):
    """The out-of-fold ``model``/``cnn`` of a case's image file, or None (the shipped ones)."""
    if oof is None:
        return None
    return oof.models(image, modality, cfg.segment.learned_cnn)


def evaluate_volume(name: str, img: np.ndarray, label: np.ndarray | None, scan, cfg,
                    modality: str, *, native: bool, offset: int,
                    brain_mask: np.ndarray | None = None, models=None) -> dict:
    """:func:`evaluate` on arrays: ``img`` and ``label`` (bool or None) on ``scan``'s grid.

    ``scan`` gives the spacing and the affine (left-right axis); with ``native`` the
    slices are run as they are, else emulated at 2 mm every 5 mm from ``offset``.
    """
    bm = brain_mask
    voxel_mm3 = float(np.prod(scan.pixel_spacing_mm)) * scan.slice_step_mm
    if native or label is None:
        thick, ref, bm_t = img, (None if label is None else label.astype(np.float64)), bm
        step_mm = scan.slice_step_mm
    else:
        thick = emulate_thick(img, offset)
        ref = emulate_thick(label, offset)
        bm_t = None if bm is None else emulate_thick(bm, offset) >= 0.5
        step_mm = STEP * scan.slice_step_mm
    spacing = (step_mm, *scan.pixel_spacing_mm)
    pre, det, seg, t = run_pipeline(thick, cfg, modality, bm_t, spacing,
                                    left_right_axis(scan.affine), models)
    mask = seg.tumor_mask
    px_mm2 = float(np.prod(scan.pixel_spacing_mm))
    vol_eq7 = step_mm * px_mm2 * float(mask.sum())
    row = {"case": name, "n_slices": thick.shape[0], "t": t,
           "flagged": int(det.abnormal.sum()), "found": int(mask.any(axis=(1, 2)).sum()),
           "vol_eq7_ml": vol_eq7 / 1000.0, "largest_ml": vol_eq7 / 1000.0}
    if ref is None:
        return row
    ref_slices = ref.sum(axis=(1, 2)) > 0
    flag = det.abnormal
    found = mask.any(axis=(1, 2))
    row["recall"] = float(flag[ref_slices].mean()) if ref_slices.any() else float("nan")
    row["spec"] = float((~flag[~ref_slices]).mean()) if (~ref_slices).any() else float("nan")
    row["recall_found"] = float(found[ref_slices].mean()) if ref_slices.any() else float("nan")
    row["spec_found"] = float((~found[~ref_slices]).mean()) if (~ref_slices).any() else float("nan")
    row["slice_dice"] = float(np.mean([soft_dice(mask[z], ref[z])
                                       for z in np.flatnonzero(ref_slices)]))
    # the same figures with tumor3d.evaluation's rules (binary reference: tumour where
    # the mean label of the slab's thin slices is >= 0.5, binary Dice), if available
    try:
        from tumor3d.evaluation.metrics import dice, slice_confusion

        ref_bin = ref >= 0.5
        conf = slice_confusion(det.abnormal, ref_bin.sum(axis=(1, 2)))
        row["eval_recall"], row["eval_spec"] = conf.sensitivity, conf.specificity
        zs = np.flatnonzero(ref_bin.any(axis=(1, 2)))
        row["eval_slice_dice"] = float(np.mean([dice(mask[z], ref_bin[z]) for z in zs]))
    except ImportError:
        pass
    ref_ml = float(label.sum()) * voxel_mm3 / 1000.0
    row["ref_ml"] = ref_ml
    row["vol_err"] = 100.0 * (vol_eq7 / 1000.0 - ref_ml) / ref_ml
    t0 = time.perf_counter()
    if native:
        row["dice3d"] = soft_dice(mask, label.astype(np.float64))
    else:
        cfg_i = cfg.interpolate
        st = interpolate_stack(mask, method=cfg_i.method, slices_between=cfg_i.slices_between,
                               slice_step_mm=step_mm, pixel_spacing_mm=scan.pixel_spacing_mm,
                               end_caps=cfg_i.end_caps)
        fine = st.mask
        m = st.slices_between
        if m + 1 != STEP:
            row["dice3d"] = float("nan")
        else:
            lab = label.astype(np.float64)
            n = min(fine.shape[0], lab.shape[0] - offset - 1)
            mid = 0.5 * (lab[offset:offset + n] + lab[offset + 1:offset + 1 + n])
            inter = float((fine[:n] * mid).sum())
            row["dice3d"] = 2.0 * inter / (float(fine[:n].sum()) + float(lab.sum()))
    t["interpolate"] = time.perf_counter() - t0
    return row


def _fmt(row: dict) -> str:
    t = row["t"]
    ts = " ".join(f"{k[:3]}={v:.2f}" for k, v in t.items())
    if "recall" not in row:
        return (f"{row['case']:<28} n={row['n_slices']:3d} flagged={row['flagged']:3d} "
                f"({100 * row['flagged'] / row['n_slices']:.1f} %) found={row['found']:3d} "
                f"tumour={row['vol_eq7_ml']:.2f} mL  [{ts}]")
    return (f"{row['case']:<12} n={row['n_slices']:3d} recall={100 * row['recall']:5.1f} "
            f"spec={100 * row['spec']:5.1f} (masks: {100 * row['recall_found']:5.1f}/"
            f"{100 * row['spec_found']:5.1f}) sliceDice={row['slice_dice']:.3f} "
            f"dice3d={row['dice3d']:.3f} vol={row['vol_eq7_ml']:.1f}/{row['ref_ml']:.1f} mL "
            f"err={row['vol_err']:+.1f} %  [{ts}]"
            + (f"\n{'':12} eval rules: recall={100 * row['eval_recall']:5.1f} "
               f"spec={100 * row['eval_spec']:5.1f} sliceDice={row['eval_slice_dice']:.3f}"
               if "eval_recall" in row else ""))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", action="append", type=Path, default=None,
                    help="config YAML (repeatable); default configs/default.yaml")
    ap.add_argument("--cases", nargs="*", default=None, help="case names (substring match)")
    ap.add_argument("--native", action="store_true", help="run the 1 mm slices (no emulation)")
    ap.add_argument("--offset", type=int, default=2, help="first thin slice of slab 0")
    ap.add_argument("--brain-mask", action="store_true", help="pass BraTS brainmask.nii.gz")
    ap.add_argument("--no-tumor-modality", default="t1c", choices=("t1c", "t2", "flair"),
                    help="modality of the no_tumor volumes (default t1c, as in the manifest)")
    add_oof_arguments(ap)
    args = ap.parse_args(argv)
    oof = oof_from_args(args)
    data = data_dir()
    if not (data / "brats2013_pat0003").is_dir():
        print(f"real data not found under {data} (set TUMOR3D_DATA_DIR): skipped")
        return 0
    configs = args.config or [ROOT / "configs" / "default.yaml"]
    cases = _cases(data, args.no_tumor_modality)
    if args.cases:
        cases = [c for c in cases if any(s in c.name for s in args.cases)]
    for cpath in configs:
        cfg = parse_config(cpath.read_text(), source=str(cpath))
        mode = "native 1 mm" if args.native else f"2 mm / 5 mm (offset {args.offset})"
        print(f"== {cpath.name}  segment.method={getattr(cfg.segment, 'method', 'paper')}  {mode}")
        for case in cases:
            try:
                row = evaluate(case, cfg, native=args.native, offset=args.offset,
                               use_mask=args.brain_mask,
                               oof=None if case.label is None else oof)
                print(_fmt(row), flush=True)
            except Exception as exc:  # report and continue with the next case
                print(f"{case.name:<12} FAILED: {type(exc).__name__}: {exc}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

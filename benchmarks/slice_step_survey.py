"""The header's slice step against the head's shape, on every scan of the shared data.

For each scan, read as the pipeline reads it (:func:`tumor3d.storage.readers.read_scan`),
the preprocess stage's figures (:func:`tumor3d.imaging.preprocess.brain_mask_figures`):
how far the head's outline moves between neighbouring slices (``outline_shift_mm``), in
slice steps, and whether :func:`tumor3d.imaging.preprocess.slice_step_note` doubts the
step. Groups: the clinical LGG heads (exported without their voxel size and written as a
nominal 1 mm), BraTS at 1 mm and cut to 5 mm slices (every 5th slice), every sequence of
the BraTS cases and the algoseg case cut as the evaluation cuts them (2 mm slabs every
5 mm, the mean of two 1 mm slices, offsets 0 and 2), the native clinical scans and the
brains without tumour (their true voxel size), and phantoms.

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/slice_step_survey.py [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.imaging.preprocess import (  # noqa: E402
    MAX_OUTLINE_SHIFT_STEPS,
    brain_mask_figures,
    preprocess_volume,
    slice_step_note,
)
from tumor3d.phantom import make_phantom_patient  # noqa: E402
from tumor3d.storage.readers import read_scan  # noqa: E402

NATIVE = (
    "tcga_fg_6692_native/fla.nii.gz", "tcga_fg_6692_native/t1.nii.gz",
    "tcga_fg_6692_native/t1c.nii.gz", "tcga_fg_6692_native/t2.nii.gz",
    "thick_t1c_brain2/image.nii.gz", "no_tumor/aniso_vox.nii.gz",
    "no_tumor/KmeansTest_T1UCharRaw.nii.gz",
)  # fmt: skip


def _row(group: str, name: str, image: np.ndarray, spacing_mm) -> dict:
    pre = preprocess_volume(image, spacing_mm=tuple(spacing_mm))
    f = brain_mask_figures(pre.brain_mask, tuple(spacing_mm), pre.brain_extraction, pre.original_u8)
    shift, step = f["outline_shift_mm"], f["slice_step_mm"]
    note = None if shift is None else slice_step_note(shift, step)
    return {
        "group": group, "case": name, "slice_step_mm": step, "outline_shift_mm": shift,
        "steps": None if shift is None else shift / step, "doubted": note is not None,
    }  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    data = Path(os.environ.get("TUMOR3D_DATA_DIR", ROOT.parent / "shared" / "data"))
    rows = []
    for f in sorted(data.glob("lgg_flair/*/flair.nii.gz")):
        s = read_scan(f, modality="flair")
        rows.append(_row("lgg (nominal 1 mm)", f.parent.name, s.image, s.spacing_zyx_mm))
    for f in sorted(data.glob("brats2018/*/flair.nii.gz")) + sorted(
        data.glob("brats2013_pat*/flair.nii.gz")
    ):
        s = read_scan(f, modality="flair")
        sp = s.spacing_zyx_mm
        rows.append(_row("brats 1 mm", f.parent.name, s.image, sp))
        rows.append(_row("brats 5 mm", f.parent.name, s.image[::5], (5 * sp[0], *sp[1:])))
        # the same brain as coronal and sagittal stacks, 1 mm and every 5th slice
        for plane, axes in (("coronal", (1, 0, 2)), ("sagittal", (2, 0, 1))):
            stack, spacing = s.image.transpose(axes), tuple(sp[a] for a in axes)
            rows.append(_row(f"brats {plane} 1 mm", f.parent.name, stack, spacing))
            rows.append(
                _row(
                    f"brats {plane} 5 mm", f.parent.name, stack[::5], (5 * spacing[0], *spacing[1:])
                )
            )
        # a slab off the brain's middle: its top 40 mm (no verdict: not through its widest part)
        top = np.flatnonzero(s.image.reshape(len(s.image), -1).max(axis=1) > 0)[-1]
        rows.append(_row("brats top 40 mm", f.parent.name, s.image[top - 39 : top + 1], sp))
    # every sequence as the evaluation and the cross-validation cut it: 2 mm slabs every 5 mm
    cases = sorted(data.glob("brats2018/*")) + sorted(data.glob("brats2013_pat*"))
    for d in [*cases, data / "brats_t2_algoseg"]:
        for f in sorted(d.glob("*.nii.gz")):
            if f.name.startswith(("seg", "brainmask")):
                continue
            s = read_scan(f, modality="t2")
            img, sp = s.image.astype(np.float32), s.spacing_zyx_mm
            for off in (0, 2):
                starts = range(off, len(img) - 1, 5)
                slabs = np.stack([img[k : k + 2].mean(axis=0) for k in starts])
                name = f"{d.name}/{f.name.split('.')[0]} offset {off}"
                group = "brats 2 mm slabs every 5 mm, every sequence"
                rows.append(_row(group, name, slabs, (5 * sp[0], *sp[1:])))
    for name in NATIVE:
        if (data / name).is_file():
            s = read_scan(data / name, modality="t2")
            rows.append(_row("native / no tumour", name, s.image, s.spacing_zyx_mm))
    for seed in range(1000, 1010):
        s = make_phantom_patient(seed, modality="flair" if seed % 2 else "t2").scan
        rows.append(_row("phantom", f"seed {seed}", s.image, s.spacing_zyx_mm))
    print(f"limit: {MAX_OUTLINE_SHIFT_STEPS:g} slice steps\n")
    print("| group | n | radius change in slice steps: min - median - max | no verdict | doubted |")
    print("|---|---|---|---|---|")
    for group in dict.fromkeys(r["group"] for r in rows):
        g = [r for r in rows if r["group"] == group]
        steps = np.array([r["steps"] for r in g if r["steps"] is not None])
        spread = (
            f"{steps.min():.2f} - {np.median(steps):.2f} - {steps.max():.2f}" if len(steps) else "-"
        )
        print(
            f"| {group} | {len(g)} | {spread} | {len(g) - len(steps)} | "
            f"{sum(r['doubted'] for r in g)} |"
        )
    for r in rows:
        if r["doubted"] and not r["group"].startswith("lgg"):
            print(f"doubted, its step correct: {r['group']}, {r['case']}: {r['steps']:.3f} steps")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

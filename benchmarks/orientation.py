"""The same patient stored in three orientations: does the result depend on the storage?

Each case is given to :func:`tumor3d.reconstruct` as an array with its affine
(the default method), stored as its file is (LPS: BraTS, the LGG heads, DICOM),
with its rows reversed (LAS, as many clinical NIfTI files) and with its slices
reversed (LPI, top down). Each mask is put back on the LPS voxels and scored
against the reference (slice Dice) and against the LPS run's mask. BraTS 2018
FLAIR cut to 2 mm slices every 5 mm as the evaluation does (slab ``i`` = mean
of 1 mm slices ``5 i + 2`` and ``5 i + 3``; reference = mean label >= 0.5);
LGG heads as they are.

The shipped models were trained on every case of ``$TUMOR3D_DATA_DIR``: these
are in-sample figures of how the storage moves the result, not accuracy.

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/orientation.py --json orientation.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import nibabel as nib
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.api import reconstruct  # noqa: E402
from tumor3d.evaluation.metrics import dice  # noqa: E402

CASES = (
    "brats2018/Brats18_2013_3_1", "brats2018/Brats18_CBICA_AME_1",
    "brats2018/Brats18_TCIA01_378_1", "brats2018/Brats18_TCIA01_499_1",
    "brats2018/Brats18_TCIA02_370_1", "brats2018/Brats18_TCIA10_637_1",
    "brats2018/Brats18_TCIA13_623_1", "lgg_flair/TCGA_CS_4942_19970222",
    "lgg_flair/TCGA_DU_5851_19950428", "lgg_flair/TCGA_FG_6688_20020215",
    "lgg_flair/TCGA_HT_7602_19951103", "lgg_flair/TCGA_DU_7014_19860618",
    "lgg_flair/TCGA_HT_8106_19970727",
)  # fmt: skip
#: storage name -> the voxel axes (i, j, k) reversed from the file's LPS
STORAGES = {"LPS": (), "LAS": (1,), "LPI": (2,)}


def _reversed(v: np.ndarray, affine: np.ndarray, axes: tuple[int, ...]):
    a = np.array(affine, dtype=float)
    for ax in axes:
        a[:3, 3] += a[:3, ax] * (v.shape[ax] - 1)
        a[:3, ax] *= -1.0
        v = np.flip(v, ax)
    return np.ascontiguousarray(v), a


def _case(data: Path, name: str):
    img = nib.load(data / name / "flair.nii.gz")
    v = np.asarray(img.dataobj, dtype=np.float32)
    lab = np.asarray(nib.load(data / name / "seg.nii.gz").dataobj) > 0
    if not name.startswith("brats2018/"):
        return v, img.affine, lab
    idx = 2 + 5 * np.arange((v.shape[2] - 4) // 5 + 1)
    thick = 0.5 * (v[:, :, idx] + v[:, :, idx + 1])
    a = img.affine.copy()
    a[:, 3] = img.affine @ np.r_[0.0, 0.0, 2.5, 1.0]
    a[:, 2] *= 5.0
    ref = 0.5 * (lab[:, :, idx].astype(float) + lab[:, :, idx + 1]) >= 0.5
    return thick, a, ref


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    data = Path(os.environ.get("TUMOR3D_DATA_DIR", ROOT.parent / "shared" / "data"))
    if not data.is_dir():
        print(f"skipped: no real data at {data} (set TUMOR3D_DATA_DIR)")
        return 0
    rows = []
    for name in args.cases:
        v, aff, ref = _case(data, name)
        masks = {}
        for storage, axes in STORAGES.items():
            sv, sa = _reversed(v, aff, axes)
            r = reconstruct(sv, affine=sa, modality="flair")
            m = np.asarray(r.on_input_grid(r.tumor_mask_slices))
            for ax in axes:
                m = np.flip(m, ax)  # back on the LPS voxels
            masks[storage] = m
            rows.append({
                "case": name, "storage": storage, "dice_ref": dice(m, ref),
                "dice_vs_lps": dice(m, masks["LPS"]), "voxels": int(m.sum()),
                "eq7_ml": float(r.volumes_ml["eq7"]),
            })  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    lps = {r["case"]: r for r in rows if r["storage"] == "LPS"}
    print(
        "\n| cases | storage | n | slice Dice vs reference | Dice vs the LPS mask (min) "
        "| volume change mean (max) |\n|---|---|---|---|---|---|"
    )
    for group in ("brats2018", "lgg_flair"):
        for storage in STORAGES:
            sel = [r for r in rows if r["case"].startswith(group) and r["storage"] == storage]
            if not sel:
                continue
            change = [abs(r["voxels"] / max(lps[r["case"]]["voxels"], 1) - 1) * 100 for r in sel]
            ref = np.mean([r["dice_ref"] for r in sel])
            same = [r["dice_vs_lps"] for r in sel]
            print(
                f"| {group} | {storage} | {len(sel)} | {ref:.3f} | {np.mean(same):.3f} "
                f"({min(same):.3f}) | {np.mean(change):.1f} % ({max(change):.1f} %) |"
            )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

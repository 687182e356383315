"""The default's answer on real scans stored with more or less air around the head.

Each case's file is written three more times into a temporary folder, the anatomy at
the same world positions (the affine's origin moved with the voxels): padded in-plane
with 20 pixels of the image's lowest value each side, cropped in-plane to the head (the
voxels above the median, plus 5 pixels), and with 20 slices of that value added above and
below. ``tumor3d.reconstruct`` (the default configuration, the shipped models) runs on
each, and the voxel count of the tumour on the acquired slices is compared with the
scan as stored. The cases: two BraTS 2018 FLAIR volumes at 1 mm, and the first, third and
fifth clinical LGG FLAIR heads (skull on) of ``$TUMOR3D_DATA_DIR``. The files' third
voxel axis is their slice axis.

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/fov_end_to_end.py [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import nibabel as nib
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import tumor3d  # noqa: E402

PAD_PX = 20


def variants(data: np.ndarray, affine: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The scan as stored, padded, cropped and with empty slices: (array, affine) each."""

    def moved(offset_ijk) -> np.ndarray:  # the affine of an array whose voxel 0 was offset_ijk
        out = affine.copy()
        out[:3, 3] = (affine @ np.r_[np.asarray(offset_ijk, float), 1.0])[:3]
        return out

    low = data.min()
    padded = np.pad(data, ((PAD_PX, PAD_PX), (PAD_PX, PAD_PX), (0, 0)), constant_values=low)
    head = (data > np.median(data)).any(axis=2)
    rows, cols = np.flatnonzero(head.any(axis=1)), np.flatnonzero(head.any(axis=0))
    i0, j0 = max(0, rows[0] - 5), max(0, cols[0] - 5)
    cropped = data[i0 : rows[-1] + 6, j0 : cols[-1] + 6]
    slabs = np.pad(data, ((0, 0), (0, 0), (PAD_PX, PAD_PX)), constant_values=low)
    return {
        "stored": (data, affine),
        "padded": (padded, moved((-PAD_PX, -PAD_PX, 0))),
        "cropped": (cropped, moved((i0, j0, 0))),
        "empty slices": (slabs, moved((0, 0, -PAD_PX))),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    data_dir = Path(os.environ.get("TUMOR3D_DATA_DIR", ROOT.parent / "shared" / "data"))
    cases = [
        data_dir / f"brats2018/{n}/flair.nii.gz"
        for n in ("Brats18_2013_3_1", "Brats18_CBICA_AME_1")
    ]
    cases += sorted(data_dir.glob("lgg_flair/*/flair.nii.gz"))[:6:2]
    rows = []
    print("| case | " + " | ".join(("stored", "padded", "cropped", "empty slices")) + " |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for f in cases:
            img = nib.load(f)
            name = f.parent.name
            counts, status = {}, {}
            for v, (arr, affine) in variants(np.asanyarray(img.dataobj), img.affine).items():
                path = Path(tmp) / f"{name}_{v.replace(' ', '_')}.nii.gz"
                nib.save(nib.Nifti1Image(arr, affine, img.header), path)
                r = tumor3d.reconstruct(path, modality="flair", patient_id=name)
                counts[v], status[v] = int(np.count_nonzero(r.tumor_mask_slices)), r.status
            base = counts["stored"]
            cells = [f"{base} voxels, {status['stored']}"] + [
                f"{100 * (counts[v] - base) / max(base, 1):+.1f} %, {status[v]}"
                for v in ("padded", "cropped", "empty slices")
            ]
            print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
            rows.append({"case": name, "voxels": counts, "status": status})
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

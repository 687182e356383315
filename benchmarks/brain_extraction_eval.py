"""Brain-mask volumes of remove_skull and extract_brain on the real volumes.

For each raw head of the data folder prints the brain volume (mL) of the
current per-slice :func:`tumor3d.imaging.preprocess.remove_skull` and of
:func:`tumor3d.imaging.brain_extraction.extract_brain`, the Dice against
``brainmask.nii.gz`` where there is one (BraTS), and the time; writes a
montage of the mask contours (red: extract_brain, blue: remove_skull).

Usage::

    python benchmarks/brain_extraction_eval.py [--data DIR] [--png PATH]

``--data`` defaults to ``$TUMOR3D_DATA_DIR`` or ``../shared/data`` relative
to the repository; the script skips with a message if it is absent.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.imaging.brain_extraction import extract_brain  # noqa: E402
from tumor3d.imaging.preprocess import remove_skull, to_uint8  # noqa: E402
from tumor3d.storage.manifest import data_dir  # noqa: E402
from tumor3d.storage.readers import read_scan  # noqa: E402

VOLUMES = [
    ("thick_t1c_brain2/image.nii.gz", "t1c"),
    ("no_tumor/KmeansTest_T1UCharRaw.nii.gz", "t1c"),  # reader knows t2/flair/t1c only
    ("tcga_fg_6692_native/t1c.nii.gz", "t1c"),
    ("tcga_fg_6692_native/t1.nii.gz", "t1c"),
    ("tcga_fg_6692_native/t2.nii.gz", "t2"),
    ("tcga_fg_6692_native/fla.nii.gz", "flair"),
    ("no_tumor/aniso_vox.nii.gz", "t2"),
    ("brats2013_pat0003/flair.nii.gz", "flair"),
    ("brats2013_pat0003/t1c.nii.gz", "t1c"),
]


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    denom = np.count_nonzero(a) + np.count_nonzero(b)
    return 2.0 * np.count_nonzero(a & b) / denom if denom else 1.0


def _tiles(image: np.ndarray, new: np.ndarray, old: np.ndarray, n: int = 8) -> np.ndarray:
    from PIL import Image

    tiles = []
    for z in np.linspace(0, image.shape[0] - 1, n).round().astype(int):
        rgb = np.stack([image[z]] * 3, -1).copy()
        rgb[old[z] & ~ndi.binary_erosion(old[z])] = [60, 120, 255]
        rgb[new[z] & ~ndi.binary_erosion(new[z])] = [255, 0, 0]
        tiles.append(np.array(Image.fromarray(rgb).resize((200, 200))))
    return np.concatenate(tiles, 1)


def main() -> None:
    default_data = data_dir()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=default_data)
    parser.add_argument(
        "--png", type=Path, default=Path(tempfile.gettempdir()) / "brain_extraction_eval.png"
    )
    args = parser.parse_args()
    if not args.data.is_dir():
        print(f"data folder {args.data} not found: skipping (set TUMOR3D_DATA_DIR)")
        return
    print(
        "| volume | spacing (mm) | remove_skull mL | extract_brain mL | Dice old | Dice new "
        "| time old s | time new s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for rel, modality in VOLUMES:
        path = args.data / rel
        if not path.exists():
            print(f"| {rel} | missing | | | | | | |")
            continue
        scan = read_scan(path, modality=modality)
        image = to_uint8(scan.image)
        spacing = (scan.slice_step_mm, *scan.pixel_spacing_mm)
        voxel_ml = float(np.prod(spacing)) / 1000.0
        t0 = time.perf_counter()
        old = remove_skull(image)
        t1 = time.perf_counter()
        new = extract_brain(image, spacing)
        t2 = time.perf_counter()
        ref_path = path.parent / "brainmask.nii.gz"
        d_old = d_new = ""
        if ref_path.exists():
            ref = read_scan(ref_path, modality=modality).image > 0
            d_old, d_new = f"{_dice(old, ref):.3f}", f"{_dice(new, ref):.3f}"
        print(
            f"| {rel} | {', '.join(f'{s:.2f}' for s in spacing)} | "
            f"{old.sum() * voxel_ml:.0f} | {new.sum() * voxel_ml:.0f} | {d_old} | {d_new} | "
            f"{t1 - t0:.2f} | {t2 - t1:.2f} |",
            flush=True,
        )
        rows.append(_tiles(image, new, old))
    if rows:
        from PIL import Image

        args.png.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.concatenate(rows, 0)).save(args.png)
        print(f"montage (red extract_brain, blue remove_skull): {args.png}")


if __name__ == "__main__":
    main()

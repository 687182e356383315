"""Write the manifest ``tumor3d train`` learns the shipped models from.

Every labelled case of ``$TUMOR3D_DATA_DIR`` (default ``../shared/data``),
as :mod:`learned_cv` groups them, plus ``--phantoms N`` FLAIR and T2
phantoms (seeds 1000 on; the tests use seeds below 100) written under the
output folder with their truth as the reference:

- BraTS (2018, 2013, the algoseg case): FLAIR, T2 and T1c, emulated as the
  paper's acquisition (``emulate_step_mm`` 5, ``emulate_thickness_mm`` 2);
  FLAIR/T2 reference = every label > 0 (whole tumour), T1c = tumour core
  (labels 1 and 4; algoseg 1 and 3);
- the clinical LGG FLAIR heads and ``thick_t1c_brain2`` at their native
  slices.

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/training_manifest.py --out /tmp/train-in
    tumor3d train /tmp/train-in/manifest.csv --out /tmp/model --t1c-threshold 0.65

The data stay where they are (the manifest names them); only the phantoms
are written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from learned_cv import PHANTOM_SEED0, case_specs  # noqa: E402

from tumor3d.phantom import make_phantom_patient  # noqa: E402
from tumor3d.storage.manifest import ManifestRow, data_dir, write_manifest  # noqa: E402
from tumor3d.storage.phantom_io import write_phantom_patient  # noqa: E402

#: The paper's acquisition emulated on 1 mm BraTS volumes (2 mm slices every 5 mm).
STEP_MM, THICKNESS_MM = 5.0, 2.0


def training_rows(data: Path) -> list[ManifestRow]:
    """One manifest row per labelled case of ``data`` (see the module docstring)."""
    rows = []
    for s in case_specs(data):
        pid = s.name.replace("/", "_")
        emulate = (
            {} if s.native else {"emulate_step_mm": STEP_MM, "emulate_thickness_mm": THICKNESS_MM}
        )
        rows.append(
            ManifestRow(
                patient_id=pid,
                image=Path(s.image),
                modality=s.modality,
                reference=Path(s.label),
                reference_labels=s.labels,
                reference_kind="expert" if s.source != "algoseg" else "algorithmic",
                **emulate,
            )
        )
    return rows


def phantom_rows(n: int, folder: Path) -> list[ManifestRow]:
    """``n`` FLAIR and ``n`` T2 phantoms written under ``folder``."""
    rows = []
    for i in range(n):
        seed = PHANTOM_SEED0 + i
        for mod in ("flair", "t2"):
            pid = f"phantom{seed}_{mod}"
            patient = make_phantom_patient(seed, modality=mod, patient_id=pid)
            rows.append(write_phantom_patient(patient, folder / pid))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="folder for manifest.csv and the phantoms")
    ap.add_argument("--phantoms", type=int, default=10, help="FLAIR and T2 phantoms each")
    args = ap.parse_args(argv)
    out = Path(args.out)
    data = data_dir()
    rows = training_rows(data) if data.is_dir() else []
    if not rows:
        print(f"note: no labelled data at {data} (set TUMOR3D_DATA_DIR); phantoms only")
    rows += phantom_rows(args.phantoms, out / "phantoms")
    path = write_manifest(rows, out / "manifest.csv")
    print(f"wrote {path}: {len(rows)} rows")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

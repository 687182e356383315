"""Write synthetic phantom patients to disk as a user would receive real data.

Per patient ``<pid>``, in ``<folder>``:

* ``<pid>_t2.nii.gz`` (or ``_flair``): the thick-slice image, with a
  BIDS-style sidecar ``<pid>_t2.json`` giving ``SliceThickness`` and
  ``SpacingBetweenSlices``;
* ``<pid>_truth_fine.nii.gz``: the true tumour on a fine grid (the
  manifest's ``reference``), in the same world space;
* ``<pid>_truth_slices.nii.gz``: the true tumour on each acquired slice;
* ``<pid>_truth.json``: the exact tumour volume and the phantom parameters.

Its manifest row names the fine truth as ``reference`` with ``reference_kind``
``truth``; a tumour-free patient's row has no reference and ``reference_kind``
``tumor_free``, so that ``tumor3d evaluate`` scores both.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from tumor3d.phantom import PhantomPatient
from tumor3d.storage import nifti
from tumor3d.storage.atomic import atomic_write_bytes
from tumor3d.storage.manifest import ManifestRow, write_manifest

__all__ = ["write_phantom_cohort", "write_phantom_patient"]


def write_phantom_patient(patient: PhantomPatient, folder: str | Path) -> ManifestRow:
    """Write one phantom patient's image, sidecar and truth; return its manifest row."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    scan = patient.scan
    pid = scan.patient_id
    image_path = folder / f"{pid}_{scan.modality}.nii.gz"
    grid = scan.source_grid
    atomic_write_bytes(
        image_path,
        nifti.encode_nifti(grid.to_source(scan.image), grid.affine, dtype="float32"),
    )
    sidecar = {
        "SliceThickness": scan.slice_thickness_mm,
        "SpacingBetweenSlices": scan.slice_step_mm,
        "Modality": "MR",
        "tumor3dNote": "synthetic phantom; SpacingBetweenSlices is centre to centre (BIDS)",
    }
    atomic_write_bytes(
        image_path.with_name(f"{pid}_{scan.modality}.json"),
        (json.dumps(sidecar, indent=2) + "\n").encode(),
    )
    fine_path = folder / f"{pid}_truth_fine.nii.gz"
    fine_arr, fine_aff = grid.to_source_with_affine(patient.fine_mask, patient.fine_affine)
    atomic_write_bytes(fine_path, nifti.encode_nifti(fine_arr, fine_aff, dtype="uint8"))
    atomic_write_bytes(
        folder / f"{pid}_truth_slices.nii.gz",
        nifti.mask_to_source_nifti_bytes(patient.slice_masks, grid),
    )
    truth: dict[str, Any] = {
        "patient_id": pid,
        "true_volume_mm3": patient.true_volume_mm3,
        "true_volume_ml": patient.true_volume_mm3 / 1000.0,
        "params": patient.params,
    }
    atomic_write_bytes(
        folder / f"{pid}_truth.json", (json.dumps(truth, indent=2, default=float) + "\n").encode()
    )
    # the truth is the reference of a tumour; a tumour-free patient's row says so (its
    # empty truth file is written all the same), so that `tumor3d evaluate` takes both
    tumour = patient.true_volume_mm3 > 0
    return ManifestRow(
        patient_id=pid,
        image=image_path.resolve(),
        modality=scan.modality,
        reference=fine_path.resolve() if tumour else None,
        reference_labels=(1,) if tumour else None,
        slice_thickness_mm=None,
        slice_gap_mm=None,
        reference_kind="truth" if tumour else "tumor_free",
    )


def write_phantom_cohort(
    patients: list[PhantomPatient], folder: str | Path, *, manifest_name: str = "manifest.csv"
) -> Path:
    """Write patients and a cohort manifest ``<folder>/<manifest_name>``; return its path."""
    folder = Path(folder)
    rows = [write_phantom_patient(p, folder / p.scan.patient_id) for p in patients]
    manifest = folder / manifest_name
    write_manifest(rows, manifest)
    return manifest

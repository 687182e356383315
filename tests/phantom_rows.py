"""Small phantom patients written as manifest rows, each phantom made once per process.

Small phantoms (128 x 128 pixels of 1.875 mm, the default field of view, 16 slices):
what the flow tests that use them check does not depend on the image size, and a run
costs a third. A phantom's arrays are read-only, so one made here is shared safely.
"""

from __future__ import annotations

import functools
from pathlib import Path

from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.manifest import ManifestRow
from tumor3d.storage.phantom_io import write_phantom_patient

SMALL = {"n_slices": 16, "matrix_size": (128, 128)}


@functools.cache
def _small_phantom(seed: int, patient_id: str):
    return make_phantom_patient(seed, patient_id=patient_id, **SMALL)


def small_phantom_rows(folder: Path, seeds, prefix: str) -> list[ManifestRow]:
    """Write phantom ``seed`` as patient ``{prefix}{seed}`` under ``folder``, for each seed."""
    return [
        write_phantom_patient(_small_phantom(s, f"{prefix}{s}"), Path(folder) / f"{prefix}{s}")
        for s in seeds
    ]

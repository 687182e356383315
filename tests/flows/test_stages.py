"""Stage tasks called directly (``task.fn``, no Prefect): edge cases of the wiring."""

from __future__ import annotations

import numpy as np
import pytest

from flows.patient import run_stages_direct
from storage.phantom_io import write_phantom_patient
from storage.store import ArtifactStore
from tasks import stages
from tumor3d.config import SimplifyConfig
from tumor3d.mesh import Mesh
from tumor3d.phantom import make_phantom_patient


def test_tumour_free_patient_completes_with_zero_volume_and_no_render(tmp_path):
    patient = make_phantom_patient(1, tumor=False, patient_id="normal1")
    image = write_phantom_patient(patient, tmp_path / "in").image
    run = run_stages_direct(image, tmp_path / "store", patient_id="normal1")
    volumes = run.outputs["measure-volume"].values
    for key in ("volume_eq7_mm3", "volume_voxel_mm3", "volume_mesh_mm3"):
        assert volumes[key] == 0.0
    assert volumes["n_tumor_slices"] == 0
    assert run.outputs["extract-surface"].values["faces"] == 0
    assert run.outputs["render-views"].artifacts == {}


def _tetrahedron() -> Mesh:
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=float)
    return Mesh(v, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))


@pytest.mark.parametrize("percent", [60.0, 99.0])
def test_mesh_too_small_to_simplify_passes_through(tmp_path, percent):
    store = ArtifactStore(tmp_path)
    ref = store.put_mesh(_tetrahedron())
    out = stages.simplify_task.fn(
        mesh=ref, config=SimplifyConfig(reduction_percent=percent), store_root=str(store.root)
    )
    assert out.values["simplified"] is False
    assert out.values["faces"] == 4 and out.values["watertight"] is True
    assert out.artifacts["mesh"].digest == ref.digest  # unchanged, same artifact

"""Tests of tumor3d.brain_surface.display_mesh: the brain reduced for the viewer."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.brain_surface import display_mesh
from tumor3d.errors import InputError
from tumor3d.pipeline import is_closed_surface
from tumor3d.surface import extract_surface, mesh_volume_mm3


@pytest.fixture(scope="module")
def ellipsoid():
    size, c = 64, 31.5
    z, y, x = np.ogrid[:size, :size, :size]
    mask = ((x - c) / 28) ** 2 + ((y - c) / 25) ** 2 + ((z - c) / 22) ** 2 <= 1
    aff = np.diag([1.0, 1.0, 1.5, 1.0])
    return extract_surface(mask, aff)


def test_reduced_to_the_budget_closed_and_about_the_same_volume(ellipsoid):
    assert ellipsoid.n_faces > 20000
    light = display_mesh(ellipsoid, 3000)
    assert 2900 <= light.n_faces <= 3000
    assert is_closed_surface(light)  # no holes to see through
    v0, v1 = mesh_volume_mm3(ellipsoid), mesh_volume_mm3(light)
    assert abs(v1 - v0) / v0 < 0.01
    # the shape is kept: same bounding box within 1.5 mm
    np.testing.assert_allclose(light.vertices.min(axis=0), ellipsoid.vertices.min(axis=0), atol=1.5)
    np.testing.assert_allclose(light.vertices.max(axis=0), ellipsoid.vertices.max(axis=0), atol=1.5)


def test_a_mesh_within_the_budget_is_returned_as_is(ellipsoid):
    assert display_mesh(ellipsoid, ellipsoid.n_faces) is ellipsoid


@pytest.mark.parametrize("bad", [0, 99, 2.5, True, "1000"])
def test_bad_budget(ellipsoid, bad):
    with pytest.raises(InputError, match="max_faces"):
        display_mesh(ellipsoid, bad)

"""Tests of tumor3d.geometry.brain_surface.display_mesh: the brain reduced for the viewer."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.geometry.brain_surface import brain_surface, display_mesh
from tumor3d.geometry.surface import extract_surface, mesh_volume_mm3
from tumor3d.pipeline import is_closed_surface


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


def _ball_slices(radius_mm, pixel_mm, step_mm, n_px=48):
    """A ball of ``radius_mm`` sampled on thick slices, its (z, y, x) mask and affine."""
    nz = int(2 * radius_mm / step_mm) + 3
    z = (np.arange(nz) - (nz - 1) / 2) * step_mm
    y = (np.arange(n_px) - (n_px - 1) / 2) * pixel_mm
    zz, yy, xx = np.meshgrid(z, y, y, indexing="ij")
    mask = zz**2 + yy**2 + xx**2 <= radius_mm**2
    return mask, np.diag([pixel_mm, pixel_mm, step_mm, 1.0])


def test_the_grid_is_coarsened_over_an_extent_larger_than_its_budget(monkeypatch):
    """The surface stays a closed ball of about its volume, on a grid within the budget."""
    import tumor3d.geometry.brain_surface as bs

    mask, aff = _ball_slices(60.0, 3.0, 6.0)
    true_ml = 4.0 / 3.0 * np.pi * 60.0**3 / 1000.0
    fine = bs.brain_surface(mask, aff)
    budget = 20_000  # far below the 2 mm grid's ~1.4 M voxels: about a 5 mm grid
    monkeypatch.setattr(bs, "MAX_GRID_VOXELS", budget)
    seen = []
    from tumor3d.geometry import surface

    original = surface.extract_surface

    def spy(grid, affine, **kw):
        seen.append(grid.size)
        return original(grid, affine, **kw)

    monkeypatch.setattr(surface, "extract_surface", spy)
    coarse = bs.brain_surface(mask, aff)
    assert seen and seen[0] <= budget
    for mesh in (fine, coarse):
        assert is_closed_surface(mesh)
        assert mesh_volume_mm3(mesh) / 1000.0 == pytest.approx(true_ml, rel=0.1)


def test_a_mask_of_specks_narrower_than_the_grid_has_an_empty_surface():
    """A user audit: an image of pure noise kept an 80-voxel brain mask of specks, which
    vanished on the 2 mm grid; the brain-surface stage then failed the run with "the mask
    holds no voxel", naming no file. Specks are drawn as no brain (the preprocess stage's
    notes say the brain was lost); a small but real brain still has its surface."""
    mask = np.zeros((10, 64, 64), bool)
    mask[::3, ::9, ::7] = True  # isolated single voxels, 0.5 mm pixels
    affine = np.diag([0.5, 0.5, 5.0, 1.0])
    assert brain_surface(mask, affine, spacing_mm=2.0).n_faces == 0
    blob = np.zeros_like(mask)
    blob[3:7, 20:40, 20:40] = True
    assert brain_surface(blob, affine, spacing_mm=2.0).n_faces > 0

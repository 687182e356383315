"""The Scan and SourceGrid data models validate themselves and round-trip grids."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.imaging.affine import zyx_index_to_ras
from tumor3d.imaging.identity import validate_patient_id
from tumor3d.imaging.scan import Scan, SourceGrid


def _scan(**overrides):
    kw = dict(
        image=np.ones((2, 3, 4), np.float32),
        affine=np.diag([-0.9, -0.8, 5.0, 1.0]),
        pixel_spacing_mm=(0.8, 0.9),
        slice_step_mm=5.0,
        slice_thickness_mm=2.0,
        slice_gap_mm=3.0,
        modality="t2",
        patient_id="p1",
        source="test",
        source_grid=SourceGrid(shape=(4, 3, 2), affine=np.diag([-0.9, -0.8, 5.0, 1.0])),
    )
    kw.update(overrides)
    return Scan(**kw)


@pytest.mark.parametrize("bad", ["", "..", ".hidden", "a/b", "../x", "a\\b", "x" * 129, "é"])
def test_unsafe_patient_ids_are_refused(bad):
    with pytest.raises(InputError, match="unsafe patient id"):
        validate_patient_id(bad)


def test_safe_patient_id_is_returned_unchanged():
    assert validate_patient_id("BraTS_2013-pat.0003") == "BraTS_2013-pat.0003"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"modality": "pd"}, "unknown modality"),
        ({"slice_step_mm": 0.0}, "slice step"),
        ({"pixel_spacing_mm": (0.8, float("nan"))}, "pixel spacing dx"),
        ({"image": np.ones((3, 4), np.float32)}, "must be 3-D"),
        ({"patient_id": "../p"}, "unsafe patient id"),
    ],
)
def test_scan_rejects_invalid_fields(overrides, message):
    with pytest.raises(InputError, match=message):
        _scan(**overrides)


def test_scan_copies_and_freezes_its_image():
    image = np.ones((2, 3, 4), np.float32)
    scan = _scan(image=image)
    image[0, 0, 0] = 7.0
    assert scan.image[0, 0, 0] == 1.0
    assert not scan.image.flags.writeable
    assert scan.slab_height_mm == 5.0 and scan.pixel_area_mm2 == pytest.approx(0.72)


def test_source_grid_round_trip_for_a_permuted_source():
    rng = np.random.default_rng(0)
    source = rng.random((5, 3, 4))  # slice axis first in the source
    grid = SourceGrid(shape=source.shape, affine=np.eye(4), axes=(1, 2, 0))
    zyx = source.transpose(grid.axes).transpose(2, 1, 0)  # what a reader builds
    np.testing.assert_array_equal(grid.to_source(zyx), source)
    with pytest.raises(ValueError, match="does not match"):
        grid.to_source(zyx[:-1])
    # and back: a mask given in the file's voxel order, on the scan's grid
    np.testing.assert_array_equal(grid.from_source(source), zyx)
    with pytest.raises(ValueError, match="does not match"):
        grid.from_source(source[:-1])


def test_zyx_index_to_ras_reverses_axes_before_the_affine():
    affine = np.array([[2.0, 0, 0, 10], [0, 3.0, 0, 20], [0, 0, 5.0, 30], [0, 0, 0, 1]])
    # (z, y, x) = (1, 2, 3) -> voxel (x, y, z) = (3, 2, 1) -> RAS (16, 26, 35)
    np.testing.assert_allclose(zyx_index_to_ras([[1, 2, 3]], affine), [[16.0, 26.0, 35.0]])

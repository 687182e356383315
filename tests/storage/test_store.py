"""Artifact store: content addressing, atomic writes, integrity, codecs."""

from __future__ import annotations

import dataclasses
import gzip
import json
import os

import numpy as np
import pandas as pd
import pytest

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.imaging.scan import Scan, SourceGrid
from tumor3d.storage import formats
from tumor3d.storage.atomic import atomic_write_bytes
from tumor3d.storage.inputs import input_digest
from tumor3d.storage.refs import StoreError
from tumor3d.storage.store import ArtifactStore


@pytest.fixture
def store(tmp_path):
    return ArtifactStore(tmp_path / "store")


def _tetrahedron() -> Mesh:
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=float) + 0.125
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return Mesh(v, f)


def test_same_content_same_ref_one_file(store):
    a = store.put_bytes(b"hello", kind="json", suffix=".json", metadata={"k": 1})
    b = store.put_bytes(b"hello", kind="json", suffix=".json", metadata={"k": 1})
    assert a == b
    files = [p for p in (store.root / "objects").rglob("*") if p.is_file()]
    assert len(files) == 1
    assert store.get_bytes(a) == b"hello"


def test_digest_covers_metadata_not_only_bytes(store):
    # Same bytes, different spacing: must be different artifacts (Pydra once missed this).
    a = store.put_bytes(b"x" * 10, kind="image", suffix=".bin", metadata={"spacing": [1, 1, 1]})
    b = store.put_bytes(b"x" * 10, kind="image", suffix=".bin", metadata={"spacing": [1, 1, 5]})
    assert a.digest != b.digest


def test_volume_digest_depends_on_affine_dtype_and_shape(store):
    arr = np.zeros((2, 3, 4), dtype=np.uint8)
    arr[1, 1, 1] = 1
    base = store.put_volume(arr, np.eye(4))
    assert store.put_volume(arr, np.diag([1, 1, 5, 1])).digest != base.digest
    assert store.put_volume(arr, np.eye(4), dtype="int16").digest != base.digest
    assert store.put_volume(arr.reshape(2, 4, 3), np.eye(4)).digest != base.digest
    assert store.put_volume(arr.copy(), np.eye(4)).digest == base.digest


def test_volume_round_trip_exact(store):
    rng = np.random.default_rng(0)
    arr = rng.normal(size=(3, 5, 7)).astype(np.float32)
    affine = np.array([[-0.9, 0, 0, 10.5], [0, -0.8, 0, -3], [0, 0, 5, 7.25], [0, 0, 0, 1]])
    ref = store.put_volume(arr, affine)
    back, back_affine = store.get_volume(ref)
    np.testing.assert_array_equal(back, arr)
    np.testing.assert_allclose(back_affine, affine, atol=1e-6)
    assert ref.metadata["shape_zyx"] == [3, 5, 7]


def test_mask_comes_back_boolean(store):
    mask = np.zeros((2, 4, 4), dtype=bool)
    mask[0, 1:3, 1:3] = True
    back, _ = store.get_volume(store.put_volume(mask, np.eye(4), kind="mask"))
    assert back.dtype == bool
    np.testing.assert_array_equal(back, mask)


def test_corrupted_artifact_is_detected(store):
    ref = store.put_bytes(b"original", kind="json", suffix=".json")
    store.path(ref).write_bytes(b"tampered")
    with pytest.raises(StoreError, match="corrupted"):
        store.get_bytes(ref)


def test_missing_artifact_names_the_file(store):
    ref = store.put_bytes(b"data", kind="json", suffix=".json")
    store.path(ref).unlink()
    assert not store.exists(ref)
    with pytest.raises(StoreError, match="missing"):
        store.get_bytes(ref)


def test_atomic_write_leaves_nothing_on_crash(tmp_path, monkeypatch):
    target = tmp_path / "out" / "artifact.bin"

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_bytes(target, b"payload")
    assert not target.exists()
    assert list(target.parent.iterdir()) == []  # no temporary left behind either


def test_a_write_error_without_a_file_names_the_file_and_no_assets_folder_is_left(
    tmp_path, monkeypatch
):
    """A full disk fails a write or its fsync with no file name ("no space left on device"
    alone, a user audit): the error names the file it was for; the viewer's assets folder
    a failed call made is not left behind, empty."""
    import errno

    from tumor3d.storage.viewer import ASSETS_DIR, write_viewer_assets

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    target = tmp_path / "out" / "artifact.bin"
    with pytest.raises(OSError) as exc:
        atomic_write_bytes(target, b"payload")
    assert (exc.value.errno, exc.value.filename) == (errno.ENOSPC, str(target))
    assert list(target.parent.iterdir()) == []
    with pytest.raises(OSError) as exc:
        write_viewer_assets(tmp_path / "cohort")
    assert exc.value.filename.startswith(str(tmp_path / "cohort" / ASSETS_DIR))
    assert list((tmp_path / "cohort").iterdir()) == []


def test_atomic_write_replaces_whole_file(tmp_path):
    target = tmp_path / "a.bin"
    atomic_write_bytes(target, b"first version, long")
    atomic_write_bytes(target, b"second")
    assert target.read_bytes() == b"second"


def test_scan_round_trip_keeps_geometry(store):
    img = np.arange(2 * 3 * 4, dtype=np.float32).reshape(2, 3, 4) + 1
    affine = np.array([[-0.9, 0, 0, 1], [0, 0, 5, 2], [0, -0.8, 0, 3], [0, 0, 0, 1]], float)
    grid = SourceGrid(shape=(4, 2, 3), affine=np.eye(4), axes=(1, 2, 0))
    scan = Scan(img, affine, (0.8, 0.9), 5.0, 2.0, 3.0, "flair", "p01", "test", grid)
    ref = store.put_scan(scan)
    back = store.get_scan(ref, patient_id="p01")
    np.testing.assert_array_equal(back.image, scan.image)
    np.testing.assert_allclose(back.affine, scan.affine)
    assert back.pixel_spacing_mm == scan.pixel_spacing_mm
    assert (back.slice_step_mm, back.slice_thickness_mm, back.slice_gap_mm) == (5.0, 2.0, 3.0)
    assert (back.modality, back.patient_id, back.source) == ("flair", "p01", "test")
    assert back.source_grid.axes == grid.axes and back.source_grid.shape == grid.shape
    assert back.orientation_stated
    assumed = dataclasses.replace(scan, orientation_stated=False)
    assert not store.get_scan(store.put_scan(assumed), patient_id="p01").orientation_stated
    assert back.source_grid.flips == (False,) * 3 and back.source_grid.xform_codes == (1, 1)
    # a file's axis reversals and header codes, which its outputs are written back with
    kept = dataclasses.replace(
        scan, source_grid=dataclasses.replace(grid, flips=(True, False, True), xform_codes=(0, 0))
    )
    kept_back = store.get_scan(store.put_scan(kept), patient_id="p01").source_grid
    assert kept_back.flips == (True, False, True) and kept_back.xform_codes == (0, 0)
    assert back.source_grid.qform is None
    qform = np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * 5.0  # shifted 5 mm in x
    moved = dataclasses.replace(scan, source_grid=dataclasses.replace(grid, qform=qform))
    moved_back = store.get_scan(store.put_scan(moved), patient_id="p01").source_grid
    np.testing.assert_array_equal(moved_back.qform, qform)
    # the patient id is not stored (issue 29): the same image under another id is the
    # same artifact, and the reader names the patient
    assert "p01" not in json.dumps(ref.metadata)
    other = dataclasses.replace(scan, patient_id="p02")
    assert store.put_scan(other) == ref
    assert store.get_scan(ref, patient_id="p02").patient_id == "p02"


def test_ply_round_trip_and_slicer_header():
    mesh = _tetrahedron()
    data = formats.encode_ply(mesh)
    assert b"comment SPACE=RAS" in data.split(b"end_header")[0]
    back = formats.decode_ply(data)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_allclose(back.vertices, mesh.vertices, rtol=1e-6)
    assert formats.encode_ply(mesh) == data  # deterministic


def test_ply_rejects_garbage():
    with pytest.raises(InputError, match="not a PLY"):
        formats.decode_ply(b"hello world", name="x.ply")
    truncated = formats.encode_ply(_tetrahedron())[:-5]
    with pytest.raises(InputError, match="does not match"):
        formats.decode_ply(truncated, name="x.ply")


def test_parquet_and_png_round_trip_deterministic():
    df = pd.DataFrame({"slice_index": [0, 1], "abnormal": [False, True], "area_mm2": [0.0, 1.5]})
    data = formats.encode_parquet(df)
    assert formats.encode_parquet(df) == data
    pd.testing.assert_frame_equal(formats.decode_parquet(data), df)
    rgb = np.random.default_rng(1).integers(0, 256, size=(8, 9, 3), dtype=np.uint8)
    png = formats.encode_png(rgb)
    assert formats.encode_png(rgb) == png
    np.testing.assert_array_equal(formats.decode_png(png), rgb)


def test_input_digest_follows_content_and_sidecar_not_location(tmp_path):
    a = tmp_path / "a"
    a.mkdir()
    img = a / "x.nii.gz"
    img.write_bytes(gzip.compress(b"image bytes", mtime=0))
    d0 = input_digest(img)
    (a / "x.json").write_text('{"SliceThickness": 2}')
    d1 = input_digest(img)
    assert d1 != d0  # the sidecar changes thickness, so it must change the key
    b = tmp_path / "b"
    b.mkdir()
    (b / "x.nii.gz").write_bytes(img.read_bytes())
    (b / "x.json").write_text('{"SliceThickness": 2}')
    assert input_digest(b / "x.nii.gz") == d1  # moved, same content


def test_input_digest_of_folder_and_missing(tmp_path):
    folder = tmp_path / "series"
    folder.mkdir()
    (folder / "1.dcm").write_bytes(b"one")
    (folder / "2.dcm").write_bytes(b"two")
    d0 = input_digest(folder)
    (folder / "2.dcm").write_bytes(b"TWO")
    assert input_digest(folder) != d0
    with pytest.raises(InputError, match="no such file"):
        input_digest(tmp_path / "nope.nii.gz")

"""Reading options checked once, formats in a registry, the input read once per run."""

from __future__ import annotations

import os

import nibabel as nib
import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.imaging.scan import Scan
from tumor3d.storage.readers import ReadOptions, derive_patient_id, handoff, read_scan, registry
from tumor3d.storage.readers.common import scan_from_volume
from tumor3d.storage.store import ArtifactStore


def _nifti(path, seed=0, shape=(12, 10, 5)):
    data = np.random.default_rng(seed).random(shape).astype(np.float32) * 100
    nib.save(nib.Nifti1Image(data, np.diag([1.0, 1.0, 3.0, 1.0])), path)
    return path


@pytest.mark.parametrize(
    "keywords, message",
    [
        ({"modality": "t1"}, "unknown modality 't1': expected one of t2, flair, t1c"),
        ({"patient_id": "../x"}, "unsafe patient id '../x'"),
        ({"slice_thickness_mm": 0}, "slice_thickness_mm must be a positive number of mm"),
        ({"slice_gap_mm": -1}, "slice_gap_mm must be a non-negative number of mm"),
        ({"max_voxels": 0}, "max_voxels must be an integer >= 1, got 0"),
        ({"dicom_series": "1.2"}, "unknown reading option 'dicom_series'"),
    ],
)
def test_options_are_refused_once_with_the_readers_own_line(tmp_path, keywords, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ReadOptions(**keywords)
    # read_scan's keywords go through the same model: the same line
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_scan(_nifti(tmp_path / "a.nii.gz"), **keywords)


def test_options_object_and_keywords_read_the_same_scan(tmp_path):
    path = _nifti(tmp_path / "a.nii.gz")
    kw = {"modality": "FLAIR", "slice_thickness_mm": 2.5, "slice_gap_mm": 0.5}
    a, b = read_scan(path, ReadOptions(**kw)), read_scan(path, **kw)
    np.testing.assert_array_equal(a.image, b.image)
    assert (a.modality, a.slice_thickness_mm, a.slice_gap_mm) == ("flair", 2.5, 0.5)
    assert (b.modality, b.slice_thickness_mm, b.slice_gap_mm) == ("flair", 2.5, 0.5)
    with pytest.raises(TypeError, match="not both"):
        read_scan(path, ReadOptions(), modality="t2")


@pytest.fixture
def readers(monkeypatch):
    """A copy of the reader registry: what a test registers is gone after it."""
    registry.registered_readers()
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    return registry


def test_a_registered_format_is_read_by_read_scan_and_listed(tmp_path, readers):
    seen = {}

    @readers.register_reader("toy", accepts="a toy volume (.toy)", suffixes=(".toy",))
    def _read_toy(path, options):
        seen["options"] = options
        data = np.load(path, allow_pickle=False)
        return scan_from_volume(
            data, np.diag([2.0, 2.0, 4.0, 1.0]), where=str(path), source="toy",
            modality=options.modality or "t2", patient_id=options.patient_id,
            slice_thickness_mm=options.slice_thickness_mm, slice_gap_mm=options.slice_gap_mm,
        )  # fmt: skip

    volume = np.random.default_rng(1).random((9, 8, 4)).astype(np.float32)
    path = tmp_path / "case.toy"
    with open(path, "wb") as fh:
        np.save(fh, volume)
    scan = read_scan(path, modality="t1c")
    assert isinstance(scan, Scan) and scan.modality == "t1c"
    assert scan.slice_step_mm == 4.0 and scan.shape == (4, 8, 9)
    # the id is derived before the reader is called
    assert seen["options"].patient_id == scan.patient_id == derive_patient_id(path)
    # an unsupported file's line lists the registered formats, the new one included
    (tmp_path / "scan.vol").write_bytes(b"x")
    with pytest.raises(InputError, match=r"scan\.vol: unsupported file type.*\.nrrd.*a toy"):
        read_scan(tmp_path / "scan.vol")


def test_registering_a_suffix_twice_or_a_second_fallback_is_refused(readers):
    with pytest.raises(InputError, match="'nifti' already reads"):
        readers.register_reader("nii2", accepts="x", suffixes=(".NII",))(lambda p, o: None)
    with pytest.raises(InputError, match="'dicom' is already the fallback"):
        readers.register_reader("dir2", accepts="x", fallback=True)(lambda p, o: None)


@pytest.fixture
def counted(monkeypatch):
    """Count the reads of the handoff module (the preflight's and the ingest stage's)."""
    calls = []
    real = handoff.read_scan

    def counting(path, options):
        calls.append(os.fspath(path))
        return real(path, options)

    monkeypatch.setattr(handoff, "read_scan", counting)
    yield calls
    handoff.forget_kept()


def test_the_kept_scan_is_handed_over_once_for_the_same_input_and_options(tmp_path, counted):
    path = _nifti(tmp_path / "a.nii.gz")
    options = ReadOptions(modality="t2", patient_id="p1")
    scan = handoff.read_and_keep(path, options)
    # another patient id names the scan differently but reads the same voxels
    same = ReadOptions(modality="t2", patient_id="p2")
    assert handoff.take_kept(path, same, keep=True)[0] is scan
    assert handoff.take_kept(str(path.resolve()), same)[0] is scan
    assert handoff.take_kept(path, same) is None  # taken
    assert len(counted) == 1
    handoff.read_and_keep(path, options)
    assert handoff.take_kept(path, ReadOptions(modality="flair")) is None  # other options
    handoff.read_and_keep(path, options)
    _nifti(path, seed=5)  # rewritten in between: read again
    assert handoff.take_kept(path, options) is None


def test_the_ingest_stage_takes_the_preflight_scan_and_keys_it_as_before(tmp_path, counted):
    from tumor3d.flows.patient import prepare_source
    from tumor3d.tasks.ingest import SPEC

    ingest_task = SPEC.task

    path = _nifti(tmp_path / "a.nii.gz")
    options = ReadOptions(modality="flair", slice_gap_mm=0.0)
    store = ArtifactStore(tmp_path / "store")
    fresh = ingest_task.fn(source=prepare_source(path, options), store_root=str(store.root))
    assert len(counted) == 1  # no preflight: the stage reads
    handoff.read_and_keep(path, options)  # the command line's check
    source = prepare_source(path, options)
    kept = ingest_task.fn(source=source, store_root=str(store.root))
    assert len(counted) == 2  # the stage did not read again
    # the same stored scan and values either way
    assert kept.artifacts["scan"].digest == fresh.artifacts["scan"].digest
    assert kept.values == fresh.values
    # the options reach the stage as one object: the keyword form is the same source
    assert prepare_source(path, modality="FLAIR", slice_gap_mm=0) == source

"""Operating-system errors become one-line errors naming the path (issue 12)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from tumor3d.errors import InputError, os_error_text
from tumor3d.storage import store as store_module
from tumor3d.storage.inputs import input_digest
from tumor3d.storage.readers import read_scan
from tumor3d.storage.refs import StoreError
from tumor3d.storage.store import ArtifactStore


def small_nifti(path):
    data = np.arange(4 * 5 * 3, dtype=np.int16).reshape(4, 5, 3) + 1
    nib.save(nib.Nifti1Image(data, np.diag([1.0, 1.0, 5.0, 1.0])), str(path))
    return path


def test_os_error_text_is_one_lower_case_line():
    assert os_error_text(PermissionError(errno.EACCES, "Permission denied")) == (
        "permission denied (EACCES)"
    )


def test_store_that_is_a_file_is_bad_input(tmp_path):
    f = tmp_path / "store"
    f.write_text("not a folder")
    with pytest.raises(InputError, match=r"store: the artifact store must be a folder"):
        ArtifactStore(f)


def test_store_below_a_file_names_the_path(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match=r"cannot create the artifact store \(.*\)") as info:
        ArtifactStore(tmp_path / "file" / "store")
    assert "\n" not in str(info.value)


def test_full_disk_on_write_is_a_one_line_store_error(tmp_path, monkeypatch):
    store = ArtifactStore(tmp_path / "store")

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(store_module, "atomic_write_bytes", full)
    with pytest.raises(StoreError, match=r"cannot write the artifact \(no space left on device"):
        store.put_bytes(b"payload", kind="json", suffix=".json")


def test_unreadable_input_is_one_line_naming_the_file(tmp_path, monkeypatch):
    f = small_nifti(tmp_path / "scan.nii.gz")

    def denied(self, *args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(self))

    monkeypatch.setattr(Path, "iterdir", denied)  # a DICOM folder that cannot be listed
    folder = tmp_path / "series"
    folder.mkdir()
    with pytest.raises(InputError, match=r"series: cannot read the input \(permission denied"):
        read_scan(folder)

    real_open = open

    def open_denied(file, *args, **kwargs):
        if os.fspath(file) == str(f):
            raise PermissionError(errno.EACCES, "Permission denied", str(f))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr("builtins.open", open_denied)
    with pytest.raises(InputError, match=r"scan\.nii\.gz: cannot read the input \(permission"):
        input_digest(f)


def test_a_writable_folder_is_made_and_left_as_it_was(tmp_path):
    from tumor3d.storage.atomic import check_writable_dir

    check_writable_dir(tmp_path / "a" / "b")
    assert (tmp_path / "a" / "b").is_dir() and not list((tmp_path / "a" / "b").iterdir())


def test_an_unwritable_folder_is_named_not_the_probe(tmp_path, monkeypatch):
    """Made (it exists) but no file can be created in it, as an immutable folder: the
    error names the folder, not the probe's random name."""
    import tempfile

    from tumor3d.storage.atomic import check_writable_dir

    def denied(*args, dir=None, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", os.path.join(dir, ".x123"))

    monkeypatch.setattr(tempfile, "mkstemp", denied)
    with pytest.raises(PermissionError) as info:
        check_writable_dir(tmp_path)
    assert info.value.filename == str(tmp_path)


def test_a_check_before_the_input_is_validated_makes_no_folder(tmp_path):
    """create=False (the commands' check before a row may be refused): an absent folder is
    judged by its nearest existing parent and not made; under a file, the file is named."""
    from tumor3d.storage.atomic import check_writable_dir

    check_writable_dir(tmp_path / "a" / "b", create=False)
    assert not (tmp_path / "a").exists() and not list(tmp_path.iterdir())
    (tmp_path / "f").write_text("x")
    with pytest.raises(NotADirectoryError) as info:
        check_writable_dir(tmp_path / "f" / "out", create=False)
    assert info.value.filename == str(tmp_path / "f")

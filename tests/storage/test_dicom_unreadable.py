"""Corrupt files in a DICOM series folder are named, never dropped silently (issue 12)."""

from __future__ import annotations

import numpy as np
import pytest
from dicom_factory import write_series

from tumor3d.errors import InputError
from tumor3d.storage.readers import read_dicom_series, read_scan
from tumor3d.storage.store import ArtifactStore


def corrupt(path, seed=0, size=3000):
    path.write_bytes(np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes())


@pytest.mark.parametrize("which", [0, 3, -1], ids=["bottom", "middle", "top"])
def test_a_corrupt_slice_stops_the_read_and_is_named(tmp_path, which):
    folder = tmp_path / "case"
    s = write_series(folder, n_slices=7)
    victim = s.files[which]
    corrupt(victim)
    with pytest.raises(InputError) as info:
        read_scan(folder)
    message = str(info.value)
    assert "1 file(s) could not be read as DICOM" in message
    assert victim.name in message
    assert "--skip-unreadable-dicom" in message
    assert "\n" not in message


def test_every_unreadable_file_is_named(tmp_path):
    folder = tmp_path / "case"
    write_series(folder, n_slices=5)
    corrupt(folder / "junk1.bin", seed=1)
    (folder / "empty").write_bytes(b"")
    (folder / "truncated.dcm").write_bytes(b"\0" * 128 + b"DICM" + b"\x02\x00")
    with pytest.raises(InputError, match="3 file.s. could not be read") as info:
        read_scan(folder)
    for name in ("junk1.bin", "empty", "truncated.dcm"):
        assert name in str(info.value)


def test_skip_unreadable_skips_and_lists_the_files(tmp_path):
    folder = tmp_path / "case"
    s = write_series(folder, n_slices=7)
    corrupt(s.files[-1])  # the top slice: the rest is still a uniform series
    scan = read_dicom_series(folder, skip_unreadable=True)
    assert scan.n_slices == 6
    assert scan.skipped_files == (s.files[-1].name,)
    assert "1 unreadable file(s) skipped" in scan.source
    np.testing.assert_array_equal(scan.image, s.raw[:-1].astype(np.float32) * 2 - 10)
    # read_scan forwards the option, and the stored scan keeps the list
    scan2 = read_scan(folder, skip_unreadable=True)
    assert scan2.skipped_files == scan.skipped_files
    store = ArtifactStore(tmp_path / "store")
    back = store.get_scan(store.put_scan(scan2), patient_id="p1")
    assert back.skipped_files == scan.skipped_files


def test_notes_and_previews_beside_the_series_are_not_unreadable(tmp_path):
    folder = tmp_path / "case"
    write_series(folder, n_slices=4)
    (folder / "README").write_text("acquired on scanner 3\n")
    (folder / "notes.txt").write_bytes(b"\x89binary-looking but a .txt")
    (folder / ".DS_Store").write_bytes(b"\0\1\2")
    corrupt(folder / "preview.png")
    scan = read_scan(folder)
    assert scan.n_slices == 4 and scan.skipped_files == ()
    assert "skipped" not in scan.source


def test_truncated_pixel_data_is_named_and_can_be_skipped(tmp_path):
    folder = tmp_path / "case"
    s = write_series(folder, n_slices=6)
    victim = s.files[0]  # the bottom slice: the others remain a uniform series
    victim.write_bytes(victim.read_bytes()[:-100])
    with pytest.raises(InputError, match=r"1 file.s. could not be read") as info:
        read_scan(folder)
    assert f"{victim.name}: cannot decode the pixel data" in str(info.value)
    scan = read_scan(folder, skip_unreadable=True)
    assert scan.skipped_files == (victim.name,) and scan.n_slices == 5
    np.testing.assert_array_equal(scan.image, s.raw[1:].astype(np.float32) * 2 - 10)

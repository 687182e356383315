"""Every file an input consists of counts as input; a header never reaches outside its folder.

Issue 29: a ``.mhd`` whose ``ElementDataFile`` lay in the output folder had
its voxel data deleted by publishing; a cohort row's brain mask kept in another
row's published folder was overwritten; ``ElementDataFile = ../../../../etc/passwd``
was read as image data. Each is now refused in one line, before any work.
"""

from __future__ import annotations

import hashlib

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from typer.testing import CliRunner

from tumor3d.errors import InputError
from tumor3d.flows.cli import EXIT_INPUT, app
from tumor3d.flows.cohort import run_cohort
from tumor3d.storage.inputs import detached_data_files, input_digest, input_files
from tumor3d.storage.publish import check_output_not_input, check_outputs_not_inputs
from tumor3d.storage.readers import read_scan

runner = CliRunner()


def _volume(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.integers(10, 50, size=(6, 12, 12)) + 100).astype(np.int16)  # (k, j, i)


def _mhd(header, data_name: str, seed: int = 0):
    """A MetaImage header whose ElementDataFile is ``data_name`` (written where it points)."""
    header.parent.mkdir(parents=True, exist_ok=True)
    sitk.WriteImage(sitk.GetImageFromArray(_volume(seed)), str(header))
    written = header.with_suffix(".raw")
    text = header.read_text().replace(f"ElementDataFile = {written.name}", "")
    header.write_text(text.rstrip("\n") + f"\nElementDataFile = {data_name}\n")
    target = (header.parent / data_name).resolve()
    if not str(data_name).startswith("/") and ".." not in data_name:
        target.parent.mkdir(parents=True, exist_ok=True)
        written.replace(target)
    return header, target


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_header_naming_a_data_file_outside_its_folder_is_refused_in_one_line(tmp_path):
    header = tmp_path / "in" / "case.mhd"
    header.parent.mkdir()
    sitk.WriteImage(sitk.GetImageFromArray(_volume()), str(header))
    text = header.read_text().replace("ElementDataFile = case.raw", "")
    header.write_text(text + "ElementDataFile = ../../../../etc/passwd\n")
    for call in (read_scan, input_digest, detached_data_files, input_files):
        with pytest.raises(InputError, match="outside the header's folder") as exc:
            call(header)
        assert "\n" not in str(exc.value) and "case.mhd" in str(exc.value)
    res = runner.invoke(app, ["run", str(header), "--out", str(tmp_path / "out")])
    assert res.exit_code == EXIT_INPUT
    assert "outside the header's folder" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "out").exists()
    # absolute paths too; a data file below the header's folder is fine
    header.write_text(text + "ElementDataFile = /etc/passwd\n")
    with pytest.raises(InputError, match="outside the header's folder"):
        read_scan(header)


def test_a_data_file_below_the_headers_folder_is_read(tmp_path):
    header, data = _mhd(tmp_path / "in" / "case.mhd", "voxels/case.raw")
    assert detached_data_files(header) == [data]
    scan = read_scan(header)
    assert scan.image.shape[0] == 6 and float(scan.image.max()) >= 100


def test_a_header_whose_data_file_lies_in_the_output_folder_is_refused(tmp_path):
    """`run D/case.mhd --out D/OUT --patient-id pat` with the voxels in D/OUT/pat/."""
    header, data = _mhd(tmp_path / "D" / "case.mhd", "OUT/pat/case.raw")
    before = _sha(data)
    assert data in input_files(header)
    with pytest.raises(InputError, match="would delete the input"):
        check_output_not_input(tmp_path / "D" / "OUT" / "pat", [header])
    res = runner.invoke(app, ["run", str(header), "--out", str(tmp_path / "D" / "OUT"),
                              "--patient-id", "pat"])  # fmt: skip
    assert res.exit_code == EXIT_INPUT, res.output
    assert "would delete the input" in res.output and "case.raw" in res.output
    assert "Traceback" not in res.output
    assert _sha(data) == before
    assert sorted(p.name for p in (tmp_path / "D" / "OUT" / "pat").iterdir()) == ["case.raw"]


def test_a_cohort_row_whose_mask_lies_in_another_rows_folder_is_refused(tmp_path):
    affine = np.diag([1.0, 1.0, 5.0, 1.0])
    rows = []
    for pid in ("p1", "p2"):
        img = tmp_path / "in" / f"{pid}.nii.gz"
        img.parent.mkdir(exist_ok=True)
        nib.save(nib.Nifti1Image(np.random.default_rng(1).random((12, 12, 6)) + 1, affine), img)
        rows.append(img)
    out = tmp_path / "out"
    mask = out / "p2" / "brain_mask_edited.nii.gz"  # a user-edited copy of p2's result
    mask.parent.mkdir(parents=True)
    (mask.parent / "provenance.json").write_text('{"versions": {"tumor3d": "0"}}')  # a result
    nib.save(nib.Nifti1Image(np.ones((12, 12, 6), np.uint8), affine), mask)
    before = _sha(mask)
    with pytest.raises(InputError, match="would delete the input") as exc:
        check_outputs_not_inputs([out / "p1", out / "p2"], [rows[0], mask, rows[1]])
    assert "brain_mask_edited" in str(exc.value)
    manifest = tmp_path / "m.csv"
    manifest.write_text(
        f"patient_id,image,modality,brain_mask\np1,{rows[0]},t2,{mask}\np2,{rows[1]},t2,\n"
    )
    with pytest.raises(InputError, match="would delete the input") as exc:
        run_cohort(manifest, out, workers=1)  # refused before any flow starts
    assert "\n" not in str(exc.value) and "brain_mask_edited" in str(exc.value)
    assert _sha(mask) == before
    assert sorted(p.name for p in out.iterdir()) == ["p2"]  # nothing started

"""The command line: help on every command, and bad input rejected cleanly.

Bad input is caught before Prefect starts: one line naming the file and the
problem on stderr, exit code 2, nothing under the output folder.
"""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
from typer.testing import CliRunner

from flows.cli import app

runner = CliRunner()


@pytest.mark.parametrize("command", [[], ["run"], ["demo"], ["phantom"]])
def test_every_command_has_help(command):
    result = runner.invoke(app, [*command, "--help"])
    assert result.exit_code == 0
    assert "Usage" in result.output


def _nifti(path, data):
    nib.save(nib.Nifti1Image(np.asarray(data, dtype=np.float32), np.eye(4)), path)
    return path


def _bad_inputs(tmp):
    """(name, input path, extra args, expected message) for each bad-input case."""
    rng = np.random.default_rng(0)
    not_image = tmp / "notes.nii.gz"
    not_image.write_text("this is not an image")
    nan = rng.random((12, 12, 4))
    nan[3, 3, 1] = np.nan
    empty_dicom = tmp / "dicom_empty"
    empty_dicom.mkdir()
    (empty_dicom / "README.txt").write_text("no images here")
    good = _nifti(tmp / "good.nii.gz", rng.random((12, 12, 4)) + 1)
    return {
        "missing": (tmp / "absent.nii.gz", [], "no such file"),
        "not-an-image": (not_image, [], "not a readable NIfTI"),
        "single-2d": (_nifti(tmp / "flat.nii.gz", rng.random((12, 12))), [], "single 2-D image"),
        "all-zero": (_nifti(tmp / "zeros.nii.gz", np.zeros((12, 12, 4))), [], "all-zero"),
        "nan": (_nifti(tmp / "nan.nii.gz", nan), [], "not finite"),
        "no-dicom": (empty_dicom, [], "no DICOM images"),
        "unsafe-id": (good, ["--patient-id", "../escape"], "unsafe patient id"),
    }


CASES = ["missing", "not-an-image", "single-2d", "all-zero", "nan", "no-dicom", "unsafe-id"]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_gives_clear_error_and_no_outputs(tmp_path, case):
    path, extra, message = _bad_inputs(tmp_path)[case]
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(path), "--out", str(out), *extra])
    assert result.exit_code == 2, result.output
    assert message in result.output
    if case != "unsafe-id":
        assert path.name in result.output  # the message names the file
    assert "Traceback" not in result.output
    assert not out.exists() or not any(out.iterdir())


def test_invalid_config_names_the_key(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("simplify:\n  reduction_percent: 150\n  colour: red\n")
    good = _nifti(tmp_path / "good.nii.gz", np.random.default_rng(1).random((12, 12, 4)) + 1)
    result = runner.invoke(
        app, ["run", str(good), "--out", str(tmp_path / "o"), "--config", str(cfg)]
    )
    assert result.exit_code == 2
    assert "simplify.reduction_percent" in result.output
    assert "simplify.colour" in result.output
    assert "bad.yaml" in result.output


def test_phantom_command_writes_patients_truth_and_a_readable_manifest(tmp_path):
    import json

    from storage.manifest import read_manifest
    from storage.readers import read_scan

    out = tmp_path / "cohort"
    result = runner.invoke(app, ["phantom", "--out", str(out), "--n", "2", "--normal", "1"])
    assert result.exit_code == 0, result.output
    rows = read_manifest(out / "manifest.csv")
    assert [r.patient_id for r in rows] == ["phantom000", "phantom001n"]
    volumes = []
    for row in rows:
        scan = read_scan(row.image, modality=row.modality)
        assert (scan.slice_thickness_mm, scan.slice_gap_mm) == (2.0, 3.0)  # from the sidecar
        assert row.reference is not None and row.reference.is_file()
        truth = json.loads((row.image.parent / f"{row.patient_id}_truth.json").read_text())
        volumes.append(truth["true_volume_mm3"])
    assert volumes[0] > 0 and volumes[1] == 0


def test_phantom_command_rejects_more_normal_than_total(tmp_path):
    result = runner.invoke(app, ["phantom", "--out", str(tmp_path), "--n", "1", "--normal", "2"])
    assert result.exit_code == 2
    assert "--normal" in result.output


def test_run_refuses_an_output_folder_that_holds_the_input(tmp_path):
    """Issue 12: `--out O --patient-id pat1` with the input in O/pat1 must not delete it."""
    rng = np.random.default_rng(1)
    (tmp_path / "O" / "pat1").mkdir(parents=True)
    image = _nifti(tmp_path / "O" / "pat1" / "t2.nii.gz", rng.random((12, 12, 4)) + 1)
    result = runner.invoke(app, ["run", str(image), "--out", str(tmp_path / "O"),
                                 "--patient-id", "pat1"])  # fmt: skip
    assert result.exit_code == 2
    assert "would delete the input" in result.output
    assert image.is_file()


def test_run_refuses_a_dicom_folder_replaced_by_its_own_output(tmp_path):
    series = tmp_path / "D"
    series.mkdir()
    (series / "slice1.dcm").write_bytes(b"not really dicom")
    # the patient id defaults to the folder name: OUT/D would be the input folder itself
    result = runner.invoke(app, ["run", str(series), "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "would delete the input" in result.output
    assert (series / "slice1.dcm").is_file()


def test_user_strings_with_brackets_are_not_read_as_markup(tmp_path):
    missing = tmp_path / "scan[/]x[bold]2.nii.gz"
    result = runner.invoke(app, ["run", str(missing), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert "scan[/]x[bold]2.nii.gz" in result.output
    assert "MarkupError" not in result.output

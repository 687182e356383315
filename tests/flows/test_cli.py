"""The command line: help on every command, and bad input rejected cleanly.

Bad input is caught before Prefect starts: one line naming the file and the
problem on stderr, exit code 2, nothing under the output folder.
"""

from __future__ import annotations

import json
import sys

import nibabel as nib
import numpy as np
import pytest
from typer.testing import CliRunner

from tumor3d.errors import InputError
from tumor3d.flows.cli import app

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

    from tumor3d.storage.manifest import read_manifest
    from tumor3d.storage.readers import read_scan

    out = tmp_path / "cohort"
    result = runner.invoke(app, ["phantom", "--out", str(out), "--n", "2", "--normal", "1"])
    assert result.exit_code == 0, result.output
    rows = read_manifest(out / "manifest.csv")
    assert [r.patient_id for r in rows] == ["phantom000", "phantom001n"]
    volumes = []
    for row in rows:
        scan = read_scan(row.image, modality=row.modality)
        assert (scan.slice_thickness_mm, scan.slice_gap_mm) == (2.0, 3.0)  # from the sidecar
        truth = json.loads((row.image.parent / f"{row.patient_id}_truth.json").read_text())
        volumes.append(truth["true_volume_mm3"])
    assert volumes[0] > 0 and volumes[1] == 0
    # the evaluation's reference kinds (issue 33: evaluate on this manifest scored no row)
    assert rows[0].reference is not None and rows[0].reference.is_file()
    assert rows[0].reference_kind == "truth"
    assert rows[1].reference is None and rows[1].reference_kind == "tumor_free"
    assert (out / "phantom001n" / "phantom001n_truth_fine.nii.gz").is_file()


def test_phantom_command_rejects_more_normal_than_total(tmp_path):
    result = runner.invoke(app, ["phantom", "--out", str(tmp_path), "--n", "1", "--normal", "2"])
    assert result.exit_code == 2
    assert "--normal" in result.output


@pytest.mark.parametrize(("option", "named"), [("--preset", "preset"), ("--modality", "modality")])
def test_a_bad_phantom_option_is_its_one_line_alone(tmp_path, option, named):
    """A user audit saw the progress bar ('generating phantoms 0/2') before the error."""
    out = tmp_path / "ph"
    result = runner.invoke(app, ["phantom", "--out", str(out), "--n", "2", option, "foo"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [result.output.strip()], result.output
    assert result.output.startswith("error: ") and named in result.output
    assert not out.exists()


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


# ---------------------------------------------------------------- issue 12 remainder (harden)


def test_max_voxels_flag_refuses_a_large_input_before_any_work(tmp_path):
    good = _nifti(tmp_path / "big.nii.gz", np.random.default_rng(2).random((12, 12, 4)) + 1)
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(good), "--out", str(out), "--max-voxels", "100"])
    assert result.exit_code == 2, result.output
    # the reader's own message: declared size, the limit given, the option
    assert "12 x 12 x 4 = 576 voxels" in result.output and "100" in result.output
    assert "--max-voxels" in result.output and "big.nii.gz" in result.output
    assert "Traceback" not in result.output
    assert not out.exists() or not any(out.iterdir())


def test_max_voxels_appears_in_the_help_of_run_and_cohort():
    for command in ("run", "cohort"):
        result = runner.invoke(app, [command, "--help"])
        assert "--max-voxels" in result.output


@pytest.mark.parametrize("command", ["run", "cohort", "phantom", "demo"])
def test_an_output_folder_that_is_a_file_is_bad_input(tmp_path, command):
    out = tmp_path / "out.txt"
    out.write_text("a file, not a folder")
    good = _nifti(tmp_path / "good.nii.gz", np.random.default_rng(3).random((12, 12, 4)) + 1)
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"patient_id,image,modality\np1,{good},t2\n")
    args = {
        "run": ["run", str(good)],
        "cohort": ["cohort", str(manifest)],
        "phantom": ["phantom", "--n", "1"],
        "demo": ["demo"],
    }[command]
    result = runner.invoke(app, [*args, "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert "out.txt: the output folder (--out) is a file" in result.output
    assert "Traceback" not in result.output
    assert out.read_text() == "a file, not a folder"


def _raiser(exc):
    def run(**kwargs):
        raise exc

    return run


@pytest.mark.parametrize(
    ("exc", "expected"),
    [
        (
            "store",
            "/s/objects/ab/x.nii.gz: cannot write the artifact (no space left on device (ENOSPC))",
        ),
        ("oserror", "/o/p1/tumor.ply: read-only file system (EROFS)"),
        ("server", "the Prefect server did not answer"),
    ],
)
def test_environment_errors_are_one_line_with_exit_code_3(tmp_path, monkeypatch, exc, expected):
    import errno

    import tumor3d.flows.cli as cli
    from tumor3d.flows.server import ServerError
    from tumor3d.storage.store import StoreError

    error = {
        "store": StoreError(
            "/s/objects/ab/x.nii.gz: cannot write the artifact (no space left on device (ENOSPC))"
        ),
        "oserror": OSError(errno.EROFS, "Read-only file system", "/o/p1/tumor.ply"),
        "server": ServerError("the Prefect server did not answer http://x/api/health in 9 s"),
    }[exc]
    monkeypatch.setattr(cli, "_run_with_progress", _raiser(error))
    good = _nifti(tmp_path / "good.nii.gz", np.random.default_rng(4).random((12, 12, 4)) + 1)
    result = runner.invoke(app, ["run", str(good), "--out", str(tmp_path / "out")])
    assert result.exit_code == cli.EXIT_ENVIRONMENT == 3, result.output
    assert expected in result.output
    assert "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_exit_codes_are_documented_in_the_cli_docstring_and_readme():
    from pathlib import Path

    import tumor3d.flows.cli as cli

    assert "3 -- environment error" in cli.__doc__
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert "| 3 |" in readme and "environment" in readme


def test_console_entry_keeps_exit_codes_and_flushes_output(tmp_path):
    """main() ends with os._exit after the exit handlers: codes and piped output survive."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root), "TUMOR3D_HOME": str(tmp_path / "home")}
    env.pop("COLUMNS", None)

    def cli(*args):
        return subprocess.run(
            [sys.executable, "-m", "tumor3d.flows.cli", *args],
            env=env, capture_output=True, text=True, timeout=300, cwd=str(root),
        )  # fmt: skip

    absent = tmp_path / ("a folder with a long name " * 4) / "absent.nii.gz"
    missing = cli("run", str(absent), "--out", str(tmp_path / "o"))
    assert missing.returncode == 2 and "absent.nii.gz: no such file" in missing.stderr
    # piped, an error with a long path stays one line
    (line,) = [line for line in missing.stderr.splitlines() if line.strip()]
    assert str(absent) in line and len(line) > 120
    status = cli("server", "status")
    assert status.returncode == 1 and "no tumor3d Prefect server running" in status.stdout
    helped = cli("--help")
    assert helped.returncode == 0 and "Usage" in helped.stdout


def test_commands_run_without_flow_heartbeats_unless_asked(monkeypatch):
    """The heartbeat thread's join cost ~0.9 s per command; the user's setting wins."""
    from prefect.settings import get_current_settings

    import tumor3d.flows.cli as cli

    monkeypatch.delenv("PREFECT_FLOWS_HEARTBEAT_FREQUENCY", raising=False)
    with cli._no_heartbeats():
        assert get_current_settings().flows.heartbeat_frequency is None
    monkeypatch.setenv("PREFECT_FLOWS_HEARTBEAT_FREQUENCY", "60")
    before = get_current_settings().flows.heartbeat_frequency
    with cli._no_heartbeats():
        assert get_current_settings().flows.heartbeat_frequency == before


# ---------------------------------------------------------------- --brain-mask (issue 7)


def _head_and_masks(tmp):
    """A 12x12x4 image (noisy air, a bright head block) and one mask file per bad case."""
    rng = np.random.default_rng(4)
    data = rng.random((12, 12, 4)) * 10
    data[3:9, 3:9, :] += 100
    aff = np.diag([0.9, 0.9, 5.0, 1.0])
    nib.save(nib.Nifti1Image(data.astype(np.float32), aff), tmp / "head.nii.gz")
    brain = np.zeros((12, 12, 4), np.float32)
    brain[4:8, 4:8, :] = 1

    def save(name, array, affine=aff):
        nib.save(nib.Nifti1Image(np.asarray(array, np.float32), affine), tmp / name)
        return tmp / name

    shifted = aff.copy()
    shifted[0, 3] = 4.5  # five voxels along x
    nan = brain.copy()
    nan[5, 5, 2] = np.nan
    air = np.zeros_like(brain)
    air[0:2, 0:2, :] = 1
    return tmp / "head.nii.gz", {
        "shape": (save("m_shape.nii.gz", brain[:, :, :3]),
                  "shape (12, 12, 3) differs from the image's (12, 12, 4)"),
        "affine": (save("m_affine.nii.gz", brain, shifted),
                   "affine [0.9 0 0 4.5; 0 0.9 0 0; 0 0 5 0] differs from the image's "
                   "[0.9 0 0 0; 0 0.9 0 0; 0 0 5 0] (voxel centres up to 5 voxels apart"),
        "empty": (save("m_empty.nii.gz", np.zeros_like(brain)), "empty: no voxel is above 0.5"),
        "nan": (save("m_nan.nii.gz", nan), "1 of 576 voxel values are not finite (1 NaN"),
        "air": (save("m_air.nii.gz", air), "no overlap with the image"),
        "missing": (tmp / "m_missing.nii.gz", "no such file"),
        "4-D": (save("m_4d.nii.gz", np.stack([brain, brain], axis=-1)),
                "a 4-D image with 2 volumes (shape (12, 12, 4, 2)): give a single 3-D volume"),
    }  # fmt: skip


@pytest.mark.parametrize("case", ["shape", "affine", "empty", "nan", "air", "missing", "4-D"])
def test_bad_brain_mask_is_one_line_naming_it_with_exit_2_before_any_work(tmp_path, case):
    image, masks = _head_and_masks(tmp_path)
    mask, message = masks[case]
    out = tmp_path / "out"
    result = runner.invoke(
        app, ["run", str(image), "--out", str(out), "--brain-mask", str(mask)]
    )  # fmt: skip
    assert result.exit_code == 2, result.output
    line = f"error: {mask}: brain mask: "
    assert line in result.output, result.output
    assert message in result.output
    assert len(result.output.strip().splitlines()) == 1, result.output
    assert "Traceback" not in result.output and "starting Prefect" not in result.output
    assert not out.exists() or not any(out.iterdir())


def test_brain_mask_inside_the_output_folder_is_refused(tmp_path):
    image, _ = _head_and_masks(tmp_path)
    inside = tmp_path / "out" / "head"
    inside.mkdir(parents=True)
    mask = inside / "brain.nii.gz"
    brain = np.zeros((12, 12, 4), np.float32)
    brain[4:8, 4:8, :] = 1
    nib.save(nib.Nifti1Image(brain, np.diag([0.9, 0.9, 5.0, 1.0])), mask)
    result = runner.invoke(
        app, ["run", str(image), "--out", str(tmp_path / "out"), "--brain-mask", str(mask)]
    )  # fmt: skip
    assert result.exit_code == 2
    assert "would delete the input" in result.output and mask.is_file()


def test_brain_mask_option_is_in_the_help_of_run():
    assert "--brain-mask" in runner.invoke(app, ["run", "--help"]).output


def test_run_refuses_to_replace_another_inputs_results_under_a_derived_id(tmp_path):
    """pat3/flair.nii.gz then pat4/flair.nii.gz into one --out: both derive the id 'flair'."""
    from tumor3d.storage.inputs import input_digest

    rng = np.random.default_rng(2)
    (tmp_path / "pat3").mkdir()
    (tmp_path / "pat4").mkdir()
    first = _nifti(tmp_path / "pat3" / "flair.nii.gz", rng.random((12, 12, 4)) + 1)
    second = _nifti(tmp_path / "pat4" / "flair.nii.gz", rng.random((12, 12, 4)) + 1)
    done = tmp_path / "out" / "flair"  # what the run of the first left
    done.mkdir(parents=True)
    from tumor3d.storage.inputs import input_location

    record = json.dumps({
        "versions": {"tumor3d": "0.1.0"},
        "input": {"name": "flair.nii.gz", "digest_sha256": input_digest(first),
                  "location_sha256": input_location(first)},
    })  # fmt: skip
    (done / "provenance.json").write_text(record)
    result = runner.invoke(app, ["run", str(second), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    assert f"error: {done}: this folder holds the results of another input" in result.output
    assert "--patient-id pat4_flair" in result.output
    assert len(result.output.strip().splitlines()) == 1 and "starting Prefect" not in result.output
    assert (done / "provenance.json").read_text() == record
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["flair"]


def test_run_refuses_to_replace_a_folder_of_the_users_own_files(tmp_path):
    rng = np.random.default_rng(3)
    image = _nifti(tmp_path / "scan.nii.gz", rng.random((12, 12, 4)) + 1)
    own = tmp_path / "project" / "data"
    own.mkdir(parents=True)
    (own / "results.xlsx").write_bytes(b"mine")
    result = runner.invoke(app, ["run", str(image), "--out", str(tmp_path / "project"),
                                 "--patient-id", "data"])  # fmt: skip
    assert result.exit_code == 2, result.output
    assert f"error: {own}: this folder exists and is not a tumor3d result" in result.output
    assert (own / "results.xlsx").read_bytes() == b"mine"
    assert sorted(p.name for p in own.iterdir()) == ["results.xlsx"]


def test_the_modality_is_case_insensitive_for_run_as_for_a_manifest(tmp_path):
    """An audit: `run --modality FLAIR` was refused while a manifest's FLAIR was accepted."""
    from tumor3d.flows.patient import prepare_source

    image = _nifti(tmp_path / "scan.nii.gz", np.random.default_rng(4).random((12, 12, 4)) + 1)
    assert prepare_source(image, modality="FLAIR").modality == "flair"
    assert prepare_source(image, modality=" T1c ").modality == "t1c"
    assert not prepare_source(image, modality="FLAIR").modality_default
    defaulted = prepare_source(image)
    assert defaulted.modality == "t2" and defaulted.modality_default
    with pytest.raises(InputError, match="unknown modality 't1'"):
        prepare_source(image, modality="t1")


def test_version_option_prints_the_installed_version():
    from importlib.metadata import version

    from tumor3d.flows.cli import app

    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"tumor3d {version('tumor3d')}"


def test_exit_code_of_a_result_to_check_is_documented():
    from pathlib import Path

    import tumor3d.flows.cli as cli
    from tumor3d.flows.cohort_result import exit_code_of
    from tumor3d.flows.exit_codes import EXIT_CHECK

    assert cli.EXIT_CHECK == EXIT_CHECK == 4 and "* 4 -- " in cli.__doc__
    assert exit_code_of(["ok", "check"]) == 4 and exit_code_of(["check", "failed"]) == 1
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    row = "| 4 | `run`/`demo`/`cohort`: every result published, but some has status `check`"
    assert row in readme


@pytest.fixture
def run_flow_given(monkeypatch):
    """``run`` with its flow replaced: the keywords the flow was given (the flow itself is
    tested elsewhere), an ``ok`` result, no summary."""
    import types

    import tumor3d.flows.cli as cli

    seen: dict = {}
    result_stub = types.SimpleNamespace(metrics={"status": "ok"})
    monkeypatch.setattr(cli, "_run_with_progress", lambda **kw: (seen.update(kw), result_stub)[1])
    monkeypatch.setattr(cli, "print_summary", lambda result: None)
    return seen


def test_run_says_the_modality_it_uses_and_when_it_is_the_default(tmp_path, run_flow_given):
    seen = run_flow_given
    good = _nifti(tmp_path / "good.nii.gz", np.random.default_rng(4).random((12, 12, 4)) + 1)
    assumed = runner.invoke(app, ["run", str(good), "--out", str(tmp_path / "o")])
    assert assumed.exit_code == 0, assumed.output
    # the flow is given none and takes the same t2 itself, marked as a default: its notes
    # (report, metrics) say so, not only this console (it was given "t2", as if chosen)
    from tumor3d.flows.patient import prepare_source

    assert seen["modality"] is None
    source = prepare_source(good, modality=seen["modality"])
    assert source.modality == "t2" and source.modality_default
    said = " ".join(assumed.output.split())
    assert "modality: t2 (the default: --modality was not given" in said
    given = runner.invoke(
        app, ["run", str(good), "--out", str(tmp_path / "o"), "--modality", "flair"]
    )
    assert seen["modality"] == "flair"
    assert "modality: flair" in given.output and "default" not in given.output


def test_run_says_the_patient_id_it_made_when_it_is_not_the_files_name(tmp_path, run_flow_given):
    data = np.random.default_rng(4).random((12, 12, 4)) + 1
    odd = _nifti(tmp_path / "Pat 01 é.nii.gz", data)
    res = runner.invoke(app, ["run", str(odd), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    said = " ".join(res.output.split())
    assert "patient id: Pat_01_e (made folder-safe from the name 'Pat 01 é'" in said
    plain = _nifti(tmp_path / "pat02.nii.gz", data)
    for args in (["run", str(plain)], ["run", str(odd), "--patient-id", "p1"]):
        res = runner.invoke(app, [*args, "--out", str(tmp_path / "o2")])
        assert res.exit_code == 0 and "patient id:" not in res.output, res.output


def test_every_commands_help_names_each_option_in_full_at_80_columns():
    """--help in an 80-column terminal: no option name or help text cut off with "…"
    (Rich's help tables cut --slice-thickness-mm, --skip-unreadable-dicom and the
    s3:// examples); every option of every command named in full."""
    import typer

    def commands(group, path):  # typer vendors click: walk its groups by their commands
        for name, command in group.commands.items():
            yield [*path, name], command
            if hasattr(command, "commands"):
                yield from commands(command, [*path, name])

    listed = list(commands(typer.main.get_command(app), []))
    assert ["run"] in [path for path, _ in listed] and len(listed) > 8
    for path, command in listed:
        res = runner.invoke(app, [*path, "--help"], terminal_width=80)
        assert res.exit_code == 0, (path, res.output)
        assert "…" not in res.output, (path, res.output)
        assert max(len(line) for line in res.output.splitlines()) <= 80, (path, res.output)
        for param in command.params:
            if param.param_type_name == "option":
                for opt in param.opts:
                    assert opt in res.output, (path, opt)


def test_an_output_folder_that_cannot_be_written_is_named_before_any_work(tmp_path, monkeypatch):
    """With --store elsewhere nothing wrote in --out before publishing: an immutable folder
    failed after every stage (chattr +i; root ignores a read-only mode, so the refusal is
    simulated where the probe writes)."""
    import errno
    import tempfile

    import tumor3d.flows.cli as cli

    ran = []
    monkeypatch.setattr(cli, "_run_with_progress", lambda **kw: ran.append(kw))
    good = _nifti(tmp_path / "good.nii.gz", np.random.default_rng(4).random((12, 12, 4)) + 1)
    out = tmp_path / "frozen"
    out.mkdir()
    real = tempfile.mkstemp

    def refused(*args, dir=None, **kwargs):
        if dir is not None and str(dir) == str(out):
            raise PermissionError(errno.EPERM, "Operation not permitted", str(out / ".probe"))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    args = ["run", str(good), "--out", str(out), "--store", str(tmp_path / "store")]
    res = runner.invoke(app, args)
    assert res.exit_code == 3 and not ran, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert lines[-1] == f"error: {out}: operation not permitted (EPERM)", res.output
    assert list(out.iterdir()) == []
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"patient_id,image,modality\np1,{good},t2\n")
    res = runner.invoke(app, ["cohort", str(manifest), *args[2:]])  # cohort: the same
    assert res.exit_code == 3 and not ran, res.output
    assert f"error: {out}: operation not permitted (EPERM)" in res.output
    monkeypatch.setattr(tempfile, "mkstemp", real)
    res = runner.invoke(app, args)  # writable: on to the run, no probe left behind
    assert ran and list(out.iterdir()) == [], res.output


def test_the_cohort_table_fits_80_columns_with_every_id_in_full(monkeypatch):
    """A piped or 80-column console cut every id to "phanto…", so an ok and a check patient
    could not be told apart; the volume methods are named, in mL."""
    import io
    import types

    from rich.console import Console

    import tumor3d.flows.cli.output as output
    from tumor3d.storage.derivatives import VOLUME_LABELS

    def patient(pid, status):
        metrics = {key: 12345.0 for key in VOLUME_LABELS} | {"notes": "", "review_reasons": ""}
        stages = [types.SimpleNamespace(cached=True)] * 10
        return types.SimpleNamespace(patient_id=pid, status=status, metrics=metrics, stages=stages)

    ids = ["phantom000", "phantom001n", "a-rather-long-patient-id-of-a-site-0042"]
    result = types.SimpleNamespace(
        patients=[patient(i, s) for i, s in zip(ids, ["ok", "check", "ok"], strict=True)],
        failed=[], removed=[], earlier=[], wall_seconds=1.0, out_dir="out",
    )  # fmt: skip
    buf = io.StringIO()
    monkeypatch.setattr(output, "console", Console(file=buf, width=80))
    output.print_cohort_summary(result)
    text = buf.getvalue()
    assert "…" not in text and max(len(line.rstrip()) for line in text.splitlines()) <= 80
    rows = [line.split() for line in text.splitlines()]
    for pid, status in zip(ids[:2], ["ok", "check"], strict=True):
        assert [pid, status, "12.345"] in [row[:3] for row in rows], text
    assert ids[2] in "".join(row[0] for row in rows if row), text  # folded, not cut
    flat = " ".join(text.split())
    assert "volumes in mL by " + ", ".join(VOLUME_LABELS.values()) in flat


def test_a_piped_console_keeps_ids_and_lines_whole(monkeypatch):
    """A user audit piped a cohort to a file: Rich wrapped at 80 columns, splitting ids
    ("TCGA_CS_4942_199" / "70222") and the outputs line, so neither could be grepped.
    Not a terminal and no COLUMNS: the commands' consoles do not wrap."""
    import importlib
    import io
    import types

    import tumor3d.flows.cli.output as output
    from tumor3d.storage.derivatives import VOLUME_LABELS

    app_module = importlib.import_module("tumor3d.flows.cli.app")  # not the Typer app
    monkeypatch.delenv("COLUMNS", raising=False)
    monkeypatch.setattr(sys, "stdout", io.StringIO())  # piped
    console = app_module._console()
    assert not console.is_terminal
    monkeypatch.setattr(output, "console", console)
    ids = [f"TCGA_CS_4942_1997022{k}_a_rather_long_site_suffix" for k in range(3)]
    metrics = {key: 12345.0 for key in VOLUME_LABELS} | {"notes": "", "review_reasons": ""}
    result = types.SimpleNamespace(
        patients=[
            types.SimpleNamespace(patient_id=i, status="ok", metrics=metrics,
                                  stages=[types.SimpleNamespace(cached=True)] * 10)
            for i in ids
        ],
        failed=[], removed=[], earlier=[], wall_seconds=1.0,
        out_dir="/a/rather/long/output/folder/of/a/site/that/runs/cohorts/every/night",
    )  # fmt: skip
    output.print_cohort_summary(result)
    lines = sys.stdout.getvalue().splitlines()
    for pid in ids:
        assert [line for line in lines if pid in line], (pid, lines)
    (last,) = [line for line in lines if line.startswith("3 ok")]
    assert last.endswith("(cohort.parquet, cohort.md, cohort.html)"), last


def test_the_demos_errors_against_the_truth_keep_their_sign(monkeypatch):
    """demo printed |error|: +1.43 % and -1.22 % both read as a plain percentage."""
    import io
    import types

    from rich.console import Console

    import tumor3d.flows.cli.output as output
    from tumor3d.flows.patient import VOLUME_LABELS, VOLUME_METHODS

    volumes = dict(zip(VOLUME_METHODS, [10143.0, 9878.0, 10000.0, 10050.0], strict=True))
    metrics = volumes | {
        "faces_mc": 10, "faces_simplified": 5, "mesh_watertight": True, "n_slices": 9,
        "n_abnormal_slices": 3, "n_tumor_slices": 3, "slab_height_mm": 5.0, "slices_between": 4,
    }  # fmt: skip
    result = types.SimpleNamespace(
        patient_id="p", metrics=metrics, stages=[], notes=[], up_to_date=False, output_dir="o"
    )
    buf = io.StringIO()
    monkeypatch.setattr(output, "console", Console(file=buf, width=120))
    output.print_summary(result, truth_mm3=10000.0)
    rows = {line.split("│")[1].strip(): line for line in buf.getvalue().splitlines() if "│" in line}
    errors = [rows[VOLUME_LABELS[key]].split("│")[4].strip() for key in VOLUME_METHODS]
    assert errors == ["+1.43 %", "-1.22 %", "+0.00 %", "+0.50 %"]


def test_a_piped_console_says_when_a_patient_was_up_to_date(capsys):
    from tumor3d.flows.cli.output import _PlainReporter
    from tumor3d.tasks.progress import ProgressEvent

    report = _PlainReporter()
    report(ProgressEvent("p1", "up to date", "published", 10, 10))
    report(ProgressEvent("p2", "published", "published", 10, 10))
    assert capsys.readouterr().out == "p1\tpublish\tup to date\np2\tpublish\tpublished\n"


def test_plain_progress_lines_of_parallel_lanes_stay_whole(monkeypatch):
    """An audit's piped log had two lanes' lines run together ("0.70 sp004 ..."): each
    lane reports from its own thread, and print writes the line and its newline apart.
    A stream that yields between writes makes the interleaving happen every time."""
    import threading
    import time

    from tumor3d.flows.cli.output import _PlainReporter
    from tumor3d.tasks.progress import ProgressEvent

    class Yielding:
        def __init__(self):
            self.parts = []

        def write(self, text):
            self.parts.append(text)
            time.sleep(0.0002)  # another thread runs here
            return len(text)

        def flush(self):
            pass

    out = Yielding()
    monkeypatch.setattr(sys, "stdout", out)
    report = _PlainReporter()

    def lane(pid):
        for k in range(20):
            report(ProgressEvent(pid, f"stage{k}", "done", k, 20, seconds=0.5))

    threads = [threading.Thread(target=lane, args=(f"p{i}",)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    lines = "".join(out.parts).splitlines()
    assert len(lines) == 80
    whole = [line.count("\t") == 2 and line.endswith("\t0.50 s wall") for line in lines]
    assert all(whole), lines[:6]


def test_the_evaluation_table_shows_the_metrics_the_run_has():
    """``--evaluation interpolation`` alone printed Dice, HD95 and Eq. 7 columns of dashes."""
    import io

    import pandas as pd
    from rich.console import Console

    from tumor3d.flows.cli.evaluate import _evaluation_table

    def shown(df, width=150):
        buf = io.StringIO()
        Console(file=buf, width=width).print(_evaluation_table(df))
        return buf.getvalue()

    base = {"config": "default", "patient_id": "p1", "status": "ok", "run_status": "ok"}
    geometry = pd.DataFrame([{**base, "interp_se_eps_percent": 1.0, "dice_3d": float("nan")}])
    text = shown(geometry)
    assert "p1" in text and "Dice" not in text and "HD95" not in text and "Eq. 7" not in text
    scored = pd.DataFrame([{**base, "dice_slices_mean": 0.9, "dice_pooled": 0.6, "dice_3d": 0.91,
                            "hd95_mm": 2.0, "volume_eq7_error_percent": -3.0}])  # fmt: skip
    text = shown(scored)
    # the mean over the reference's tumour slices beside the pooled Dice, which counts the
    # slices segmented where the reference has none (a user audit read 0.926 as the whole)
    for header, value in (("Dice ref slices", "0.900"), ("Dice pooled", "0.600"),
                          ("3-D Dice", "0.910"), ("Eq. 7 err", "-3.0 %")):  # fmt: skip
        assert header in text and value in text, text
    # an 80-column terminal keeps a row's config and patient id whole beside its status
    long = scored.assign(config="peer_multiotsu", patient_id="phantom001n", run_status="check")
    rows = [line for line in shown(long, width=80).splitlines() if "phantom001n" in line]
    assert len(rows) == 1 and "peer_multiotsu" in rows[0] and "check" in rows[0], rows


def test_a_stacks_sidecar_names_the_modality_when_none_is_given(
    tmp_path, monkeypatch, run_flow_given
):
    """stack.yaml's ``modality`` (documented) is the run's when --modality is not given:
    the command line, the flow's source and the Python API take it before the default,
    and --modality still overrides it."""
    import yaml
    from PIL import Image

    import tumor3d.api
    from tumor3d.flows.patient import prepare_source

    stack = tmp_path / "stk"
    stack.mkdir()
    rng = np.random.default_rng(6)
    for k in range(4):
        Image.fromarray(rng.integers(10, 250, (12, 12)).astype(np.uint8)).save(stack / f"s{k}.png")
    sidecar = {"pixel_spacing_mm": 1.0, "slice_thickness_mm": 2.0, "slice_gap_mm": 3.0}
    (stack / "stack.yaml").write_text(yaml.safe_dump({**sidecar, "modality": "FLAIR"}))
    seen = run_flow_given
    named = runner.invoke(app, ["run", str(stack), "--out", str(tmp_path / "o")])
    assert named.exit_code == 0, named.output
    assert seen["modality"] == "flair"
    assert "modality: flair (named by the stack's sidecar)" in " ".join(named.output.split())
    given = runner.invoke(
        app, ["run", str(stack), "--out", str(tmp_path / "o"), "--modality", "t1c"]
    )
    assert given.exit_code == 0 and seen["modality"] == "t1c"
    # the sidecar's other modality is said beside the given one (a user audit: a typo in
    # --modality passed silently); the same one is not repeated
    said = " ".join(given.output.split())
    assert "modality: t1c (given; the stack's sidecar names flair)" in said
    same = runner.invoke(
        app, ["run", str(stack), "--out", str(tmp_path / "o"), "--modality", "FLAIR"]
    )
    assert same.exit_code == 0 and "sidecar" not in same.output
    assert prepare_source(stack).modality == "flair" and not prepare_source(stack).modality_default
    assert prepare_source(stack, modality="t2").modality == "t2"
    scans = []
    monkeypatch.setattr(tumor3d.api, "reconstruct_scan", lambda scan, **kw: scans.append(scan))
    tumor3d.api.reconstruct(stack)  # no "give modality=": the sidecar names it
    assert scans[-1].modality == "flair"
    # without the key: the default, said as the default; a bad value names the sidecar
    (stack / "stack.yaml").write_text(yaml.safe_dump(sidecar))
    assert prepare_source(stack).modality == "t2"
    with pytest.raises(InputError, match="give modality="):
        tumor3d.api.reconstruct(stack)
    (stack / "stack.yaml").write_text(yaml.safe_dump({**sidecar, "modality": "pd"}))
    bad = runner.invoke(app, ["run", str(stack), "--out", str(tmp_path / "o")])
    assert bad.exit_code == 2 and "unknown modality 'pd'" in bad.output
    assert "stack.yaml" in bad.output and "Traceback" not in bad.output


def test_prefect_run_records_stay_off_the_console_without_verbose():
    import logging

    from tumor3d.flows.quiet_logs import NoRunRecords

    keep = NoRunRecords()

    def record(name, level):
        return logging.LogRecord(name, level, __file__, 1, "x", None, None)

    # a flow run's warning (a skipped row, a failed patient) is said by the command itself
    assert not keep.filter(record("prefect.flow_runs", logging.WARNING))
    assert not keep.filter(record("prefect.task_runs", logging.ERROR))
    assert keep.filter(record("prefect.client", logging.WARNING))
    # an events worker draining as the command ends (a user audit saw it after the error line)
    draining = record("EventsWorker", logging.WARNING)
    draining.msg = "Still processing items: 1 items remaining..."
    assert not keep.filter(draining)


def test_methods_lists_the_registered_segmentation_methods_and_formats():
    from tumor3d.segmentation.methods import method_names
    from tumor3d.storage.readers.registry import registered_readers

    result = CliRunner().invoke(app, ["methods"], env={"COLUMNS": "200"})
    assert result.exit_code == 0
    rows = {line.split("│")[1].strip() for line in result.output.splitlines() if "│" in line}
    assert set(method_names()) | set(registered_readers()) <= rows
    # piped with no COLUMNS (a log file: the console is 1,000 wide), the tables still wrap
    # their descriptions to a readable width (a user audit saw 230 columns)
    piped = CliRunner().invoke(app, ["methods"], env={"COLUMNS": None})
    lines = piped.output.splitlines()
    assert max(len(line) for line in lines) <= 100 and len(lines) > len(rows)
    assert {line.split("│")[1].strip() for line in lines if "│" in line} == rows

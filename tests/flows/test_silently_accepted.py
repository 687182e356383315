"""Issue 29's "silently accepted" and "one line" inputs: each refused in one line, exit 2.

A YAML giving a key twice, ``true`` or ``"3"`` for a number, a config file that
is not UTF-8, voxels of 0.0009 mm (a unit error) and a slice thickness larger
than the slice step: all refused before any work, naming the file and the
problem, with nothing left in the output folder.
"""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
from typer.testing import CliRunner

from tumor3d.config import parse_config
from tumor3d.errors import ConfigError, InputError
from tumor3d.flows.cli import EXIT_INPUT, app
from tumor3d.storage.readers import read_scan

runner = CliRunner()


def _nifti(path, spacing=(1.0, 1.0, 5.0)):
    data = np.random.default_rng(0).random((24, 24, 6)) + 1
    nib.save(nib.Nifti1Image(data.astype(np.float32), np.diag([*spacing, 1.0])), path)
    return path


def _one_line(res, *needles):
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert res.exit_code == EXIT_INPUT, res.output
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    for n in needles:
        assert n in res.output, (n, res.output)


def _run_with_config(tmp_path, content: bytes):
    cfg = tmp_path / "c.yaml"
    cfg.write_bytes(content)
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(_nifti(tmp_path / "x.nii.gz")), "--out", str(out),
                              "--config", str(cfg)])  # fmt: skip
    assert not out.exists()
    return res


def test_a_key_given_twice_is_refused(tmp_path):
    doc = b"render:\n  views: [anterior]\nsimplify: {reduction_percent: 40}\nrender: {}\n"
    _one_line(_run_with_config(tmp_path, doc), "c.yaml", "'render' is given twice", "lines 1 and 4")
    # nested keys too; distinct keys are fine
    with pytest.raises(ConfigError, match="'reduction_percent' is given twice"):
        parse_config("simplify: {reduction_percent: 40, reduction_percent: 50}\n")
    assert parse_config("simplify: {reduction_percent: 40}\n").simplify.reduction_percent == 40


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("segment: {min_tumor_slices: true}\n", "segment.min_tumor_slices"),
        ("simplify: {reduction_percent: '40'}\n", "simplify.reduction_percent"),
        ("preprocess: {median_size: false}\n", "preprocess.median_size"),
    ],
)
def test_booleans_and_text_are_not_numbers(tmp_path, text, key):
    _one_line(_run_with_config(tmp_path, text.encode()), "c.yaml", key, "must be a number")


def test_a_number_yaml_reads_as_text_is_told_how_to_write_it(tmp_path):
    """PyYAML (YAML 1.1) reads ``1e1`` as text: the error says so, not "quoted"."""
    r = _run_with_config(tmp_path, b"simplify: {reduction_percent: 1e1}\n")
    _one_line(r, "c.yaml", "simplify.reduction_percent", "YAML reads 1e1 as text")
    assert "quoted" not in r.output and "1.0e+1" in r.output


def test_numbers_stay_numbers():
    cfg = parse_config({"segment": {"min_tumor_slices": 3}, "simplify": {"reduction_percent": 40}})
    assert cfg.segment.min_tumor_slices == 3 and cfg.simplify.reduction_percent == 40.0
    # an integer for a float field, and booleans for boolean fields, are fine
    assert parse_config({"preprocess": {"sharpen": True}}).preprocess.sharpen is True


def test_a_config_that_is_not_utf8_is_one_line(tmp_path):
    from tumor3d.flows.serve import load_config_file

    res = _run_with_config(tmp_path, b"render: {}\n# \xff\xfe\n")
    _one_line(res, "c.yaml", "not UTF-8", "0xff")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_config_file(tmp_path / "c.yaml")


def test_a_scheduled_runs_config_names_its_models_folder_absolute(tmp_path, monkeypatch):
    """Audit 5: ``serve`` read segment.learned_models relative, to be resolved later from
    the scheduled run's working directory; a URL is refused at once (it was resolved as
    a local path). Each patient's run checks the files it uses (test_bundle.py)."""
    from tumor3d.flows.serve import load_config_file

    (tmp_path / "c.yaml").write_text("segment:\n  learned_models: m\n")
    monkeypatch.chdir(tmp_path)
    cfg = load_config_file(tmp_path / "c.yaml")
    assert cfg["segment"]["learned_models"] == str(tmp_path.resolve() / "m")
    (tmp_path / "c.yaml").write_text("segment:\n  learned_models: s3://bucket/m\n")
    with pytest.raises(InputError, match=r"^s3://bucket/m: .* a local folder, not a URL"):
        load_config_file(tmp_path / "c.yaml")


@pytest.mark.parametrize("spacing", [(0.0009, 0.0009, 0.0045), (1.0, 1.0, 0.001)])
def test_voxels_finer_than_any_mr_are_refused_in_one_line(tmp_path, spacing):
    image = _nifti(tmp_path / "tiny.nii.gz", spacing)
    with pytest.raises(InputError, match="finer than any MR scanner"):
        read_scan(image)
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(image), "--out", str(out)])
    _one_line(res, "tiny.nii.gz", "finer than any MR scanner")
    assert not out.exists()  # no .tumor3d-store left behind
    assert read_scan(_nifti(tmp_path / "fine.nii.gz", (0.1, 0.1, 0.5))).slice_step_mm == 0.5


@pytest.mark.parametrize("thickness", ["1e9", "1e6", "100"])
def test_a_slice_thickness_larger_than_the_step_is_refused(tmp_path, thickness):
    image = _nifti(tmp_path / "x.nii.gz")  # 5 mm slice step
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(image), "--out", str(out),
                              "--slice-thickness-mm", thickness])  # fmt: skip
    _one_line(res, "x.nii.gz", "slice_thickness_mm", "larger than the slice step")
    assert not out.exists()
    # at most the step is the acquired thickness, the rest the gap
    scan = read_scan(image, slice_thickness_mm=2.0)
    assert (scan.slice_thickness_mm, scan.slice_gap_mm) == (2.0, 3.0)

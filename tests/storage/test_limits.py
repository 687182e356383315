"""Resource limits: YAML alias bombs, long values in messages, declared volume size (issue 12)."""

from __future__ import annotations

import gzip

import nibabel as nib
import numpy as np
import pytest
from dicom_factory import write_series
from PIL import Image

from tumor3d.config import load_yaml, parse_config
from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.errors import ConfigError, InputError
from tumor3d.storage.readers import read_scan


def alias_bomb(levels: int = 6, fan: int = 10, key: str = "render") -> str:
    """Nested anchors: ``fan ** levels`` values from a few hundred bytes."""
    lines = [f"l0: &l0 [{', '.join(['0'] * fan)}]"]
    for i in range(1, levels):
        lines.append(f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * fan)}]")
    lines.append(f"{key}: {{azimuths_deg: *l{levels - 1}}}")
    return "\n".join(lines) + "\n"


def test_config_alias_bomb_is_refused_before_validation():
    text = alias_bomb()  # 10**6 azimuths from about 300 bytes; 9 levels would be 10**9
    assert len(text) < 400
    with pytest.raises(ConfigError, match="bomb.yaml: not valid YAML: .*alias bomb") as info:
        parse_config(text, source="bomb.yaml")
    assert len(str(info.value)) < 300 and "\n" not in str(info.value)


def test_too_many_aliases_and_recursive_aliases_are_refused():
    many = "a: &a 1\nb: [" + ", ".join(["*a"] * 101) + "]\n"
    with pytest.raises(ConfigError, match="more than 100 aliases"):
        load_yaml(many, source="many.yaml")
    with pytest.raises(ConfigError, match="recursive alias"):
        load_yaml("a: &a [1, *a]\n", source="loop.yaml")
    # ordinary reuse still works
    assert load_yaml("a: &x [1, 2]\nb: *x\n") == {"a": [1, 2], "b": [1, 2]}


def test_long_values_and_many_errors_are_cut_in_the_message():
    huge = "x" * 100_000
    with pytest.raises(ConfigError) as info:
        parse_config({"render": {"width": huge}}, source="c.yaml")
    assert "key 'render.width'" in str(info.value)
    assert len(str(info.value)) < 400
    text = "render: {views: [" + ", ".join(["1"] * 1000) + "]}\n"
    with pytest.raises(ConfigError) as info:
        parse_config(text, source="c.yaml")
    message = str(info.value)
    assert "more problem(s)" in message and len(message) < 1500


def test_oversized_yaml_is_refused():
    with pytest.raises(ConfigError, match="more than the 1,000,000 allowed"):
        load_yaml("a: 1\n" + "#" * 1_000_001, source="big.yaml")


def test_stack_sidecar_alias_bomb_is_refused(tmp_path):
    folder = tmp_path / "stack"
    folder.mkdir()
    for k in range(2):
        Image.fromarray((np.arange(64).reshape(8, 8) + k).astype(np.uint8)).save(
            folder / f"s{k}.png"
        )
    text = "pixel_spacing_mm: 1\nslice_thickness_mm: 2\nslice_gap_mm: 0\n" + alias_bomb(key="extra")
    (folder / "stack.yaml").write_text(text)
    with pytest.raises(InputError, match=r"stack\.yaml: not a readable YAML sidecar.*alias bomb"):
        read_scan(folder)


def test_stack_sidecar_messages_have_no_square_brackets(tmp_path):
    """'[dy, dx]' was eaten as Rich markup and printed as '( in mm)'."""
    folder = tmp_path / "stack"
    folder.mkdir()
    for k in range(2):
        Image.fromarray((np.arange(64).reshape(8, 8) + k).astype(np.uint8)).save(
            folder / f"s{k}.png"
        )
    (folder / "stack.yaml").write_text("slice_thickness_mm: 2\nslice_gap_mm: 0\n")
    with pytest.raises(InputError, match="missing key 'pixel_spacing_mm'") as info:
        read_scan(folder)
    assert "[" not in info.value.problem and "dy, dx in mm" in info.value.problem


def _nifti_header_only(path, shape):
    """A .nii.gz whose header declares ``shape`` but holds almost no voxel data."""
    header = nib.Nifti1Header()
    header.set_data_dtype(np.int16)
    header.set_data_shape(shape)
    header.set_sform(np.diag([1.0, 1.0, 5.0, 1.0]), code=1)
    raw = header.binaryblock + b"\0" * 4 + b"\0" * 1024  # vox_offset 352, then a stub
    path.write_bytes(gzip.compress(raw))
    return path


def test_nifti_declared_size_is_checked_before_reading(tmp_path):
    f = _nifti_header_only(tmp_path / "bomb.nii.gz", (2048, 2048, 300))
    assert f.stat().st_size < 10_000
    with pytest.raises(InputError) as info:
        read_scan(f)
    message = str(info.value)
    assert "bomb.nii.gz" in message
    assert "2048 x 2048 x 300 = 1,258,291,200 voxels" in message
    assert f"{MAX_VOXELS_DEFAULT:,}" in message and "max_voxels" in message


def test_voxel_limit_is_configurable(tmp_path):
    data = np.arange(6 * 5 * 4, dtype=np.int16).reshape(6, 5, 4) + 1
    f = tmp_path / "small.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([1.0, 1.0, 5.0, 1.0])), str(f))
    assert read_scan(f, max_voxels=120).shape == (4, 5, 6)
    with pytest.raises(InputError, match="6 x 5 x 4 = 120 voxels, more than the limit of 119"):
        read_scan(f, max_voxels=119)
    with pytest.raises(TypeError, match="max_voxels must be an integer"):
        read_scan(f, max_voxels=1.5)


def test_dicom_series_size_is_checked_before_decoding(tmp_path):
    folder = tmp_path / "case"
    write_series(folder, n_slices=6, rows=16, cols=12)
    with pytest.raises(InputError, match="16 x 12 x 6 = 1,152 voxels"):
        read_scan(folder, max_voxels=1000)
    assert read_scan(folder, max_voxels=1152).n_slices == 6


def test_read_nifti_checks_the_declared_size(tmp_path):
    from tumor3d.storage.nifti import read_nifti

    f = _nifti_header_only(tmp_path / "ref.nii.gz", (2048, 2048, 300))
    with pytest.raises(InputError, match=r"ref\.nii\.gz: the header declares 2048 x 2048 x 300"):
        read_nifti(f)


def test_image_stack_size_is_checked_before_decoding(tmp_path):
    folder = tmp_path / "stack"
    folder.mkdir()
    for k in range(3):
        Image.fromarray((np.arange(80).reshape(8, 10) + k).astype(np.uint8)).save(
            folder / f"s{k}.png"
        )
    (folder / "stack.yaml").write_text(
        "pixel_spacing_mm: 1\nslice_thickness_mm: 2\nslice_gap_mm: 0\n"
    )
    with pytest.raises(InputError, match=r"stack: the header declares 10 x 8 x 3 = 240 voxels"):
        read_scan(folder, max_voxels=239)
    assert read_scan(folder, max_voxels=240).shape == (3, 8, 10)


def test_image_decompression_bomb_is_one_line(tmp_path, monkeypatch):
    folder = tmp_path / "stack"
    folder.mkdir()
    for k in range(2):
        Image.fromarray(np.full((64, 64), 10 + k, np.uint8)).save(folder / f"s{k}.png")
    (folder / "stack.yaml").write_text(
        "pixel_spacing_mm: 1\nslice_thickness_mm: 2\nslice_gap_mm: 0\n"
    )
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # 64 x 64 > 2 x 1000: Pillow's bomb error
    with pytest.raises(InputError, match=r"s0\.png: refused as a decompression bomb"):
        read_scan(folder)

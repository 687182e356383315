"""A given brain mask (``--brain-mask``, issue 7) through the patient flow.

One phantom, one shared store: a run without a mask, a run with a mask that
keeps only the half of the brain holding the tumour's left part, the same
mask again (all cache hits), the same bytes under another name (all cache
hits: the key follows the content), and the whole-brain mask (preprocess and
every stage after it recomputed).
"""

from __future__ import annotations

import hashlib
import json
import shutil

import nibabel as nib
import numpy as np
import pandas as pd
import pytest

from tumor3d.flows.patient import run_patient
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.tasks.stages import STAGES

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]

STAGE_NAMES = list(STAGES)
BRAIN_LABELS = (3, 4, 5, 6)  # csf, grey and white matter, tumour (tumor3d.phantom LABEL_NAMES)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """The phantom, its image, the x column splitting its tumour and two mask files."""
    tmp = tmp_path_factory.mktemp("mask-in")
    patient = make_phantom_patient(3, patient_id="maskpat", n_slices=16)
    image = write_phantom_patient(patient, tmp).image
    affine = nib.load(image).affine
    brain = np.isin(patient.tissue_labels, BRAIN_LABELS)  # (z, y, x)
    xs = np.nonzero(patient.slice_masks)[2]
    cut = int(round((xs.min() + xs.max()) / 2))  # the tumour's middle column
    half = brain.copy()
    half[:, :, cut:] = False

    def save(name, mask_zyx, scale):  # NIfTI order (x, y, z), as the image
        path = tmp / name
        data = (mask_zyx.transpose(2, 1, 0) * scale).astype(np.uint8)
        nib.save(nib.Nifti1Image(data, affine), path)
        return path

    return {
        "patient": patient, "image": image, "cut": cut, "half_zyx": half,
        "half": save("half_brain.nii.gz", half, 255),  # a 0/255 mask
        "full": save("whole_brain.nii.gz", brain, 1),  # a 0/1 mask
        "store": tmp_path_factory.mktemp("mask-store"),
    }  # fmt: skip


def _run(case, out, mask=None):
    return run_patient(
        case["image"], out, patient_id="maskpat", store_dir=str(case["store"]),
        brain_mask=None if mask is None else str(mask),
    )  # fmt: skip


@pytest.fixture(scope="module")
def runs(case, tmp_path_factory):
    """The run without a mask, then with the half mask (in that order, one store)."""
    plain_out = tmp_path_factory.mktemp("plain-out")
    mask_out = tmp_path_factory.mktemp("mask-out")
    plain = _run(case, plain_out)
    half = _run(case, mask_out, case["half"])
    return {"plain": (plain_out, plain), "half": (mask_out, half)}


def _zyx(path):
    return np.asarray(nib.load(path).dataobj).transpose(2, 1, 0)


def test_the_given_mask_is_the_brain_and_bounds_the_tumour(case, runs):
    out, result = runs["half"]
    folder = out / "maskpat"
    assert [s.cached for s in result.stages][:1] == [True]  # the scan is the plain run's
    np.testing.assert_array_equal(_zyx(folder / "brain_mask.nii.gz") > 0, case["half_zyx"])
    tumour = _zyx(folder / "tumor_mask_slices.nii.gz") > 0
    assert tumour.any() and not (tumour & ~case["half_zyx"]).any()


def test_half_the_brain_gives_about_the_tumour_part_inside_it(case, runs):
    """Independent expectation: the truth's share of tumour area left of the cut."""
    truth = case["patient"].slice_masks
    share = truth[:, :, : case["cut"]].sum() / truth.sum()
    assert 0.3 < share < 0.7
    plain = runs["plain"][1].metrics["volume_eq7_mm3"]
    half = runs["half"][1].metrics["volume_eq7_mm3"]
    assert half < 0.8 * plain
    assert half / plain == pytest.approx(share, abs=0.1)


def test_provenance_and_notes_record_the_given_mask(case, runs):
    out, result = runs["half"]
    prov = json.loads((out / "maskpat" / "provenance.json").read_text())
    sha = hashlib.sha256(case["half"].read_bytes()).hexdigest()
    assert prov["brain_mask"]["given"] is True
    assert prov["brain_mask"]["file"] == "half_brain.nii.gz"
    assert prov["brain_mask"]["sha256"] == sha
    assert any(n.startswith("brain mask given (half_brain.nii.gz") for n in result.notes)
    assert "brain mask given" in (out / "maskpat" / "report.html").read_text()
    plain = json.loads((runs["plain"][0] / "maskpat" / "provenance.json").read_text())
    assert plain["brain_mask"]["given"] is False


def test_cache_follows_the_mask_content(case, runs, tmp_path):
    out, first = runs["half"]
    again = _run(case, out, case["half"])
    assert all(again.cache_hits), [s.stage for s in again.stages if not s.cached]
    assert again.up_to_date
    # the same bytes under another name: the same keys, but provenance names the new file
    renamed = tmp_path / "renamed_mask.nii.gz"
    shutil.copyfile(case["half"], renamed)
    moved = _run(case, out, renamed)
    assert all(moved.cache_hits) and not moved.up_to_date
    prov = json.loads((out / "maskpat" / "provenance.json").read_text())
    assert prov["brain_mask"]["file"] == "renamed_mask.nii.gz"
    # another mask: the scan is reused, preprocess and every later stage recompute
    whole = _run(case, out, case["full"])
    assert whole.cache_hits == [True] + [False] * (len(STAGE_NAMES) - 1)
    assert whole.metrics["volume_eq7_mm3"] > first.metrics["volume_eq7_mm3"]
    # and the run without a mask still finds all its results
    plain_out, plain = runs["plain"]
    after = _run(case, plain_out)
    assert all(after.cache_hits), [s.stage for s in after.stages if not s.cached]
    assert after.metrics["volume_eq7_mm3"] == plain.metrics["volume_eq7_mm3"]


def test_a_brain_mask_larger_than_any_skull_is_named_in_the_notes(case, runs, tmp_path):
    # the same phantom declared with 2.5 times larger pixels: its (correct) brain mask
    # now holds about 7 L, more than any skull; the run says so instead of reporting a
    # tumour volume silently
    img = nib.load(case["image"])
    affine = img.affine.copy()
    affine[:3, :2] *= 2.5  # the in-plane voxel axes (x, y) of the NIfTI
    big = tmp_path / "big_pixels.nii.gz"
    nib.save(nib.Nifti1Image(np.asarray(img.dataobj), affine), big)
    result = run_patient(big, tmp_path / "out", patient_id="bigpat", store_dir=str(tmp_path / "s"))
    note = [n for n in result.notes if "more than any skull holds" in n]
    assert len(note) == 1 and "--brain-mask" in note[0]
    metrics = pd.read_parquet(tmp_path / "out" / "bigpat" / "metrics.parquet")
    assert "more than any skull holds" in metrics.loc[0, "notes"]
    # the run at the true pixel size has no such note
    assert not any("more than any skull" in n for n in runs["plain"][1].notes)

"""nibabel's header repairs never reach the console; the run's notes say them (issue 29).

nibabel repairs some NIfTI headers on reading (an invalid ``qform_code``, a
``sizeof_hdr`` other than 348) and logs each repair on its own logger, which
printed it to stderr, once per reading (the command line reads the input two
or three times), and again through Prefect's console handler. The ingest-scan
stage now records the repairs as one note of the run instead.
"""

from __future__ import annotations

import functools
import logging
import struct

import nibabel as nib
import numpy as np

from tumor3d.flows.patient import run_notes, run_stages_direct
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.storage.readers import read_scan

NOTE = "hdr.nii: nibabel repaired the NIfTI header on reading: qform_code 7 not valid; setting to 0"


@functools.cache
def _patient():
    return make_phantom_patient(3, patient_id="hdr", n_slices=12)  # read-only arrays


def _bad_qform_code(tmp_path):
    """A phantom NIfTI (uncompressed) whose qform_code is 7: nibabel sets it to 0, logging it."""
    patient = _patient()
    row = write_phantom_patient(patient, tmp_path / "in")
    img = nib.load(row.image)
    plain = tmp_path / "hdr.nii"
    nib.save(nib.Nifti1Image(np.asarray(img.dataobj), img.affine), plain)
    raw = bytearray(plain.read_bytes())
    struct.pack_into("<h", raw, 252, 7)  # qform_code
    plain.write_bytes(bytes(raw))
    return plain


def test_reading_a_repaired_header_prints_nothing(tmp_path, capfd, caplog):
    path = _bad_qform_code(tmp_path)
    capfd.readouterr()
    with caplog.at_level(logging.DEBUG):
        scan = read_scan(path, patient_id="hdr")
    assert scan.n_slices == 12
    err = capfd.readouterr().err
    assert "qform_code" not in err, err
    assert not [r for r in caplog.records if r.name.startswith("nibabel")]


def test_the_repair_is_one_note_of_the_run(tmp_path, capfd):
    path = _bad_qform_code(tmp_path)
    capfd.readouterr()
    run = run_stages_direct(path, tmp_path / "store", patient_id="hdr")
    assert "qform_code" not in capfd.readouterr().err
    assert run.outputs["ingest-scan"].values["header_notes"] == [NOTE]
    notes, doubts = run_notes(run.outputs)
    assert notes.count(NOTE) == 1
    assert not [d for d in doubts if "qform_code" in d]  # informational: status stays ok


def test_a_later_logging_set_up_does_not_bring_the_messages_back(tmp_path, capfd, caplog):
    """Another library re-enabling propagation (and adding a printer) after the
    first reading: the next reading is as quiet as the first."""
    path = _bad_qform_code(tmp_path)
    read_scan(path, patient_id="hdr")  # installs the collector
    logger = logging.getLogger("nibabel.global")
    logger.propagate = True
    logger.addHandler(logging.StreamHandler())  # stderr
    capfd.readouterr()
    with caplog.at_level(logging.DEBUG):
        read_scan(path, patient_id="hdr")
    assert "qform_code" not in capfd.readouterr().err
    assert not [r for r in caplog.records if r.name.startswith("nibabel")]


def test_a_header_without_orientation_is_a_doubt_of_the_run(tmp_path):
    """sform and qform codes 0 (an Analyze-style header): nibabel assumes its default
    axes, so the side and the front are a guess; the run says so and is checked. The
    same file with its orientation stated gives no such note."""
    img = nib.load(write_phantom_patient(_patient(), tmp_path / "in").image)
    stated = nib.Nifti1Image(np.asarray(img.dataobj), img.affine)
    nib.save(stated, tmp_path / "stated.nii")
    unstated = nib.Nifti1Image(np.asarray(img.dataobj), None)
    unstated.header.set_zooms(img.header.get_zooms())
    assert int(unstated.header["sform_code"]) == int(unstated.header["qform_code"]) == 0
    nib.save(unstated, tmp_path / "unstated.nii")
    run = run_stages_direct(tmp_path / "unstated.nii", tmp_path / "store", patient_id="hdr")
    notes, doubts = run_notes(run.outputs)
    said = [n for n in notes if "states no orientation" in n]
    assert said == [
        "unstated.nii: the NIfTI header states no orientation (sform and qform codes 0): "
        "read with nibabel's default axes (LAS), so left-right and front-back are "
        "unverified, and the segmentation and its volume with them (the learned model "
        "reads a head as it lies: this guess may turn it); check them, or give the file "
        "its orientation (the masks on its grid "
        "state none either and overlay it in any viewer; the meshes and the interpolated "
        "mask are placed by that guess, which 3D Slicer and ITK-SNAP do not share)"
    ]
    assert said[0] in doubts
    assert run.outputs["ingest-scan"].values["orientation_stated"] is False
    # the Python API says the same (a review: it read the file without the notes)
    import tumor3d

    api = tumor3d.reconstruct(str(tmp_path / "unstated.nii"), modality="t2")
    assert api.status == "check" and said[0] in api.review_reasons
    run = run_stages_direct(tmp_path / "stated.nii", tmp_path / "store", patient_id="hdr")
    assert run.outputs["ingest-scan"].values["orientation_stated"] is True
    notes, doubts = run_notes(run.outputs)
    assert not [n for n in notes if "orientation" in n]

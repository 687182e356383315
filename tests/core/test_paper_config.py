"""The paper's configuration (configs/paper.yaml) reaches the paper's own claims on T2 phantoms.

Arakeri & Reddy (2013) report every abnormal and every normal slice
recognised (Table 2), a pixel-count error (Eq. 9) of 2.36 % on average
(Table 3) and the Eq. 7 volume. On the project's T2 phantoms (2 mm slices
every 5 mm, tumour brighter than white and grey matter), the chain of
``configs/paper.yaml`` (core entry points, as the stage adapters call them)
must give:

* every slice holding tumour in the truth reported with tumour, and no
  tumour on any other slice (Table 2, counted on the slices the method
  reports with tumour);
* the Eq. 9 error of the patient's tumour pixel count, and its mean over the
  slices, at most 5 %;
* the Eq. 7 volume within 5 % of the phantom's exact volume (quadrature of
  the analytic tumour, independent of any pixel count);
* nothing on a tumour-free phantom.

The literal chain (sharpening and histogram equalisation on, as the previous
paper.yaml had it) segments nothing on these phantoms (0.0 mm3).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tumor3d.config import PipelineConfig, parse_config
from tumor3d.imaging.preprocess import preprocess_volume
from tumor3d.metrics import volume_eq7_mm3
from tumor3d.phantom import make_phantom_patient
from tumor3d.segmentation.detect import detect_abnormal_slices
from tumor3d.segmentation.segment import segment_tumor

PAPER_YAML = Path(__file__).resolve().parents[2] / "configs" / "paper.yaml"


def _paper_config() -> PipelineConfig:
    return parse_config(PAPER_YAML.read_text(), source=str(PAPER_YAML))


def _run(patient, cfg: PipelineConfig):
    scan = patient.scan
    spacing = (scan.slice_step_mm, *scan.pixel_spacing_mm)
    pre = preprocess_volume(
        np.asarray(scan.image), **cfg.preprocess.model_dump(), spacing_mm=spacing
    )
    det = detect_abnormal_slices(
        pre.enhanced, pre.brain_mask, modality=scan.modality, spacing_mm=spacing,
        **cfg.detect.model_dump(),
    )  # fmt: skip
    seg = segment_tumor(
        pre.enhanced, pre.brain_mask, det, modality=scan.modality, spacing_mm=spacing,
        **cfg.segment.model_dump(),
    )  # fmt: skip
    return det, seg


@pytest.fixture(scope="module")
def tumour_run():
    patient = make_phantom_patient(1)
    return patient, *_run(patient, _paper_config())


def test_every_abnormal_slice_is_recognised_and_no_normal_one(tumour_run):
    patient, _, seg = tumour_run
    truth = patient.slice_masks.any(axis=(1, 2))
    found = seg.tumor_pixels > 0
    assert truth.sum() >= 5
    np.testing.assert_array_equal(found, truth)


def test_pixel_count_error_eq9_within_five_percent(tumour_run):
    patient, _, seg = tumour_run
    n_g = patient.slice_masks.sum(axis=(1, 2)).astype(float)
    n_p = seg.tumor_pixels.astype(float)
    assert abs(n_p.sum() - n_g.sum()) / n_g.sum() * 100 <= 5.0
    rows = n_g > 0
    assert np.mean(np.abs(n_p[rows] - n_g[rows]) / n_g[rows] * 100) <= 5.0


def test_eq7_volume_within_five_percent_of_the_truth(tumour_run):
    patient, det, seg = tumour_run
    scan = patient.scan
    slices = det.abnormal | (seg.tumor_pixels > 0)
    volume = volume_eq7_mm3(
        seg.tumor_pixels,
        slices,
        pixel_area_mm2=float(np.prod(scan.pixel_spacing_mm)),
        slab_height_mm=scan.slice_step_mm,
    )
    assert abs(volume - patient.true_volume_mm3) / patient.true_volume_mm3 <= 0.05


def test_no_tumour_on_a_tumour_free_phantom():
    patient = make_phantom_patient(2, tumor=False)
    _, seg = _run(patient, _paper_config())
    assert int(seg.tumor_pixels.sum()) == 0


def test_the_paper_configuration_reads_the_paper_method():
    cfg = _paper_config()
    assert cfg.detect.method == "histogram" and cfg.segment.method == "paper"
    assert cfg.preprocess.brain_extraction == "skull_strip"
    assert cfg.preprocess.skull_threshold == "otsu"
    assert cfg.interpolate.method == "enhanced" and cfg.simplify.method == "curvature"


def test_outside_its_premise_the_paper_method_asks_for_a_check(tumour_run):
    """The paper's method assumes white matter, grey matter and CSF each form a histogram
    mode on (nearly) every slice (T2). On the T2 phantom every slice shows them and the
    run says nothing; on the same head as FLAIR, whose CSF is dark and thin, fewer than
    half of the slices do (0.26-0.53 over seeds 1000-1009): the run says it ran outside
    its premise, with the share of slices, and its status is check."""
    from tumor3d.segmentation.detect.methods import paper_premise_share
    from tumor3d.segmentation.review import review_status

    _, det, seg = tumour_run
    assert paper_premise_share(det.n_modes, det.brain_pixels) == 1.0
    assert not [c for c in seg.caveats if "premise" in c]
    assert review_status(seg.caveats).status == "ok"
    flair = make_phantom_patient(1, modality="flair")
    det2, seg2 = _run(flair, _paper_config())
    share = paper_premise_share(det2.n_modes, det2.brain_pixels)
    assert share < 0.95
    said = [c for c in seg2.caveats if "outside its premise" in c]
    assert len(said) == 1 and f"on {100 * share:.0f} % of the slices with brain" in said[0]
    assert said[0].index("check") < said[0].index("%")  # what to do comes first
    assert review_status(seg2.caveats).status == "check"

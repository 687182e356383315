"""The segment-tumor stage's core function: what it stores, for each branch.

:func:`tumor3d.segmentation.patient.segment_patient` on a small FLAIR phantom, through
the core's own preprocessing and detection (no store, no Prefect): a given mask, the
robust method, the learned method with and without the U-Net; and the pieces of its
values (the review, the shipped models' identity) against expectations computed here.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import tumor3d.learned
from tumor3d.config import LesionConfig, SegmentConfig
from tumor3d.errors import InputError
from tumor3d.imaging.preprocess import preprocess_volume
from tumor3d.learned.review import Review
from tumor3d.learned.shipped import MODEL_IDENTITY_KEYS, model_identity, shipped_model
from tumor3d.phantom.patient import make_phantom_patient
from tumor3d.segmentation.detect import detect_abnormal_slices
from tumor3d.segmentation.lesion import left_right_axis
from tumor3d.segmentation.patient import review_values, segment_detected, segment_patient
from tumor3d.tasks.detect import lesion_metadata

MODELS = Path(tumor3d.learned.__file__).parent / "models"


def _never(what: str):
    def read():
        raise AssertionError(f"{what} was read")

    return read


class _Counted:
    """A reader that counts its calls."""

    def __init__(self, array: np.ndarray) -> None:
        self.array, self.calls = array, 0

    def __call__(self) -> np.ndarray:
        self.calls += 1
        return self.array


@pytest.fixture(scope="module")
def case():
    """A 16-slice 128 x 128 FLAIR phantom through the core's preprocess and detection."""
    patient = make_phantom_patient(2, modality="flair", n_slices=16, matrix_size=(128, 128))
    scan = patient.scan
    spacing = scan.spacing_zyx_mm
    pre = preprocess_volume(scan.image, spacing_mm=spacing)
    lesion_params = LesionConfig().model_dump()
    det = detect_abnormal_slices(
        pre.enhanced,
        pre.brain_mask,
        modality="flair",
        spacing_mm=spacing,
        lr_axis=left_right_axis(scan.affine),
        lesion=lesion_params,
    )
    assert det.lesion is not None  # the robust detection computed the model
    # what the detect stage stores: its records and the lesion's record, through JSON
    record = json.loads(json.dumps(lesion_metadata(det.lesion, lesion_params)))
    exterior = pre.head_exterior if pre.head_exterior is not None else np.zeros_like(pre.brain_mask)
    return {
        "scan": scan,
        "det": det,
        "lesion": det.lesion.mask,
        "abnormal": np.asarray(det.abnormal, bool),
        "inputs": dict(
            enhanced=pre.enhanced,
            brain_mask=pre.brain_mask,
            detection=det.to_records(),
            affine=scan.affine,
            modality="flair",
            spacing_mm=spacing,
            lesion=record,
            head_exterior=exterior,
        ),
    }


def test_a_given_mask_replaces_the_method_and_reads_neither_image_nor_lesion(case):
    nz = case["scan"].image.shape[0]
    mask = np.zeros(case["scan"].image.shape, np.uint8)
    mask[5:9, 40:60, 50:70] = 3  # a label value: any value above 0.5 is tumour
    mask[7, 40:45, 50:52] = 0
    affine = np.diag([0.9, 0.9, 5.0, 1.0])  # the given mask's own, kept
    seg = segment_patient(
        **case["inputs"],
        lesion_mask=_never("the lesion mask"),
        image=_never("the image"),
        given=(mask, affine),
        given_name="seg.nii.gz",
        **SegmentConfig().model_dump(),
    )
    assert seg.result.method == "given"
    assert np.array_equal(seg.result.tumor_mask, mask > 0) and seg.affine is affine
    # independent expectation: the counts of the mask, flagged where it holds tumour
    per_slice = [int(np.count_nonzero(mask[z])) for z in range(nz)]
    assert [r["tumor_pixels"] for r in seg.records] == per_slice
    assert [r["flagged"] for r in seg.records] == [n > 0 for n in per_slice]
    assert [r["flagged"] for r in seg.records] != case["abnormal"].tolist()  # not the detection's
    assert seg.values == {
        "tumor_pixels_total": 4 * 20 * 20 - 10,
        "n_tumor_slices": 4,
        "caveats": [],  # inside the scan: nothing to say
        "modality": "flair",
        "segment_method": "given",
        "measured": "the segmentation given by the user (seg.nii.gz)",
        "segment_model": "",
    }
    assert seg.result.probability is None


def test_the_robust_method_reuses_the_detections_lesion_and_never_reads_the_image(case):
    lesion = _Counted(case["lesion"])
    cfg = SegmentConfig(method="robust").model_dump()
    seg = segment_patient(**case["inputs"], lesion_mask=lesion, image=_never("the image"), **cfg)
    assert lesion.calls == 1
    # independent expectation: the detect stage's lesion on the slices it flags abnormal
    expected = case["lesion"] & case["abnormal"][:, None, None]
    assert np.array_equal(seg.result.tumor_mask, expected) and expected.any()
    assert seg.affine is case["inputs"]["affine"]
    assert seg.values["segment_method"] == "robust" and seg.values["segment_model"] == ""
    assert seg.values["tumor_pixels_total"] == int(expected.sum())
    assert seg.values["n_tumor_slices"] == int(expected.any(axis=(1, 2)).sum())
    assert not set(MODEL_IDENTITY_KEYS) & set(seg.values) and "needs_review" not in seg.values
    assert [r["flagged"] for r in seg.records] == case["abnormal"].tolist()
    # the paper's method does not reuse the lesion model: its mask is not read
    segment_patient(
        **case["inputs"],
        lesion_mask=_never("the lesion mask"),
        image=_never("the image"),
        **SegmentConfig(method="paper").model_dump(),
    )


def _sha256(name: str) -> str:
    return hashlib.sha256((MODELS / f"{name}.npz").read_bytes()).hexdigest()


@pytest.mark.parametrize("learned_cnn", ["auto", "off"])
def test_the_learned_method_records_its_review_and_the_shipped_models(case, learned_cnn):
    image = _Counted(case["scan"].image)
    cfg = SegmentConfig(method="learned", learned_cnn=learned_cnn).model_dump()
    seg = segment_patient(**case["inputs"], lesion_mask=lambda: case["lesion"], image=image, **cfg)
    assert image.calls == 1 and seg.result.method == "learned"
    assert seg.result.probability is not None and seg.result.probability.shape == image.array.shape
    v, review = seg.values, seg.result.review
    # the review, as the segmentation's own Review says it (JSON-able figures)
    assert v["needs_review"] is bool(review.needs_review)
    assert v["review_reasons"] == list(review.reasons)
    assert v["quality_score"] == float(review.quality_score)
    assert set(v["review_figures"]) == set(review.figures)
    json.dumps(v, allow_nan=False)
    # the shipped files, hashed here: the forest of FLAIR's family, and the U-Nets with auto
    expected = {
        "model": shipped_model("flair").meta["name"],
        "model_file": "tumor3d/learned/models/hyper.npz",
        "model_sha256": _sha256("hyper"),
    }
    if learned_cnn == "auto":
        names = ["unet_flair_seed0", "unet_flair_seed1"]
        expected.update(cnn_model=names, cnn_sha256=[_sha256(n) for n in names])
    assert {k: v[k] for k in MODEL_IDENTITY_KEYS if k in v} == expected
    assert v["segment_model"] == ("forest + U-Net mean" if learned_cnn == "auto" else "forest")
    assert v["measured"].startswith("whole tumour: the FLAIR-hyperintense lesion")
    assert v["tumor_pixels_total"] == int(seg.result.tumor_mask.sum())


def test_a_users_models_are_read_only_by_the_learned_method_and_recorded_as_theirs(case):
    """``segment.learned_models``: the models (a callable) are read once, by the learned
    method only; their files are what the values name; named and not given, an error."""
    from tumor3d.learned.bundle import model_set

    files = {f"{n}.npz": (MODELS / f"{n}.npz").read_bytes() for n in ("hyper", "unet_flair_seed1")}
    calls = []

    def models():
        calls.append(1)
        return model_set(files, "flair", source="/data/mine")

    cfg = SegmentConfig(method="robust", learned_models="/data/mine").model_dump()
    robust = segment_patient(
        **case["inputs"], lesion_mask=lambda: case["lesion"], image=_never("the image"),
        models=models, **cfg,
    )  # fmt: skip
    assert robust.result.method == "robust" and calls == []
    cfg = SegmentConfig(method="learned", learned_models="/data/mine").model_dump()
    seg = segment_patient(
        **case["inputs"], lesion_mask=lambda: case["lesion"], image=lambda: case["scan"].image,
        models=models, **cfg,
    )  # fmt: skip
    assert calls == [1]
    assert seg.values["segment_model"] == "forest + U-Net mean, models of /data/mine"
    assert {k: seg.values[k] for k in MODEL_IDENTITY_KEYS} == {
        "model": shipped_model("flair").meta["name"],
        "model_file": "/data/mine/hyper.npz",
        "model_sha256": _sha256("hyper"),
        "cnn_model": ["/data/mine/unet_flair_seed1.npz"],  # the folder's one net
        "cnn_sha256": [_sha256("unet_flair_seed1")],
    }
    for method in ("learned", "auto"):  # never the shipped models, nor robust, in their place
        cfg = SegmentConfig(method=method, learned_models="/data/mine").model_dump()
        with pytest.raises(InputError, match="names '/data/mine' but no model was given"):
            segment_patient(
                **case["inputs"], lesion_mask=lambda: case["lesion"],
                image=lambda: case["scan"].image, **cfg,
            )  # fmt: skip


def test_review_values_are_json_able():
    review = Review(True, ("low confidence",), 0.25, {"a": 1.5, "b": math.nan, "c": math.inf})
    assert review_values(review) == {
        "needs_review": True,
        "review_reasons": ["low confidence"],
        "quality_score": 0.25,
        "review_figures": {"a": 1.5, "b": None, "c": None},
    }


def test_a_model_built_in_memory_is_identified_by_its_arrays():
    shipped = shipped_model("t1c")
    unnamed = replace(
        shipped, meta={k: v for k, v in shipped.meta.items() if k != "name"}, file_sha256=""
    )
    got = model_identity("t1c", unnamed)
    assert got == {
        "model": "shipped",
        "model_file": "tumor3d/learned/models/t1c.npz",
        "model_sha256": unnamed.digest(),
    }
    assert got["model_sha256"] != _sha256("t1c")
    assert tuple(model_identity("T1C", shipped)) == MODEL_IDENTITY_KEYS[:3]


def test_one_net_is_identified_as_an_ensemble_of_one():
    """segment_tumor takes one U-Net or several: the identity reads both (the API's path)."""
    from tumor3d.learned.shipped import shipped_cnn

    nets = shipped_cnn("flair")
    model = shipped_model("flair")
    one = model_identity("flair", model, nets[0])
    ensemble_of_one = model_identity("flair", model, nets[:1])
    assert one["cnn_sha256"] == [nets[0].sha256] == ensemble_of_one["cnn_sha256"]


@pytest.mark.parametrize("method", ["robust", "learned", "paper"])
def test_the_detection_in_memory_segments_as_the_stored_one(case, method):
    """segment_detected (tumor3d.reconstruct's entry) and segment_patient (the stage's, from
    the stored records) give the same mask, table and values."""
    cfg = SegmentConfig(method=method, learned_cnn="off").model_dump()
    inputs = case["inputs"]
    stored = segment_patient(
        **inputs, lesion_mask=lambda: case["lesion"], image=lambda: case["scan"].image, **cfg
    )
    det = case["det"] if method != "paper" else replace(case["det"], lesion=None)
    memory = segment_detected(
        inputs["enhanced"], inputs["brain_mask"], det, affine=inputs["affine"],
        modality="flair", spacing_mm=inputs["spacing_mm"], lesion=LesionConfig().model_dump(),
        head_exterior=inputs["head_exterior"], image=lambda: case["scan"].image, **cfg,
    )  # fmt: skip
    assert memory.result.method == stored.result.method
    assert np.array_equal(memory.result.tumor_mask, stored.result.tumor_mask)
    assert memory.records == stored.records and memory.values == stored.values

"""tumor3d.segmentation.review: one rule decides ok / check / failed and the reasons."""

from __future__ import annotations

import pytest

from tumor3d.segmentation.review import STATUSES, review_status, segmentation_review


def test_no_doubt_is_ok_and_needs_no_review():
    r = review_status([], segmentation={"segment_method": "robust", "caveats": []})
    assert (r.status, r.needs_review, r.reasons, r.quality_score) == ("ok", False, (), None)


def test_any_caveat_is_check_with_that_caveat_as_reason():
    caveat = "the brain mask (2,886 mL) is larger than any skull holds: unreliable"
    r = review_status([caveat, "  "])
    assert r.status == "check" and r.needs_review and r.reasons == (caveat,)


def test_the_segmentation_stage_can_ask_for_review_with_its_own_reasons_and_score():
    seg = {"needs_review": True, "review_reasons": ["low ensemble agreement"],
           "quality_score": 0.31}  # fmt: skip
    r = review_status(["tumour on the last slice of the scan"], segmentation=seg)
    assert r.status == "check"
    assert r.reasons == ("tumour on the last slice of the scan", "low ensemble agreement")
    assert r.quality_score == pytest.approx(0.31)
    # a flag without words still says why, with the score
    r = review_status([], segmentation={"needs_review": True, "quality_score": 0.2})
    assert r.status == "check" and r.reasons == ("the segmentation asks for review "
                                                 "(quality score 0.20)",)  # fmt: skip
    # words without a flag (a method of the API's that gives only its reasons) are a doubt;
    # an explicit False keeps them as information
    r = review_status([], segmentation={"review_reasons": ["thin rim"]})
    assert r.status == "check" and r.reasons == ("thin rim",)
    r = review_status([], segmentation={"needs_review": False, "review_reasons": ["thin rim"]})
    assert r.status == "ok"


def test_a_confident_segmentation_keeps_ok_and_its_score():
    r = review_status([], segmentation={"needs_review": False, "quality_score": 0.93,
                                        "review_reasons": []})  # fmt: skip
    assert r.status == "ok" and r.quality_score == pytest.approx(0.93)
    assert segmentation_review(None) == (False, [], None)
    assert segmentation_review({"quality_score": float("nan")}) == (False, [], None)


def test_an_error_is_failed_whatever_else_is_said():
    r = review_status(["a caveat"], error="InputError: no brain found")
    assert r.status == "failed" and r.reasons == ("InputError: no brain found",)
    assert STATUSES == ("ok", "check", "failed")


@pytest.mark.parametrize("bad", [{"needs_review": "yes"}, {"review_reasons": [3]}])
def test_malformed_segmentation_values_are_refused(bad):
    with pytest.raises(TypeError):
        review_status([], segmentation=bad)

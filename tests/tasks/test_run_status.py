"""A run's status from its stages' values: which notes doubt the result (issue 28 item 5).

The brain mask's notes doubt the volume of a mask that lies inside the brain mask (the
robust, paper and multi-Otsu methods, a given segmentation); the learned method reads
the whole head's tissue, so for it they only inform. No tumour found always doubts.
"""

from __future__ import annotations

import pytest

from tumor3d.segmentation.review import review_status
from tumor3d.tasks.publish import run_notes, run_review
from tumor3d.tasks.spec import StageOutput

# a brain mask on 3 of the 30 slices that hold tissue (tumor3d.imaging.preprocess.notes)
LOST_BRAIN = {"brain_volume_ml": 1200.0, "brain_slices": 3, "tissue_slices": 30}


def _outputs(method: str, faces: int = 120) -> dict[str, StageOutput]:
    values = {
        "ingest-scan": {},
        "preprocess": {**LOST_BRAIN, "brain_extraction": "skull_strip"},
        "segment-tumor": {"caveats": [], "segment_method": method},
        "extract-surface": {"faces": faces},
    }
    return {k: StageOutput(stage=k, values=v) for k, v in values.items()}


@pytest.mark.parametrize(
    ("method", "doubted"), [("robust", True), ("paper", True), ("given", True), ("learned", False)]
)
def test_the_brain_mask_notes_doubt_only_a_mask_inside_the_brain_mask(method, doubted):
    notes, doubts = run_notes(_outputs(method))
    lost = [n for n in notes if n.startswith("brain mask on 3 of the 30 slices")]
    assert len(lost) == 1  # said to everyone
    assert (lost[0] in doubts) is doubted
    # worded for what it doubts: the result, or (read from the whole head) the brain surface
    assert (
        "the result (a tumour volume, or no tumour found) is not reliable" in lost[0]
    ) is doubted
    assert ("is not confined to this mask" in lost[0]) is not doubted
    status = review_status(doubts, segmentation={"needs_review": False}).status
    assert status == ("check" if doubted else "ok")


def test_no_tumour_found_doubts_whatever_the_method():
    for method in ("robust", "learned"):
        notes, doubts = run_notes(_outputs(method, faces=0))
        assert doubts and doubts[0].startswith("no tumour found: confirm") and notes[0] == doubts[0]


def test_a_voxel_size_no_brain_can_have_doubts_every_method():
    """A brain under 20 cm2 on every slice: the header's voxel size is off, so every
    volume is, whichever method read the head."""
    for method in ("robust", "learned"):
        outputs = _outputs(method)
        outputs["preprocess"].values.update(brain_max_slice_mm2=150.0, brain_slices=30)
        notes, doubts = run_notes(outputs)
        (size,) = [n for n in notes if n.startswith("brain mask of at most 1.5 cm2")]
        assert size in doubts


def test_a_default_modality_is_said_in_the_notes_and_asks_for_a_check():
    """Issue 28 item 4: the modality is never assumed silently. The report and metrics
    say a default one (the console says it at the start), and the status asks for a check:
    the sequence decides what is segmented (a user audit: a FLAIR run without --modality
    was segmented as T2, twice its tumour's volume, with status ok)."""
    outputs = _outputs("robust")
    outputs["segment-tumor"].values["modality"] = "t2"
    notes, doubts = run_notes(outputs, modality_default=True)
    (said,) = [n for n in notes if n.startswith("modality: t2 by default")]
    assert "give the modality if the scan is not T2" in said and said in doubts
    assert run_review(outputs, doubts).status == "check"
    named, named_doubts = run_notes(outputs)
    assert not [n for n in named if n.startswith("modality:")]
    assert named_doubts == [d for d in doubts if d != said]  # the modality's doubt alone


def test_the_review_adds_the_segmentations_own_reasons_to_the_doubts():
    outputs = _outputs("learned")
    _, doubts = run_notes(outputs)
    assert run_review(outputs, doubts).status == "ok" and doubts == []
    outputs["segment-tumor"].values.update(
        needs_review=True, review_reasons=["low confidence inside the lesion"], quality_score=0.4
    )
    review = run_review(outputs, ["tumour on the last slice of the scan"])
    assert review.status == "check" and review.quality_score == 0.4
    assert review.reasons == (
        "tumour on the last slice of the scan",
        "low confidence inside the lesion",
    )

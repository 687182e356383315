"""A run's status: ``ok``, ``check`` or ``failed``, and the reasons a human should look.

One rule, used everywhere a status is shown (console, ``metrics.parquet``,
the cohort table, ``cohort.html``, ``cohort.md``, ``report.html``, the
evaluation's ``evaluation.parquet`` and ``REPORT.md``, and the command's exit
code):

* ``failed`` -- the run did not complete (an error);
* ``check`` -- it completed, but the tool's own checks doubt the result: a
  caveat of the segmentation (:mod:`tumor3d.segmentation.caveats`; the midline
  caveat informs, :data:`INFORMING_CAVEATS`), a brain mask
  too small to be a human brain (the header's voxel size), a brain mask whose
  volume or coverage says the skull removal failed (for a method whose mask lies
  inside it: :func:`tumor3d.segmentation.methods.brain_mask_doubts_volume`), input
  files skipped as unreadable, or a segmentation method that asks for review itself
  (``needs_review`` with ``review_reasons`` and ``quality_score`` in the
  segment-tumor stage's values), or no tumour found (no method can tell a
  tumour it missed from none: a scan sent to be measured asks a human to
  confirm that there is none);
* ``ok`` -- it completed and nothing asks for a human. Informational notes
  (a brain mask or a segmentation given by the user) do not change it.

A result is never ``ok`` when the tool itself doubts it.

The function is pure: words and flags in, a :class:`Review` out.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

__all__ = [
    "INFORMING_CAVEATS",
    "MIDLINE_CAVEAT_START",
    "NO_TUMOUR_NOTE",
    "ORIENTATION_UNSTATED",
    "STATUSES",
    "STATUS_CHECK",
    "STATUS_FAILED",
    "STATUS_OK",
    "Review",
    "brain_mask_run_notes",
    "review_status",
    "run_notes",
    "segmentation_review",
]

STATUS_OK = "ok"
STATUS_CHECK = "check"
STATUS_FAILED = "failed"
#: Every status, from best to worst.
STATUSES = (STATUS_OK, STATUS_CHECK, STATUS_FAILED)

#: The words of the reader's note on an input whose NIfTI header states no orientation
#: (``sform_code`` and ``qform_code`` 0, an Analyze-style header): nibabel then assumes
#: its default axes, so which side is left and which is front is a guess, and the
#: learned method may read the head mirrored. Among a run's header notes, it doubts.
ORIENTATION_UNSTATED = "the NIfTI header states no orientation (sform and qform codes 0)"

#: The note of a run that found no tumour: a doubt (the status is ``check``), since
#: an empty result on a scan sent to be measured cannot tell a missed tumour from none.
NO_TUMOUR_NOTE = (
    "no tumour found: confirm on the slices that there is none (no mesh and no render written)"
)


@dataclass(frozen=True)
class Review:
    """A run's status and why.

    Parameters
    ----------
    status : {"ok", "check", "failed"}
    reasons : tuple of str
        Why a human should look (``check``) or what went wrong (``failed``);
        empty for ``ok``.
    quality_score : float or None
        The segmentation's own quality score, when its method gives one.
    """

    status: str
    reasons: tuple[str, ...] = ()
    quality_score: float | None = None

    @property
    def needs_review(self) -> bool:
        """True unless the status is ``ok``."""
        return self.status != STATUS_OK


#: How the robust method's midline caveat begins
#: (:func:`tumor3d.segmentation.caveats.midline_caveat`).
MIDLINE_CAVEAT_START = "tumour reaches the brain's midline"
#: Caveats shown in the notes that do not doubt the volume, by the words they start
#: with: the midline caveat. Out of fold (``benchmarks/learned_cv.py --method robust``,
#: the 76 real cases of every group) it named 14 of the 41 volumes off by more than 25 %
#: and 9 of the 19 within 10 %, and a mask it named was less often short by more than
#: 25 % (3 of 28) than one it did not name (18 of 48): no sign of the far part it says
#: may be missing (``reports/learned_cv.md``, "When to check: the review,
#: cross-validated"; the rule was chosen on those rows, not nested). The learned method
#: does not say it (``learned_caveats``).
INFORMING_CAVEATS = (MIDLINE_CAVEAT_START,)


def _words(items: Iterable[Any] | str | None, name: str) -> list[str]:
    if items is None:
        return []
    if isinstance(items, str):
        items = [items]
    out = []
    for item in items:
        if not isinstance(item, str):
            raise TypeError(f"{name} must be strings, got {type(item).__name__}")
        if item.strip():
            out.append(item.strip())
    return out


def segmentation_review(values: Mapping[str, Any] | None) -> tuple[bool, list[str], float | None]:
    """What a segmentation method says about its own result.

    Reads ``needs_review`` (bool), ``review_reasons`` (list of str) and
    ``quality_score`` (float) from the segment-tumor stage's values; absent
    keys mean no doubt and no score.

    Examples
    --------
    >>> segmentation_review({"segment_method": "robust"})
    (False, [], None)
    >>> segmentation_review({"needs_review": True, "quality_score": 0.4})
    (True, ['the segmentation asks for review (quality score 0.40)'], 0.4)
    """
    if not values:
        return False, [], None
    flag = values.get("needs_review")
    if flag is not None and not isinstance(flag, bool):
        raise TypeError(f"needs_review must be a bool, got {type(flag).__name__}")
    score = values.get("quality_score")
    score = None if score is None else float(score)
    if score is not None and score != score:  # NaN: no score
        score = None
    reasons = _words(values.get("review_reasons"), "review_reasons")
    if flag and not reasons:
        said = "" if score is None else f" (quality score {score:.2f})"
        reasons = [f"the segmentation asks for review{said}"]
    return bool(flag) or bool(flag is None and reasons), reasons, score


def review_status(
    caveats: Iterable[str] | None = (),
    *,
    segmentation: Mapping[str, Any] | None = None,
    error: str | None = None,
) -> Review:
    """Decide a run's status from the doubts its checks raised.

    Parameters
    ----------
    caveats : iterable of str
        The run's doubts in words (:func:`run_notes`' second list): no tumour
        found, segmentation caveats, the brain-mask notes that doubt, skipped
        files. Informational notes are not passed here.
    segmentation : mapping, optional
        The segment-tumor stage's values; its ``needs_review``,
        ``review_reasons`` and ``quality_score`` are read when present
        (:func:`segmentation_review`).
    error : str, optional
        The run failed with this one-line error: status ``failed``.

    Returns
    -------
    Review

    Examples
    --------
    >>> review_status([]).status
    'ok'
    >>> r = review_status(["tumour on the last slice of the scan"])
    >>> r.status, r.needs_review, r.reasons
    ('check', True, ('tumour on the last slice of the scan',))
    >>> review_status([], segmentation={"needs_review": False, "quality_score": 0.9}).status
    'ok'
    >>> review_status(error="InputError: no brain").status
    'failed'
    """
    doubts = _words(caveats, "caveats")
    flagged, seg_reasons, score = segmentation_review(segmentation)
    if error is not None:
        return Review(STATUS_FAILED, tuple(_words(error, "error") or ["failed"]), score)
    reasons = doubts + [r for r in seg_reasons if r not in doubts] if flagged else doubts
    return Review(STATUS_CHECK if reasons else STATUS_OK, tuple(reasons), score)


def run_notes(
    *,
    tumour_found: bool,
    caveats: Iterable[str] = (),
    skipped_files: Iterable[str] = (),
    brain_mask_note: str | None = None,
    brain_notes: Iterable[str] = (),
    brain_doubts: bool = True,
    scale_notes: Iterable[str] = (),
    header_notes: Iterable[str] = (),
    slice_order_note: str | None = None,
) -> tuple[list[str], list[str]]:
    """A run's notes, in their fixed order, and those of them that doubt the result.

    Every note is shown (summary, metrics, provenance, report); the doubts
    (no tumour found, segmentation caveats, files skipped as unreadable, notes
    on the brain mask's size or coverage) are :func:`review_status`'s
    ``caveats``. "Brain mask given" informs; it does not doubt; nor does a
    caveat of :data:`INFORMING_CAVEATS` (the midline caveat). The notes on
    the skull removal (``brain_notes``) doubt only a mask that lies inside the
    brain mask (``brain_doubts``:
    :func:`tumor3d.segmentation.methods.brain_mask_doubts_volume` of the method
    that ran); for one read from the whole head they inform (worded so by
    :func:`tumor3d.imaging.preprocess.brain_mask_notes`). ``scale_notes``
    (a voxel size in the header that cannot be right) doubt every volume.
    ``header_notes`` (the reader's notes on the input's header) inform, except one
    that the header states no orientation (:data:`ORIENTATION_UNSTATED`), which
    doubts; ``slice_order_note`` (which end the slice numbers count from) informs.

    Returns
    -------
    notes, doubts : list of str

    Examples
    --------
    >>> notes, doubts = run_notes(tumour_found=False, brain_mask_note="brain mask given (m.nii)")
    >>> [n[:15] for n in notes], [d[:15] for d in doubts]
    (['no tumour found', 'brain mask give'], ['no tumour found'])
    >>> run_notes(tumour_found=True, brain_mask_note="brain mask given (m.nii)")
    (['brain mask given (m.nii)'], [])
    >>> run_notes(tumour_found=True, caveats=["tumour on the last slice of the scan",
    ...                                       "tumour reaches the brain's midline on slice 4"])[1]
    ['tumour on the last slice of the scan']
    >>> run_notes(tumour_found=True, brain_notes=["brain mask on 3 of 30 slices"])
    (['brain mask on 3 of 30 slices'], ['brain mask on 3 of 30 slices'])
    >>> run_notes(tumour_found=True, brain_notes=["brain mask on 3 of 30 slices"],
    ...           brain_doubts=False)
    (['brain mask on 3 of 30 slices'], [])
    """
    caveat_list = _words(caveats, "caveats")
    skipped = [str(f) for f in skipped_files]
    skipped_note = (
        [f"skipped {len(skipped)} unreadable file(s): {', '.join(skipped)}"] if skipped else []
    )
    brain = _words(brain_notes, "brain_notes")
    none = [] if tumour_found else [NO_TUMOUR_NOTE]
    notes = none + caveat_list + skipped_note
    if brain_mask_note:
        notes.append(brain_mask_note)
    scale = _words(scale_notes, "scale_notes")
    header = _words(header_notes, "header_notes")
    notes += brain + scale + header + ([slice_order_note] if slice_order_note else [])
    doubting = [c for c in caveat_list if not c.startswith(INFORMING_CAVEATS)]
    unstated = [n for n in header if ORIENTATION_UNSTATED in n]
    return notes, (
        none + doubting + skipped_note + (brain if brain_doubts else []) + scale + unstated
    )


def brain_mask_run_notes(figures: Mapping[str, Any], method: str | None) -> dict[str, Any]:
    """:func:`run_notes`' keywords on the brain mask of a run of segmentation ``method``.

    The notes of :func:`tumor3d.imaging.preprocess.brain_mask_notes` on the mask's
    ``figures`` (the preprocess stage's values,
    :func:`tumor3d.imaging.preprocess.brain_mask_figures`): those on the skull removal
    (``brain_notes``), worded for and doubting only a method whose mask lies inside the
    brain mask (``brain_doubts``:
    :func:`tumor3d.segmentation.methods.brain_mask_doubts_volume`), and that on the
    voxel size (``scale_notes``), which doubts every volume.

    >>> kw = brain_mask_run_notes({"brain_volume_ml": 3257.0}, "learned")
    >>> kw["brain_doubts"], [n[:22] for n in kw["brain_notes"]], kw["scale_notes"]
    (False, ['brain mask of 3257 mL:'], [])
    >>> run_notes(tumour_found=True, **brain_mask_run_notes({"brain_volume_ml": 3257.0},
    ...                                                     "robust"))[1][0][:22]
    'brain mask of 3257 mL:'
    """
    from tumor3d.imaging.preprocess import brain_mask_notes
    from tumor3d.segmentation.methods import brain_mask_doubts_volume

    inside = brain_mask_doubts_volume(method)
    skull, size = brain_mask_notes(figures, doubts_result=inside)
    return {"brain_notes": skull, "brain_doubts": inside, "scale_notes": size}

"""What each method's mask holds, in words, and which method ``auto`` picks."""

from __future__ import annotations

from tumor3d.errors import InputError
from tumor3d.imaging.identity import MODALITIES
from tumor3d.segmentation.detect import SliceDetection, paper_premise_holds
from tumor3d.segmentation.methods import method_names, registered_methods

#: What the robust and learned masks hold (their ``measures`` in the registry).
_WHOLE_TUMOUR = (
    "whole tumour: the {seq}-hyperintense lesion with its enclosed necrotic core "
    "(oedema and non-enhancing tumour included, as the BraTS whole-tumour label)"
)
_SEQUENCE_NAMES = {"flair": "FLAIR", "t2": "T2", "t1c": "T1c"}


def lesion_definition(method: str, modality: str) -> str:
    """What a segmentation method's mask (and so every volume of it) holds, in words.

    The words a volume is reported with (summary, ``metrics.parquet``,
    report): a FLAIR volume of the robust method counts the oedema, a T1c
    one does not. Each method states them when it registers
    (:func:`tumor3d.segmentation.methods.register_method`, ``measures``).

    Parameters
    ----------
    method : str
        A registered method that ran (``"auto"`` resolved, :func:`resolve_method`).
    modality : {"t2", "flair", "t1c"}

    Raises
    ------
    InputError
        For another method or modality (``"auto"`` included: resolve it first).

    Examples
    --------
    >>> lesion_definition("robust", "t1c")
    'enhancing tumour: the contrast-enhancing lesion with its enclosed necrotic core (no oedema)'
    """
    mod = modality.strip().lower() if isinstance(modality, str) else modality
    if mod not in _SEQUENCE_NAMES:
        raise InputError(f"unknown modality {modality!r}: expected one of {MODALITIES}")
    spec = registered_methods().get(method) if isinstance(method, str) else None
    text = None if spec is None else (spec.measures.get(mod) or spec.measures.get(None))
    if text is None:
        raise InputError(
            f"no definition for method {method!r}: expected one of "
            f"{', '.join(method_names(auto=False))}"
        )
    return text.format(seq=_SEQUENCE_NAMES[mod])


def resolve_method(
    method: str, modality: str | None, detection: SliceDetection | None = None
) -> str:
    """``"auto"`` -> ``"learned"`` on FLAIR and T1c; on T2 ``"paper"`` where its premise holds.

    The learned method on FLAIR and T1c because it beats the robust one by
    cross-validation by patient (``reports/learned_cv.md``, the figures as
    shipped: 3-D Dice 0.787 against 0.479 on the 45 clinical LGG FLAIR heads,
    0.833 against 0.819 on BraTS FLAIR; T1c 0.639 against 0.615 with 5
    volumes within 10 % against 3); on the BraTS T2 cases it does not (0.723
    against 0.747), so T2 keeps the rule below.

    On T2, ``"paper"`` when the detection's histograms show the three tissue
    modes the paper assumes on nearly every slice
    (:func:`tumor3d.segmentation.detect.paper_premise_holds`), otherwise ``"robust"``;
    ``"paper"`` for an unknown modality or without a detection. Measured
    (``reports/segmentation.md``): on the T2 phantoms (three modes on every
    slice) the paper's method is exact and the robust one over-segments the
    thick-slice tips (+4 % Eq. 9 on average); on the real T2 case (three
    modes on 48 % of the slices) the paper's method finds a third of the
    tumour (3-D Dice 0.26) and the robust one 0.89.
    """
    if method != "auto":
        return method
    mod = modality.strip().lower() if isinstance(modality, str) else None
    if mod in ("flair", "t1c"):
        return "learned"
    if mod == "t2" and detection is not None:
        premise = paper_premise_holds(detection.n_modes, detection.brain_pixels)
        return "paper" if premise else "robust"
    return "paper"

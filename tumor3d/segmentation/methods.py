"""The registry of segmentation methods (``segment.method``).

A *method* is a function ``fn(enhanced, brain_mask, detection, **keywords) ->
SegmentationResult``: the enhanced slices ``J``, their brain mask and the
detection of section 2 in, the tumour mask out. It names, as keyword-only
parameters, the keywords of :func:`tumor3d.segmentation.segment.segment_tumor`
it uses (the context: ``modality``, ``spacing_mm``, ``lr_axis``,
``head_exterior``, ``lesion``, ``image``, ``model``; and the ``segment``
configuration's fields: ``min_tumor_pixels``, ...); the dispatcher passes
those and no other.

Adding a method = one function and one decorator:

1. in a module listed in :data:`METHOD_MODULES` (or a new one added there)::

       from tumor3d.segmentation.methods import register_method

       @register_method(
           "kmeans",
           description="k-means of the brain gray levels, brightest cluster",
           measures="the brightest k-means cluster of the brain on {seq}",
       )
       def segment_kmeans(enhanced, brain_mask, detection, *, modality, min_tumor_pixels):
           ...
           return SegmentationResult(...)

The configuration (:class:`tumor3d.config.SegmentConfig`) accepts ``"auto"``
and every registered name and refuses another one, listing them; the
``segment-tumor`` stage, :func:`tumor3d.segmentation.segment.lesion_definition`
(the words a volume is reported with), ``tumor3d methods`` and the README's
table read the same registry. ``"auto"`` is not a method but the rule that
picks one (:func:`tumor3d.segmentation.segment.resolve_method`).
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.imaging.identity import MODALITIES

__all__ = [
    "AUTO",
    "METHOD_MODULES",
    "SegmentMethod",
    "check_method_name",
    "method_names",
    "method_spec",
    "method_uses_lesion",
    "register_method",
    "slices_flagged",
    "brain_mask_doubts_volume",
    "registered_methods",
]

#: Modules whose import registers segmentation methods; add one line per new module.
METHOD_MODULES: tuple[str, ...] = ("tumor3d.segmentation.segment",)

#: The configuration's choice that is the rule picking a method, not a method.
AUTO = "auto"


@dataclass(frozen=True)
class SegmentMethod:
    """A registered segmentation method.

    Attributes
    ----------
    name : str
        ``segment.method`` value, also ``SegmentationResult.method`` and
        ``segment_method`` in ``metrics.parquet``.
    description : str
        One line for ``tumor3d methods``, the configuration's schema and the README.
    fn : callable
        ``fn(enhanced, brain_mask, detection, **keywords) -> SegmentationResult``.
    measures : mapping of str or None to str
        What its mask (every volume of it) holds, in words, by modality
        (``None``: any modality); ``{seq}`` becomes the sequence's name.
    modalities : tuple of str
        The sequences it segments; another one is refused before it runs.
    uses_lesion : bool
        It reuses the patient lesion model the detect stage computes
        (``SliceDetection.lesion``): the adapter then loads it.
    needs_model : bool
        It needs the acquired image and the shipped model of the modality
        (keywords ``image`` and ``model``): the adapter then loads them.
    within_brain_mask : bool
        Its mask lies inside the brain mask (it segments the skull-stripped
        brain), so a doubtful brain mask doubts its volume: the brain mask's
        notes then make the status ``check``
        (:func:`tumor3d.segmentation.review.run_notes`). False for a method
        that reads the whole head (the learned one): the notes only inform.
    within_detection : bool
        It segments only the slices the detection flags abnormal (robust,
        paper), so those flags are its slice verdict. False for a method that
        reads every slice (learned, multiotsu): the slices it flags are those
        its mask holds tumour on (:func:`slices_flagged`).
    keywords : frozenset of str
        The keywords ``fn`` takes (read from its signature).
    """

    name: str
    description: str
    fn: Callable[..., Any]
    measures: Mapping[str | None, str]
    modalities: tuple[str, ...] = MODALITIES
    uses_lesion: bool = False
    needs_model: bool = False
    within_brain_mask: bool = True
    within_detection: bool = True
    keywords: frozenset[str] = frozenset()
    takes_any: bool = False

    def arguments(self, keywords: Mapping[str, Any]) -> dict[str, Any]:
        """The keywords of ``keywords`` that :attr:`fn` takes."""
        if self.takes_any:
            return dict(keywords)
        return {k: v for k, v in keywords.items() if k in self.keywords}


_REGISTRY: dict[str, SegmentMethod] = {}


def _keywords(fn: Callable[..., Any]) -> tuple[frozenset[str], bool]:
    """The keyword-only parameter names of ``fn`` and whether it takes ``**kwargs``."""
    params = inspect.signature(fn).parameters.values()
    names = frozenset(p.name for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY)
    return names, any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params)


def register_method(
    name: str,
    *,
    description: str,
    measures: str | Mapping[str | None, str],
    modalities: tuple[str, ...] = MODALITIES,
    uses_lesion: bool = False,
    needs_model: bool = False,
    within_brain_mask: bool = True,
    within_detection: bool = True,
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator registering a segmentation method under ``name``.

    Parameters
    ----------
    name : str
        Unique lower-case name (not ``"auto"``); re-registering the same
        function is a no-op.
    description : str
        One line: what the method is.
    measures : str or mapping
        What its mask holds, in words (``{seq}`` = the sequence's name), or a
        mapping modality -> words (key ``None``: the other modalities).
    modalities : tuple of str
        Sequences it segments (default all of :data:`tumor3d.imaging.scan.MODALITIES`).
    uses_lesion, needs_model, within_brain_mask, within_detection : bool
        See :class:`SegmentMethod`.

    Raises
    ------
    InputError
        A name that is empty, ``"auto"``, not lower case, or already taken
        by another function; a modality that is not known.
    """
    if not isinstance(name, str) or not name or name != name.strip().lower() or name == AUTO:
        raise InputError(
            f"a segmentation method's name must be a non-empty lower-case string other "
            f"than {AUTO!r}, got {name!r}"
        )
    unknown = [m for m in modalities if m not in MODALITIES]
    if unknown or not modalities:
        raise InputError(
            f"method {name!r}: modalities must be some of {', '.join(MODALITIES)}, "
            f"got {modalities!r}"
        )
    words = {None: measures} if isinstance(measures, str) else dict(measures)

    def deco(fn: Callable[..., Any]) -> Callable[..., Any]:
        old = _REGISTRY.get(name)
        if old is not None and old.fn.__qualname__ != fn.__qualname__:
            raise InputError(f"a segmentation method named {name!r} is already registered")
        keywords, takes_any = _keywords(fn)
        _REGISTRY[name] = SegmentMethod(
            name=name,
            description=description,
            fn=fn,
            measures=MappingProxyType(words),
            modalities=tuple(modalities),
            uses_lesion=bool(uses_lesion),
            needs_model=bool(needs_model),
            within_brain_mask=bool(within_brain_mask),
            within_detection=bool(within_detection),
            keywords=keywords,
            takes_any=takes_any,
        )
        return fn

    return deco


def registered_methods() -> dict[str, SegmentMethod]:
    """Every method, after importing :data:`METHOD_MODULES` (name -> SegmentMethod)."""
    for module in METHOD_MODULES:
        importlib.import_module(module)
    return dict(_REGISTRY)


def method_names(*, auto: bool = True) -> tuple[str, ...]:
    """The values ``segment.method`` accepts, sorted, ``"auto"`` first.

    >>> method_names()
    ('auto', 'learned', 'multiotsu', 'paper', 'robust')
    """
    names = tuple(sorted(registered_methods()))
    return ((AUTO,) if auto else ()) + names


def check_method_name(method: Any) -> str:
    """``method`` if it is ``"auto"`` or a registered method; else an error naming them.

    >>> check_method_name("paper")
    'paper'
    >>> try:
    ...     check_method_name("kmeans")
    ... except InputError as exc:
    ...     print(exc.problem)
    unknown segmentation method 'kmeans': expected one of auto, learned, multiotsu, paper, robust
    """
    if method == AUTO or (isinstance(method, str) and method in registered_methods()):
        return method
    raise InputError(
        f"unknown segmentation method {method!r}: expected one of {', '.join(method_names())}"
    )


def method_spec(method: str) -> SegmentMethod:
    """The registered method ``method`` (``"auto"`` resolved first), or an error naming them."""
    spec = registered_methods().get(method) if isinstance(method, str) else None
    if spec is None:
        check_method_name(method)  # raises, naming the registered ones
        raise InputError(f"{method!r} is the rule that picks a method: resolve it first")
    return spec


def slices_flagged(method: str, detected: Any, tumor_pixels: Any) -> np.ndarray:
    """The acquired slices the segmentation ``method`` flags abnormal, ``(z,)`` bool.

    A method that segments the slices the detection flags (robust, paper) flags
    those (``detected``); one that reads every slice (learned, multiotsu; a
    given mask, ``"given"``, or any name not registered) flags the slices its
    mask holds tumour on (``tumor_pixels > 0``): the detection did not find its
    tumour, so its flags would contradict the mask (0 slices flagged abnormal
    beside 52 with tumour). Eq. 7, the overlay's frames and ``n_abnormal_slices``
    read this.

    >>> slices_flagged("robust", [False, True, True], [0, 3, 0]).tolist()
    [False, True, True]
    >>> slices_flagged("learned", [False, False, True], [4, 3, 0]).tolist()
    [True, True, False]
    """
    detected = np.asarray(detected, dtype=bool)
    tumour = np.asarray(tumor_pixels) > 0
    if detected.shape != tumour.shape:
        raise InputError(
            f"the detection has {detected.shape} slices but the segmentation {tumour.shape}"
        )
    spec = registered_methods().get(method) if isinstance(method, str) else None
    return detected if spec is not None and spec.within_detection else tumour


def method_uses_lesion(method: str) -> bool:
    """Whether ``method`` may reuse the detect stage's lesion model (``"auto"``: it may).

    An adapter loads the lesion model for the segmentation only then.

    >>> method_uses_lesion("robust"), method_uses_lesion("paper"), method_uses_lesion("auto")
    (True, False, True)
    """
    if method == AUTO:
        return any(m.uses_lesion for m in registered_methods().values())
    return method_spec(method).uses_lesion


def brain_mask_doubts_volume(method: str) -> bool:
    """Whether the brain mask's notes doubt the volume of ``method``'s mask.

    True for a registered method whose mask lies inside the brain mask
    (:attr:`SegmentMethod.within_brain_mask`) and for any other name (a given
    segmentation, an unknown method: the cautious answer).

    >>> brain_mask_doubts_volume("robust"), brain_mask_doubts_volume("learned")
    (True, False)
    >>> brain_mask_doubts_volume("given")
    True
    """
    spec = registered_methods().get(method) if isinstance(method, str) else None
    return True if spec is None else spec.within_brain_mask

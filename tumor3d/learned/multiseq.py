"""Features of several co-registered sequences of one patient, side by side.

The learned lesion model (:mod:`tumor3d.learned.features`) reads one
sequence. When a patient has several sequences on one grid (FLAIR, T2, T1c
of a BraTS case), each pixel's row can hold every sequence's features: the
first sequence in :data:`SEQUENCE_ORDER` that is given (the *primary*)
contributes all of :data:`~tumor3d.learned.features.FEATURE_NAMES`; each
further sequence adds its intensity and prior columns
(:data:`SEQUENCE_FEATURES`), computed on the primary's tissue so that the
rows are the same pixels. The position, depth and modality columns would
repeat the primary's and are left out.

Nothing here reads a file, and nothing registers images: the sequences must
already share one ``(z, y, x)`` grid (same shape, same spacing); a caller
that reads files checks their affines.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from tumor3d.errors import InputError
from tumor3d.learned.features import (
    FEATURE_NAMES,
    MODALITY_CODES,
    PatientFeatures,
    compute_features,
    tissue_foreground,
)

__all__ = [
    "SEQUENCE_FEATURES",
    "SEQUENCE_ORDER",
    "multiseq_feature_names",
    "order_sequences",
    "sequence_columns",
    "stack_features",
]

#: The order of the sequences in a row; the first one given is the primary.
SEQUENCE_ORDER: tuple[str, ...] = ("flair", "t2", "t1c")

#: Columns of :data:`FEATURE_NAMES` that depend on the sequence's own intensities
#: (or its own prior mask): the ones a further sequence adds.
_SHARED = frozenset(
    {
        "depth_mm",
        "relative_depth",
        "lr_offset",
        "ap_position",
        "z_position",
        "slice_tissue_area",
        "modality",
    }
)
SEQUENCE_FEATURES: tuple[str, ...] = tuple(n for n in FEATURE_NAMES if n not in _SHARED)


def order_sequences(sequences: Iterable[str]) -> tuple[str, ...]:
    """The given sequences, lower-cased, in :data:`SEQUENCE_ORDER`, each once.

    >>> order_sequences(["T1c", "flair"])
    ('flair', 't1c')
    """
    seqs = [str(s).strip().lower() for s in sequences]
    unknown = sorted(set(seqs) - set(SEQUENCE_ORDER))
    if unknown:
        raise InputError(f"unknown sequence(s) {unknown}: expected some of {list(SEQUENCE_ORDER)}")
    if len(set(seqs)) != len(seqs):
        raise InputError(f"a sequence is given twice: {list(sequences)}")
    if not seqs:
        raise InputError("no sequence given")
    return tuple(s for s in SEQUENCE_ORDER if s in seqs)


def multiseq_feature_names(sequences: Iterable[str]) -> tuple[str, ...]:
    """Column names of :func:`stack_features`: ``"<sequence>.<feature>"``.

    >>> names = multiseq_feature_names(["t2", "flair"])
    >>> names[0], names[len(FEATURE_NAMES)], len(names) - len(FEATURE_NAMES)
    ('flair.intensity', 't2.intensity', 19)
    """
    seqs = order_sequences(sequences)
    out = [f"{seqs[0]}.{n}" for n in FEATURE_NAMES]
    for s in seqs[1:]:
        out += [f"{s}.{n}" for n in SEQUENCE_FEATURES]
    return tuple(out)


def sequence_columns() -> np.ndarray:
    """Indices of :data:`SEQUENCE_FEATURES` among :data:`FEATURE_NAMES` (column picks)."""
    return np.array([FEATURE_NAMES.index(n) for n in SEQUENCE_FEATURES], dtype=np.intp)


def stack_features(
    images: Mapping[str, np.ndarray],
    *,
    spacing_mm: tuple[float, float, float],
    lr_axis: int | None = 2,
    priors: Mapping[str, np.ndarray | None] | None = None,
) -> PatientFeatures:
    """The rows of :func:`multiseq_feature_names` for every tissue pixel of the primary.

    Parameters
    ----------
    images : mapping of sequence name to (z, y, x) ndarray
        Co-registered slices of one patient, keys from :data:`SEQUENCE_ORDER`
        (any case), all of one shape.
    spacing_mm : (3,) tuple of float
        The common ``(slice step, row, column)`` spacing, mm.
    lr_axis : {1, 2} or None
        Left-right array axis (see :func:`~tumor3d.learned.features.compute_features`).
    priors : mapping of sequence name to (z, y, x) bool ndarray, optional
        Each sequence's rule-based mask (the robust lesion model's), a
        feature of that sequence's columns; a missing key = an empty prior.

    Returns
    -------
    PatientFeatures
        One row per tissue pixel of the primary sequence, columns
        :func:`multiseq_feature_names` of the given sequences.

    Raises
    ------
    InputError
        Unknown or repeated sequences, shapes that differ, or what
        :func:`~tumor3d.learned.features.compute_features` raises.

    Examples
    --------
    >>> img = np.zeros((3, 48, 48)); img[:, 4:44, 4:44] = 100.0
    >>> f = stack_features({"flair": img, "t2": 2.0 * img}, spacing_mm=(5.0, 1.0, 1.0))
    >>> f.values.shape == (4800, len(multiseq_feature_names(["flair", "t2"])))
    True
    """
    given = {str(k).strip().lower(): v for k, v in images.items()}
    seqs = order_sequences(given)
    pri = {str(k).strip().lower(): v for k, v in (priors or {}).items()}
    extra = sorted(set(pri) - set(seqs))
    if extra:
        raise InputError(f"prior(s) given for sequence(s) {extra} without an image")
    arrays = {s: np.asarray(given[s]) for s in seqs}
    shape0 = arrays[seqs[0]].shape
    for s in seqs[1:]:
        if arrays[s].shape != shape0:
            raise InputError(
                f"the {s} slices have shape {arrays[s].shape}, the {seqs[0]} slices "
                f"{shape0}: the sequences must be co-registered on one grid"
            )
    for s in seqs:
        if s not in MODALITY_CODES:  # pragma: no cover - SEQUENCE_ORDER is a subset
            raise InputError(f"no features for sequence {s!r}")
    first = np.asarray(arrays[seqs[0]])
    if first.ndim != 3:
        raise InputError(f"image must be a 3-D (z, y, x) array, got shape {first.shape}")
    cand = tissue_foreground(first)
    parts = []
    for i, s in enumerate(seqs):
        f = compute_features(
            arrays[s],
            spacing_mm=spacing_mm,
            modality=s,
            lr_axis=lr_axis,
            prior=pri.get(s),
            candidates=cand,
        )
        parts.append(f.values if i == 0 else f.values[:, sequence_columns()])
        if i == 0:
            primary = f
    values = parts[0] if len(parts) == 1 else np.ascontiguousarray(np.hstack(parts))
    return PatientFeatures(values, primary.index, primary.shape, primary.candidates)

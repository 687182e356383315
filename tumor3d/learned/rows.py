"""One labelled patient as training rows of the learned model, and rows as plain bytes.

The training command (``tumor3d train``, :mod:`tumor3d.flows.train`) turns each
labelled patient of a manifest into rows with :func:`patient_rows`: the
features the model sees at inference (:func:`tumor3d.learned.features.
compute_features`, with the robust method's mask of the same slices as the
prior, as :func:`tumor3d.segmentation.segment.segment_tumor` computes it for the learned
method), sampled by :func:`tumor3d.learned.training.sample_rows` with a
generator seeded per patient (so a patient's rows do not depend on which
other patients are trained with it, and a cached stage stays valid).

:func:`rows_to_bytes` / :func:`rows_from_bytes` store rows as an ``.npz``
of three plain arrays, read back with ``allow_pickle=False`` (a shared
store is not trusted). Nothing here reads a file.
"""

from __future__ import annotations

import io
import zipfile

import numpy as np

from tumor3d.errors import InputError
from tumor3d.learned.features import FEATURE_NAMES, compute_features  # noqa: F401 (doctest)
from tumor3d.learned.training import TrainingRows, sample_rows

__all__ = ["ROW_SEED", "patient_rows", "rows_from_bytes", "rows_to_bytes"]

#: Seed of every patient's row sampling (the same for all: a patient's rows
#: depend on that patient alone).
ROW_SEED = 0

#: The most rows one stored patient may hold (the sampler takes at most 16,000).
_MAX_ROWS = 1_000_000


def patient_rows(
    image: np.ndarray,
    reference: np.ndarray,
    *,
    spacing_mm: tuple[float, float, float],
    modality: str,
    lr_axis: int | None,
    prior: np.ndarray | None,
    seed: int = ROW_SEED,
) -> TrainingRows:
    """The training rows of one patient.

    Parameters
    ----------
    image : (z, y, x) ndarray
        The slices as acquired (the scan the pipeline reads).
    reference : (z, y, x) bool ndarray
        The tumour on those slices (the label the model learns).
    spacing_mm : (3,) tuple of float
        ``(slice step, row, column)`` spacing, mm.
    modality : {"flair", "t2", "t1c"}
    lr_axis : int or None
        The left-right voxel axis of ``image`` (symmetry features).
    prior : (z, y, x) bool ndarray or None
        The robust method's mask of these slices (the model's prior features).
    seed : int
        Seed of the row sampling.

    Examples
    --------
    >>> z, y, x = np.ogrid[:6, :48, :48]
    >>> head = ((y - 24) ** 2 + (x - 24) ** 2 < 20**2).astype(np.float32) * 100
    >>> lesion = (z >= 2) & (z <= 3) & ((y - 20) ** 2 + (x - 28) ** 2 < 16)
    >>> image = head + 80 * lesion
    >>> rows = patient_rows(image, lesion, spacing_mm=(5.0, 1.0, 1.0), modality="flair",
    ...                     lr_axis=2, prior=lesion)
    >>> bool(rows.y.any() and not rows.y.all()), rows.x.shape[1] == len(FEATURE_NAMES)
    (True, True)
    """
    feats = compute_features(
        np.asarray(image, dtype=np.float32),
        spacing_mm=spacing_mm,
        modality=modality,
        lr_axis=lr_axis,
        prior=prior,
    )
    return sample_rows(feats, np.asarray(reference, dtype=bool), rng=np.random.default_rng(seed))


def rows_to_bytes(rows: TrainingRows) -> bytes:
    """``rows`` as an uncompressed ``.npz`` of ``x`` (float32), ``y`` (uint8), ``w`` (float32)."""
    buf = io.BytesIO()
    np.savez(
        buf,
        x=np.ascontiguousarray(rows.x, dtype=np.float32),
        y=np.ascontiguousarray(rows.y, dtype=np.uint8),
        w=np.ascontiguousarray(rows.w, dtype=np.float32),
    )
    return buf.getvalue()


def rows_from_bytes(data: bytes, *, source: str = "rows") -> TrainingRows:
    """Rows written by :func:`rows_to_bytes`, checked; never unpickled.

    Raises
    ------
    InputError
        Naming ``source`` when the bytes are not such rows.

    Examples
    --------
    >>> rows = TrainingRows(np.zeros((2, 3), np.float32), np.array([0, 1], np.uint8),
    ...                     np.ones(2, np.float32))
    >>> back = rows_from_bytes(rows_to_bytes(rows))
    >>> back.x.shape, back.y.tolist()
    ((2, 3), [0, 1])
    >>> rows_from_bytes(b"not an npz", source="p1 rows")
    Traceback (most recent call last):
    ...
    tumor3d.errors.InputError: p1 rows: not training rows (not an .npz archive)
    """
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if set(z.files) != {"x", "y", "w"}:
                raise InputError(f"{source}: not training rows (arrays {sorted(z.files)})")
            x, y, w = z["x"], z["y"], z["w"]
    except (ValueError, OSError, zipfile.BadZipFile, EOFError):
        raise InputError(f"{source}: not training rows (not an .npz archive)") from None
    n = y.shape[0] if y.ndim == 1 else -1
    if (
        x.dtype != np.float32
        or y.dtype != np.uint8
        or w.dtype != np.float32
        or x.ndim != 2
        or n < 0
        or x.shape[0] != n
        or w.shape != (n,)
        or n > _MAX_ROWS
    ):
        raise InputError(f"{source}: not training rows (shapes or types do not match)")
    return TrainingRows(x, y, w)

"""What detection returns: the histogram modes of a slice and the per-slice detection."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError
from tumor3d.segmentation.lesion import LesionResult


@dataclass(frozen=True, eq=False)
class HistogramModes:
    """Modes of a gray-level histogram.

    Attributes
    ----------
    n_modes : int
        ``k``, the number of modes after merging.
    peaks_gray : (k,) ndarray of float64
        Peak positions as gray levels (0-255), ascending.
    areas : (k,) ndarray of float64
        Fraction of the histogram mass in each mode; sums to 1 (0 modes: empty).
    """

    n_modes: int
    peaks_gray: np.ndarray
    areas: np.ndarray


def _as_float_vector(a: object) -> np.ndarray:
    out = np.array(a, dtype=np.float64).reshape(-1)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class SliceDetection:
    """Per-slice result of :func:`detect_abnormal_slices`.

    Attributes
    ----------
    n_modes : (z,) ndarray of int64
        ``k`` of each slice.
    abnormal : (z,) ndarray of bool
        ``k >= abnormal_min_modes`` and enough brain pixels [A6].
    peaks_gray : tuple of (k_i,) ndarray of float64
        Peak gray levels of each slice: the FCM seeds of section 3.
    brain_pixels : (z,) ndarray of int64
        Number of brain-mask pixels of each slice.
    lesion : LesionResult or None
        The patient lesion model when the robust method ran (its mask over
        all slices, before the abnormal-slice restriction); reused by
        :func:`tumor3d.segmentation.segment.segment_tumor`'s robust method so that the
        model runs once. Not part of :meth:`to_records`.
    """

    n_modes: np.ndarray
    abnormal: np.ndarray
    peaks_gray: tuple[np.ndarray, ...]
    brain_pixels: np.ndarray
    lesion: LesionResult | None = None

    def __post_init__(self) -> None:
        n_modes = np.array(self.n_modes, dtype=np.int64).reshape(-1)
        abnormal = np.array(self.abnormal, dtype=bool).reshape(-1)
        brain_pixels = np.array(self.brain_pixels, dtype=np.int64).reshape(-1)
        peaks = tuple(_as_float_vector(p) for p in self.peaks_gray)
        nz = n_modes.size
        if not (abnormal.size == brain_pixels.size == len(peaks) == nz):
            raise InputError(
                "SliceDetection fields must all have one entry per slice, got "
                f"{nz} n_modes, {abnormal.size} abnormal, {len(peaks)} peaks_gray, "
                f"{brain_pixels.size} brain_pixels"
            )
        if self.lesion is not None and (
            not isinstance(self.lesion, LesionResult)
            or np.ndim(self.lesion.mask) != 3
            or np.shape(self.lesion.mask)[0] != nz
        ):
            raise InputError(f"SliceDetection.lesion must be a LesionResult with {nz} slices")
        for arr in (n_modes, abnormal, brain_pixels):
            arr.setflags(write=False)
        object.__setattr__(self, "n_modes", n_modes)
        object.__setattr__(self, "abnormal", abnormal)
        object.__setattr__(self, "peaks_gray", peaks)
        object.__setattr__(self, "brain_pixels", brain_pixels)

    def __len__(self) -> int:
        return int(self.n_modes.size)

    def to_records(self) -> list[dict]:
        """One JSON/parquet-friendly row per slice.

        Returns
        -------
        list of dict
            Keys ``slice_index`` (int), ``n_modes`` (int), ``abnormal`` (bool),
            ``peaks_gray`` (list of float) and ``brain_pixels`` (int).
        """
        return [
            {
                "slice_index": z,
                "n_modes": int(self.n_modes[z]),
                "abnormal": bool(self.abnormal[z]),
                "peaks_gray": [float(v) for v in self.peaks_gray[z]],
                "brain_pixels": int(self.brain_pixels[z]),
            }
            for z in range(len(self))
        ]

    @classmethod
    def from_records(cls, records) -> SliceDetection:
        """Rebuild from :meth:`to_records` rows (in any order).

        Parameters
        ----------
        records : iterable of mapping
            Rows with the keys written by :meth:`to_records`; the slice
            indices must be exactly ``0 .. z-1``.

        Returns
        -------
        SliceDetection

        Raises
        ------
        InputError
            On missing keys or slice indices that are not ``0 .. z-1``.
        """
        rows = list(records)
        required = ("slice_index", "n_modes", "abnormal", "peaks_gray", "brain_pixels")
        for row in rows:
            missing = [key for key in required if key not in row]
            if missing:
                raise InputError(f"slice detection record lacks key(s) {missing}")
        rows.sort(key=lambda row: int(row["slice_index"]))
        indices = [int(row["slice_index"]) for row in rows]
        if indices != list(range(len(rows))):
            raise InputError("slice detection records must have slice_index 0 .. z-1 exactly once")
        return cls(
            n_modes=np.array([int(r["n_modes"]) for r in rows], dtype=np.int64),
            abnormal=np.array([bool(r["abnormal"]) for r in rows], dtype=bool),
            peaks_gray=tuple(np.array(list(r["peaks_gray"]), dtype=np.float64) for r in rows),
            brain_pixels=np.array([int(r["brain_pixels"]) for r in rows], dtype=np.int64),
        )

"""The per-slice table published as ``slices.parquet``."""

from __future__ import annotations

import pandas as pd

__all__ = ["slice_table"]


def slice_table(
    detection: pd.DataFrame,
    segmentation: pd.DataFrame,
    *,
    pixel_area_mm2: float,
    slices_reversed: bool = False,
) -> pd.DataFrame:
    """One row per acquired slice: detection's columns, segmentation's, and the tumour area.

    Parameters
    ----------
    detection, segmentation : DataFrame
        The stage tables, each with a ``slice_index`` column; segmentation has
        ``tumor_pixels``.
    pixel_area_mm2 : float
        ``dx * dy`` of the acquired slices.
    slices_reversed : bool
        The input file stores the slices the other way round
        (:attr:`tumor3d.imaging.scan.SourceGrid.flips` of ``z``).

    Returns
    -------
    DataFrame
        Joined on ``slice_index`` (every detection row kept; the working order,
        inferior to superior on an axial stack) plus ``tumor_area_mm2`` = tumour
        pixels x pixel area (0 where missing) and ``file_slice_index``, the
        slice's index in the input file (``slice_index`` unless reversed).

    Examples
    --------
    >>> det = pd.DataFrame({"slice_index": [0, 1], "abnormal": [False, True]})
    >>> seg = pd.DataFrame({"slice_index": [0, 1], "tumor_pixels": [0, 8]})
    >>> slice_table(det, seg, pixel_area_mm2=0.5)["tumor_area_mm2"].tolist()
    [0.0, 4.0]
    >>> slice_table(det, seg, pixel_area_mm2=0.5, slices_reversed=True)["file_slice_index"].tolist()
    [1, 0]
    """
    table = detection.merge(segmentation, on="slice_index", how="left")
    table["tumor_area_mm2"] = table["tumor_pixels"].fillna(0).astype(float) * float(pixel_area_mm2)
    index = table["slice_index"].astype(int)
    table["file_slice_index"] = len(table) - 1 - index if slices_reversed else index
    return table

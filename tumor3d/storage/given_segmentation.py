"""A given tumour segmentation (``tumor3d run --segmentation FILE``, manifest ``segmentation``).

:func:`read_given_segmentation` reads the mask file (the formats of a given
brain mask: NIfTI, NRRD, MetaImage, or a DICOM / image-stack folder, read
by :func:`tumor3d.storage.brain_mask.read_brain_mask_volume`), checks it against its
image with the brain mask's grid rule (same shape, voxel centres within 0.01
voxel: :func:`tumor3d.imaging.brain_mask.check_same_grid`) and returns a
:class:`GivenSegmentation`: the tumour (values > 0.5,
:mod:`tumor3d.segmentation.given_segmentation`) on the Scan's ``(z, y, x)`` grid, with
the file's name and SHA-256 for provenance. Every problem is one
:class:`~tumor3d.errors.InputError` line naming the file. The file is only
read.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.errors import InputError
from tumor3d.imaging.brain_mask import check_same_grid
from tumor3d.imaging.scan import Scan
from tumor3d.segmentation.given_segmentation import binarize_segmentation, given_definition
from tumor3d.storage.brain_mask import brain_mask_sha256, read_brain_mask_volume

__all__ = ["GivenSegmentation", "read_given_segmentation"]

_WHAT = "segmentation"


@dataclass(frozen=True, eq=False)
class GivenSegmentation:
    """A checked tumour segmentation on its image's Scan grid.

    Parameters
    ----------
    path : str
        Absolute path of the file (or folder).
    name : str
        Its name (what provenance and ``measured`` record).
    sha256 : str
        SHA-256 of the file's bytes (of a folder: :func:`tumor3d.storage.inputs.input_digest`).
    mask : ndarray of bool, shape (z, y, x)
        The tumour (values > 0.5), on the image's Scan grid.
    affine : (4, 4) ndarray
        The Scan grid's affine (``(x, y, z, 1)`` -> RAS mm).
    """

    path: str
    name: str
    sha256: str
    mask: np.ndarray
    affine: np.ndarray

    def provenance(self) -> dict[str, Any]:
        """What ``provenance.json`` records: given, file name, SHA-256, tumour voxels."""
        return {
            "given": True,
            "file": self.name,
            "sha256": self.sha256,
            "tumour_voxels": int(np.count_nonzero(self.mask)),
            "rule": "tumour = mask voxels > 0.5; replaces the segment-tumor stage's mask",
            "measured": given_definition(self.name),
        }

    def note(self) -> str:
        """The run's note (summary, ``metrics.parquet``, report): the mask is the user's."""
        return f"segmentation: given ({self.name}, SHA-256 {self.sha256[:12]}...)"


def read_given_segmentation(
    path: str | os.PathLike[str], image: Scan, *, max_voxels: int = MAX_VOXELS_DEFAULT
) -> GivenSegmentation:
    """Read a tumour segmentation file and check it against its image.

    Parameters
    ----------
    path : path
        The mask, on the image's own voxel grid as read.
    image : Scan
        The image, as :func:`tumor3d.storage.readers.read_scan` read it.
    max_voxels : int
        Refuse a mask whose header declares more voxels.

    Raises
    ------
    InputError
        ``"<file>: segmentation: <problem>"``: unreadable, another shape or
        affine than the image's (both named), non-numeric or non-finite values.
    """
    p = Path(path).expanduser()
    values, affine = read_brain_mask_volume(p, max_voxels=max_voxels, what=_WHAT)
    grid = image.source_grid
    try:
        check_same_grid(values.shape, affine, grid.shape, grid.affine)
        tumour = binarize_segmentation(values.transpose(tuple(grid.axes)[::-1]))
    except InputError as exc:
        raise InputError(f"{_WHAT}: {exc.problem}", str(p)) from None
    return GivenSegmentation(
        path=str(p.resolve()), name=p.name, sha256=brain_mask_sha256(p, what=_WHAT),
        mask=np.ascontiguousarray(tumour), affine=np.asarray(image.affine, dtype=np.float64),
    )  # fmt: skip

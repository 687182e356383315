"""A given tumour segmentation (``tumor3d run --segmentation FILE``, manifest ``segmentation``).

:func:`read_given_segmentation` reads the mask file (the formats of a given
brain mask: NIfTI, NRRD, MetaImage, or a DICOM / image-stack folder, read
by :func:`tumor3d.storage.brain_mask.read_mask_on_image_grid`), checks it against its
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
from typing import Any

import numpy as np

from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.imaging.scan import Scan
from tumor3d.segmentation.given_segmentation import binarize_segmentation, given_definition
from tumor3d.storage.brain_mask import GivenMask, read_mask_on_image_grid

__all__ = ["GivenSegmentation", "read_given_segmentation"]

_WHAT = "segmentation"


@dataclass(frozen=True, eq=False)
class GivenSegmentation(GivenMask):
    """A checked tumour segmentation on its image's Scan grid.

    :class:`~tumor3d.storage.brain_mask.GivenMask`; ``mask``: the tumour (values > 0.5),
    ``name``: what provenance and ``measured`` record.
    """

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
    p, tumour = read_mask_on_image_grid(
        path, image, binarize_segmentation, max_voxels=max_voxels, what=_WHAT
    )
    return GivenSegmentation.on_image(p, tumour, image, what=_WHAT)

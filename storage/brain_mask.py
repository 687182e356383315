"""A given brain mask file (``tumor3d run --brain-mask FILE``, manifest column ``brain_mask``).

:func:`read_given_brain_mask` reads the mask file, checks it against its
image (a :class:`tumor3d.imaging.scan.Scan` as the readers made it) and returns a
:class:`GivenBrainMask`: the brain on the Scan's ``(z, y, x)`` grid, ready
for the preprocess stage, with the file's name and SHA-256 for provenance.

The file: a NIfTI (``.nii``, ``.nii.gz``), NRRD or MetaImage file read
without any intensity check (so an all-ones mask is fine), or a DICOM /
image-stack folder read by :func:`tumor3d.storage.readers.read_scan` (which refuses
a constant volume). It must be on the *image's own voxel grid as read*: the
same voxel shape and affine (for a DICOM image, that of its sorted slices;
the published ``brain_mask.nii.gz`` of an earlier run always is). Brain =
voxels > 0.5 (:mod:`tumor3d.imaging.brain_mask`). Every problem is one
:class:`~tumor3d.errors.InputError` line naming the mask file.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

import numpy as np

from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.errors import InputError, os_error_path, os_error_text
from tumor3d.imaging.brain_mask import binarize_brain_mask, check_same_grid
from tumor3d.imaging.scan import Scan
from tumor3d.storage.inputs import input_digest
from tumor3d.storage.readers import ITK_SUFFIXES, read_scan
from tumor3d.storage.readers.common import NIFTI_SUFFIXES
from tumor3d.storage.readers.nifti import load_nifti_volume

__all__ = [
    "GivenBrainMask",
    "GivenMask",
    "brain_mask_sha256",
    "read_brain_mask_volume",
    "read_given_brain_mask",
    "read_mask_on_image_grid",
]

_WHAT = "brain mask"


@dataclass(frozen=True, eq=False)
class GivenMask:
    """A checked mask file on its image's Scan grid: a given brain mask or tumour segmentation.

    Parameters
    ----------
    path : str
        Absolute path of the file (or folder).
    name : str
        Its name (what provenance records, as for the input).
    sha256 : str
        SHA-256 of the file's bytes (of a folder: :func:`tumor3d.storage.inputs.input_digest`).
    mask : ndarray of bool, shape (z, y, x)
        The mask (values > 0.5), on the image's Scan grid.
    affine : (4, 4) ndarray
        The Scan grid's affine (``(x, y, z, 1)`` -> RAS mm).
    """

    path: str
    name: str
    sha256: str
    mask: np.ndarray
    affine: np.ndarray

    @classmethod
    def on_image(cls, path: Path, mask: np.ndarray, image: Scan, *, what: str = _WHAT) -> Self:
        """The checked ``mask`` read from ``path``, on ``image``'s grid (the file hashed here)."""
        return cls(
            path=str(path.resolve()), name=path.name, sha256=brain_mask_sha256(path, what=what),
            mask=np.ascontiguousarray(mask), affine=np.asarray(image.affine, dtype=np.float64),
        )  # fmt: skip


@dataclass(frozen=True, eq=False)
class GivenBrainMask(GivenMask):
    """A checked brain mask on its image's Scan grid (:class:`GivenMask`; ``mask``: the brain)."""

    def provenance(self) -> dict[str, Any]:
        """What ``provenance.json`` records: given, file name, SHA-256, brain voxels."""
        return {
            "given": True,
            "file": self.name,
            "sha256": self.sha256,
            "brain_voxels": int(np.count_nonzero(self.mask)),
            "rule": "brain = mask voxels > 0.5; replaces skull removal",
        }


def _fail(problem: str, where: str | os.PathLike[str], what: str = _WHAT) -> InputError:
    return InputError(f"{what}: {problem}", str(where))


def brain_mask_sha256(path: str | os.PathLike[str], *, what: str = _WHAT) -> str:
    """SHA-256 of a mask file's bytes (a folder: its :func:`~.inputs.input_digest`)."""
    p = Path(path)
    if p.is_dir():
        return input_digest(p)
    h = hashlib.sha256()
    try:
        with open(p, "rb") as fh:
            while chunk := fh.read(1 << 20):
                h.update(chunk)
    except OSError as exc:
        raise _fail(f"cannot read it ({os_error_text(exc)})", os_error_path(exc, p), what) from None
    return h.hexdigest()


def _read_itk_values(p: Path, limit: int) -> tuple[np.ndarray, np.ndarray]:
    import SimpleITK as sitk

    from tumor3d.storage.readers.itk import _read_itk

    kind = "NRRD" if p.name.lower().endswith((".nrrd", ".nhdr")) else "MetaImage"
    shown = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        return _read_itk(sitk, str(p), kind, limit)
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(shown)


def read_brain_mask_volume(
    path: str | os.PathLike[str], *, max_voxels: int = MAX_VOXELS_DEFAULT, what: str = _WHAT
) -> tuple[np.ndarray, np.ndarray]:
    """Read a mask file's values and affine in the file's own voxel order.

    ``what`` names the mask in errors (``"brain mask"``; a given tumour
    segmentation, :mod:`tumor3d.storage.given_segmentation`, says ``"segmentation"``).

    Returns
    -------
    values : ndarray, 3-D
        Voxel values as stored (float32 for NIfTI/NRRD/MetaImage).
    affine : (4, 4) ndarray
        Voxel index -> RAS mm.

    Raises
    ------
    InputError
        ``"<file>: <what>: <problem>"`` for a missing or unreadable
        file, one that is not 3-D (or has fewer than 2 slices), a singular or
        non-finite affine, or more voxels than ``max_voxels``.
    """
    p = Path(path)
    if not p.exists():
        raise _fail("no such file or folder", p, what)
    lower = p.name.lower()
    try:
        if p.is_file() and lower.endswith(NIFTI_SUFFIXES):
            return load_nifti_volume(p, max_voxels)
        if p.is_file() and lower.endswith(ITK_SUFFIXES):
            return _read_itk_values(p, max_voxels)
        scan = read_scan(p, max_voxels=max_voxels, patient_id="brain-mask")
    except InputError as exc:
        if exc.problem.startswith(f"{what}: "):
            raise
        raise _fail(exc.problem, exc.path or p, what) from None
    except OSError as exc:
        raise _fail(f"cannot read it ({os_error_text(exc)})", os_error_path(exc, p), what) from None
    grid = scan.source_grid
    return np.ascontiguousarray(grid.to_source(scan.image)), np.asarray(grid.affine)


def read_given_brain_mask(
    path: str | os.PathLike[str], image: Scan, *, max_voxels: int = MAX_VOXELS_DEFAULT
) -> GivenBrainMask:
    """Read a brain mask file and check it against its image.

    Parameters
    ----------
    path : path
        The mask (see the module docstring for the formats).
    image : Scan
        The image, as :func:`tumor3d.storage.readers.read_scan` read it (its
        ``source_grid`` is the grid the mask must be on).
    max_voxels : int
        Refuse a mask whose header declares more voxels.

    Returns
    -------
    GivenBrainMask

    Raises
    ------
    InputError
        One line naming the mask file: unreadable, another shape or affine
        than the image's (both named), non-finite values, empty, or no
        overlap with the image's non-background.
    """
    p, brain = read_mask_on_image_grid(
        path, image, lambda zyx: binarize_brain_mask(np.ascontiguousarray(zyx), image.image),
        max_voxels=max_voxels,
    )  # fmt: skip
    return GivenBrainMask.on_image(p, brain, image)


def read_mask_on_image_grid(
    path: str | os.PathLike[str],
    image: Scan,
    binarize: Callable[[np.ndarray], np.ndarray],
    *,
    max_voxels: int = MAX_VOXELS_DEFAULT,
    what: str = _WHAT,
) -> tuple[Path, np.ndarray]:
    """Read a given mask file, check that it is on its image's grid, binarize it there.

    The one reading of a given brain mask and of a given tumour segmentation
    (:mod:`tumor3d.storage.given_segmentation`): the file's values
    (:func:`read_brain_mask_volume`), the grid rule
    (:func:`tumor3d.imaging.brain_mask.check_same_grid`: same shape, voxel centres
    within 0.01 voxel) and ``binarize`` applied to the values in the image
    Scan's ``(z, y, x)`` order.

    Returns
    -------
    path : Path
        ``path`` with ``~`` expanded.
    mask : ndarray
        What ``binarize`` returned.

    Raises
    ------
    InputError
        ``"<file>: <what>: <problem>"``: unreadable, another shape or affine
        than the image's (both named), or what ``binarize`` refused.
    """
    p = Path(path).expanduser()
    values, affine = read_brain_mask_volume(p, max_voxels=max_voxels, what=what)
    grid = image.source_grid
    try:
        check_same_grid(values.shape, affine, grid.shape, grid.affine)
        mask = binarize(grid.from_source(values))
    except InputError as exc:
        raise _fail(exc.problem, p, what) from None
    return p, mask

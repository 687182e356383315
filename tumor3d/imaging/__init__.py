"""Imaging: the scan as acquired and its preprocessing (spec sections 1-2).

:mod:`~tumor3d.imaging.scan` (the :class:`Scan` volume and its source grid),
:mod:`~tumor3d.imaging.affine` (the RAS affine: slice spacing, shear, slab height, voxel
to world), :mod:`~tumor3d.imaging.orientation` (the working orientation and the slice
order), :mod:`~tumor3d.imaging.identity` (modalities, patient ids),
:mod:`~tumor3d.imaging.preprocess` (sharpening, equalisation, skull removal),
:mod:`~tumor3d.imaging.brain_extraction` and :mod:`~tumor3d.imaging.brain_mask`
(the brain of a raw head, a given mask checked against the scan).
"""

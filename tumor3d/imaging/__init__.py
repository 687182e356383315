"""Imaging: the scan as acquired and its preprocessing (spec sections 1-2).

:mod:`~tumor3d.imaging.scan` (the :class:`Scan` volume, its grid and RAS affine),
:mod:`~tumor3d.imaging.preprocess` (sharpening, equalisation, skull removal),
:mod:`~tumor3d.imaging.brain_extraction` and :mod:`~tumor3d.imaging.brain_mask`
(the brain of a raw head, a given mask checked against the scan).
"""

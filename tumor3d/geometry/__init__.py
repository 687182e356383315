"""Geometry: from slice masks to a measured surface (spec sections 5-7).

:mod:`~tumor3d.geometry.interpolate` (enhanced shape-based interpolation),
:mod:`~tumor3d.geometry.distance` (its distance transforms),
:mod:`~tumor3d.geometry.surface` (marching cubes), :mod:`~tumor3d.geometry.mesh`
(the triangle mesh in RAS mm), :mod:`~tumor3d.geometry.brain_surface` (the brain's
context surface), :mod:`~tumor3d.geometry.measures` (diameters, Eq. 7 precision).
The paper's simplifier is :mod:`tumor3d.simplify`.
"""

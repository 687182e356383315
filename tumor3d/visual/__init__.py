"""Visual: Phong renders, rotations and cut-aways (spec section 8), and slice overlays.

:mod:`~tumor3d.visual.render` (camera, rasteriser, Open3D scene) and
:mod:`~tumor3d.visual.overlay` (the masks drawn on the acquired slices).
"""

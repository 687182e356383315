r"""Offscreen rendering of a tumour inside its brain (spec section 7, Figures 7, 9, 11, 12).

:func:`render_views` renders, in ONE renderer start, the tumour surface
(opaque) inside an optional translucent brain surface:

* the six anatomical views (``anterior``, ``posterior``, ``right``,
  ``left``, ``superior``, ``inferior``: the camera sits on that side of the
  patient and looks at the scene centre);
* cut-away views (``cut_axial``, ``cut_coronal``, ``cut_sagittal``, the
  paper's Figure 12): the brain (or, without a brain, the tumour) is clipped
  by the plane through the tumour's surface centroid normal to the viewing
  direction; the clipped part on the camera side is removed, the remaining
  brain is drawn opaque and its inner wall, seen through the cut, in a
  darker *interior* colour, so the tumour shows in place;
* a turntable: ``turntable_frames`` views orbiting the superior axis at
  ``turntable_elevation_deg`` (:func:`turntable_gif` encodes them);

and draws orientation labels (R/L, A/P, S/I, from the RAS world directions
of the image edges, not from voxel axes) and a millimetre scale bar onto
every image (Pillow, after rendering, from the known camera geometry).

Projection and cameras
----------------------
All views are **orthographic** and share one scale (pixels per mm), so the
scale bar is exact everywhere in the image and the views can be compared
side by side. The scene is framed on the brain when one is given (else the
tumour): its bounding-box centre ``c`` is the image centre of every view
and the bounding sphere of brain and tumour about ``c`` fits the smaller
image side with the margin ``1 / _FRAME_FILL``. A view is the unit vector ``forward`` along
which the camera looks and the image ``up`` vector; the image right is
``forward x up``. The anterior view looks along ``-A`` with ``+S`` up, so
the patient's right is on the image's left (radiological display); the
right view looks along ``-R``; the superior view looks down (``-S``) with
``+A`` up, the inferior view up with ``+A`` up. A turntable frame at
azimuth ``az`` looks from ``c + (sin az cos el, cos az cos el, sin el)``:
azimuth 0 is the anterior view, 90 the view from the patient's right.
:class:`Camera` maps RAS points to pixel coordinates (``Camera.project``),
which is how the tests locate the tumour and the labels are placed.

Lighting (spec section 7, [A25])
--------------------------------
Vertex normals are the unweighted average of the adjacent face normals
(:func:`vertex_normals`), interpolated per fragment and renormalised (Phong
shading). One white headlight (travelling along ``forward``):

.. math:: I = k_a I_a + I_l [k_d \max(0, N \cdot L) + k_s \max(0, R \cdot V)^s],
          \quad R = 2 (N \cdot L) N - L,

with ``k_a = ambient``, ``k_d = diffuse``, ``k_s = specular``,
``s = shininess`` and ``I_a = I_l = 1``; the diffuse and ambient terms are
multiplied by the surface colour, the specular highlight is white. The
numpy renderer evaluates exactly this formula. Open3D's Filament has no
Phong material: its physically based ``defaultLit`` is set up to match it
(the ambient and diffuse intensities are calibrated to give ``k_a + k_d``
of the base colour on a surface facing the light; roughness
``(2 / (s + 2)) ** 0.25``, the Blinn-Phong/GGX equivalence; reflectance
``0.5 * k_s / 0.3``), so the two renderers agree in layout and closely in
colour, not bit for bit.

Transparency: the brain is blended over what lies behind it with
``opacity``. The numpy renderer blends only the nearest brain layer;
Filament sorts per object, not per triangle, and blends both brain walls.

Renderers and fallback
----------------------
``renderer="open3d"``: Open3D's offscreen Filament renderer in a child
process (see below). ``renderer="numpy"``: a z-buffer rasteriser in this
process (numba-compiled scan conversion, numpy deferred Phong shading),
no graphics driver needed; the default, because on a machine without a GPU
it is much faster than Filament on llvmpipe (measured on the project's
2-core machine at load average ~10: 8 views of a 101,900-face tumour in a
170,492-face brain at 640x480, 1.70 s against 122.7 s, see
``benchmarks/bench_render.py``). ``renderer="auto"`` tries Open3D
and falls back to numpy when the child cannot start or render (no Open3D,
no Vulkan/Mesa driver, crash or timeout); ``RenderResult.info["renderer"]``
names the renderer used and ``info["fallback_reason"]`` why Open3D was not,
for the provenance record. Each renderer gives the same image bytes for the
same input (no anti-aliasing, no post-processing, deterministic order).

Design: one subprocess per call
-------------------------------
Measurements of Open3D's Filament renderer (open3d-cpu 0.20, Mesa 22.3
llvmpipe through Filament's Vulkan backend, headless: no DISPLAY needed) on
this 2-core machine, shared with other jobs:

* a fresh process: ``import open3d`` 0.6-0.9 s, ``OffscreenRenderer``
  creation ~0.1 s, first frame ~0.3 s (about 1.5 s more while the Mesa
  shader cache in ``~/.cache/mesa_shader_cache`` is cold), later frames
  0.07-0.1 s at 320x240 and ~0.1-0.4 s at 640x480;
* meshes given as the *legacy* ``o3d.geometry.TriangleMesh`` made some
  frames take 5-100 s instead of 0.1 s, erratically. The tensor-based
  ``o3d.t.geometry.TriangleMesh`` never showed this, so it is used here;
* rendering from any thread other than the one that created the (process-
  wide) Filament engine aborts the whole process (``PreconditionPanic``:
  "This thread has not been adopted"), and so does creating a second
  renderer in a new thread; two renderers alive at once in one thread work
  but abort the process at exit. Prefect may run tasks in worker threads,
  so an in-process renderer would be a process-killing hazard.

So every :func:`render_views` call runs ONE renderer in a fresh child
process (``python -m tumor3d.visual.render``) that renders all the views of the
call: every geometry is uploaded once and shown or hidden per view. The
scene goes to the child's stdin and the images come back on a private copy
of its stdout, as ``.npy`` bytes (no pickle, no temporary files);
Filament's C++ messages are diverted to the child's stderr, which is shown
only if the child fails. The child leaves with ``os._exit`` once the images
are written, skipping Filament's teardown. The calling process never
imports Open3D, may call from any thread, and survives a crash of the
renderer.

The package holds these parts by concept: :mod:`~tumor3d.visual.render.camera` (the
views and the orthographic camera), :mod:`~tumor3d.visual.render.scene` (geometries,
cut-aways and visibility per view), :mod:`~tumor3d.visual.render.raster` (the numpy
renderer), :mod:`~tumor3d.visual.render.offscreen` (the Open3D renderer and its child
process; ``python -m tumor3d.visual.render`` runs the child),
:mod:`~tumor3d.visual.render.annotate` (labels, scale bar, GIF),
:mod:`~tumor3d.visual.render.checks` (parameter checks) and
:mod:`~tumor3d.visual.render.views` (:func:`render_views`). The public names are
importable from here.
"""

from __future__ import annotations

from tumor3d.geometry.brain_surface import brain_surface
from tumor3d.visual.render.annotate import turntable_gif
from tumor3d.visual.render.camera import ANATOMICAL_VIEWS, CUTAWAYS, Camera
from tumor3d.visual.render.scene import vertex_normals
from tumor3d.visual.render.views import RENDERERS, RenderResult, render_views

__all__ = [
    "ANATOMICAL_VIEWS",
    "CUTAWAYS",
    "RENDERERS",
    "Camera",
    "RenderResult",
    "brain_surface",
    "render_views",
    "turntable_gif",
    "vertex_normals",
]

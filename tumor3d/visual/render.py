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
"""

from __future__ import annotations

import io
import math
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.brain_surface import brain_surface
from tumor3d.geometry.mesh import Mesh

__all__ = [
    "ANATOMICAL_VIEWS",
    "CUTAWAYS",
    "Camera",
    "RenderResult",
    "brain_surface",
    "render_views",
    "turntable_gif",
    "vertex_normals",
]

#: The six anatomical views: name -> (forward = viewing direction, image up), RAS.
_ANATOMICAL: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "anterior": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "posterior": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "right": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "left": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "superior": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
    "inferior": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
}
#: Cut-away planes: name -> the anatomical view that looks at the cut face.
_CUT_VIEW = {"axial": "superior", "coronal": "anterior", "sagittal": "right"}

ANATOMICAL_VIEWS: tuple[str, ...] = tuple(_ANATOMICAL)
CUTAWAYS: tuple[str, ...] = tuple(_CUT_VIEW)
RENDERERS = ("auto", "open3d", "numpy")

#: The bounding sphere of the framed geometry fills this fraction of the
#: smaller image half-side; the band outside holds the labels.
_FRAME_FILL = 0.85
#: Interior (cut-away inner wall) colour = this factor x the surface colour.
_INTERIOR_FACTOR = 0.7
_DEFAULT_TIMEOUT_S = 600.0

# Filament calibration (measured, open3d 0.20): a directional light of
# 100 000 lux gives a radiance of 0.47 x the albedo on a surface facing it
# (Open3D's default camera exposure), and the default image-based light at
# 30 000 gives 0.47 on average.
_SUN_LUX_PER_UNIT = 100_000.0 / 0.47
_IBL_PER_UNIT = 30_000.0 / 0.47

# RAS axis letters: (+ letter, - letter) per axis.
_AXIS_LETTERS = (("R", "L"), ("A", "P"), ("S", "I"))


# ---------------------------------------------------------------------------
# public data types
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """An orthographic camera: RAS mm -> pixel coordinates.

    Parameters
    ----------
    centre : (3,) ndarray
        RAS point (mm) imaged at the image centre.
    forward, up : (3,) ndarray
        Unit viewing direction and image-up direction (orthogonal), RAS.
    pixels_per_mm : float
        Image scale, the same on both image axes.
    width, height : int
        Image size in pixels.
    """

    centre: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    pixels_per_mm: float
    width: int
    height: int

    @property
    def right(self) -> np.ndarray:
        """Image-right direction in RAS, ``forward x up``."""
        return np.cross(self.forward, self.up)

    def project(self, points_ras: np.ndarray) -> np.ndarray:
        """Pixel coordinates of RAS points.

        Parameters
        ----------
        points_ras : (n, 3) array_like
            Points in RAS mm.

        Returns
        -------
        (n, 3) float64 ndarray
            ``(column, row, depth_mm)``: pixel ``(row, column)`` has its
            centre at integer coordinates, row 0 at the top; depth along
            ``forward`` from the centre (larger is farther from the camera).
        """
        p = np.asarray(points_ras, dtype=np.float64).reshape(-1, 3) - self.centre
        s = self.pixels_per_mm
        col = (self.width / 2.0) + (p @ self.right) * s - 0.5
        row = (self.height / 2.0) - (p @ self.up) * s - 0.5
        return np.stack([col, row, p @ self.forward], axis=1)

    def edge_labels(self) -> dict[str, str]:
        """Anatomical letters of the image edges (``left``, ``right``, ``top``, ``bottom``).

        The letter(s) of the RAS direction each edge points to; an oblique
        direction gets the letters of every axis with a component of at
        least ``sin 22.5 deg``, the dominant first (e.g. ``"LA"``).
        """
        r, u = self.right, self.up
        return {
            "left": _direction_letters(-r),
            "right": _direction_letters(r),
            "top": _direction_letters(u),
            "bottom": _direction_letters(-u),
        }


@dataclass(frozen=True)
class RenderResult:
    """What :func:`render_views` returns.

    Attributes
    ----------
    images : dict of str to ndarray
        View name -> ``(height, width, 3)`` uint8 RGB image, in the order:
        anatomical views, then cut-aways (``cut_<plane>``), as requested.
    turntable : tuple of ndarray
        The turntable frames, ``(height, width, 3)`` uint8 each.
    cameras : dict of str to Camera
        The camera of each image (turntable frames as ``turntable_<k>``).
    info : dict
        ``renderer`` ("open3d" or "numpy"), ``fallback_reason`` (None or
        why Open3D was not used), ``seconds`` (wall time of the rendering),
        ``pixels_per_mm``, ``scale_bar_mm``, ``n_faces_tumor``,
        ``n_faces_brain``, ``cut_plane_point_ras`` (the tumour centroid).
    """

    images: dict[str, np.ndarray]
    turntable: tuple[np.ndarray, ...]
    cameras: dict[str, Camera]
    info: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------------------
# geometry (pure numpy, in the calling process)
# ---------------------------------------------------------------------------


def vertex_normals(mesh: Mesh) -> np.ndarray:
    r"""Per-vertex normals: unweighted mean of the adjacent face normals.

    .. math:: n_v = \frac{\sum_{t \ni v} \hat n_t}{\lVert \sum_{t \ni v} \hat n_t \rVert}

    as in spec section 7 (every face counts once, whatever its area).
    Zero-area faces contribute nothing; a vertex with no usable face (or
    whose normals cancel) gets ``(0, 0, 1)``.

    Parameters
    ----------
    mesh : Mesh
        Faces counter-clockwise seen from outside.

    Returns
    -------
    (n_vertices, 3) float64 ndarray
        Unit outward normals.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    return _vertex_normals(mesh.vertices, mesh.faces)


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    out = np.zeros((len(v), 3))
    if len(f):
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        norm = np.linalg.norm(fn, axis=1, keepdims=True)
        fn = np.divide(fn, norm, out=np.zeros_like(fn), where=norm > 0)
        for k in range(3):
            out[:, k] = np.bincount(f.reshape(-1), weights=np.repeat(fn[:, k], 3), minlength=len(v))
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    tiny = norm[:, 0] <= 1e-12
    out = np.divide(out, norm, out=np.zeros_like(out), where=~tiny[:, None])
    out[tiny] = (0.0, 0.0, 1.0)
    return out


def _surface_centroid(mesh: Mesh) -> np.ndarray:
    v, f = mesh.vertices, mesh.faces
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = area.sum()
    if total <= 0:
        return v[np.unique(f)].mean(axis=0)
    return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / total


def _used_vertices(mesh: Mesh) -> np.ndarray:
    used = np.zeros(mesh.n_vertices, dtype=bool)
    used[mesh.faces.reshape(-1)] = True
    return mesh.vertices[used]


def _direction_letters(d: np.ndarray) -> str:
    d = np.asarray(d, dtype=np.float64)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    order = np.argsort(-np.abs(d), kind="stable")
    letters = [
        _AXIS_LETTERS[k][0 if d[k] > 0 else 1]
        for k in order
        if abs(d[k]) >= math.sin(math.radians(22.5))
    ]
    return "".join(letters)


def _clip_by_plane(
    v: np.ndarray, n: np.ndarray, f: np.ndarray, point: np.ndarray, normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the part of a triangle soup with ``(p - point) . normal <= 0``.

    Straddling triangles are cut exactly along the plane (one triangle
    when one vertex is kept, two when two are); new vertices interpolate
    positions and normals linearly. Winding is preserved.

    Returns
    -------
    vertices (k, 3), normals (k, 3), faces (m, 3) int64
    """
    s = (v - point) @ normal
    sf = s[f] > 0  # True = removed side
    n_out = sf.sum(axis=1)
    keep = f[n_out == 0]
    new_v = [v]
    new_n = [n]
    new_f = [keep]
    base = len(v)

    def edge_points(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sa, sb = s[a], s[b]
        t = (sa / (sa - sb))[:, None]
        pv = v[a] + t * (v[b] - v[a])
        pn = n[a] + t * (n[b] - n[a])
        pn /= np.maximum(np.linalg.norm(pn, axis=1, keepdims=True), 1e-12)
        return pv, pn

    for n_removed in (2, 1):
        tri = f[n_out == n_removed]
        if not len(tri):
            continue
        flags = s[tri] > 0
        # the odd vertex: the kept one (two removed) or the removed one (one removed)
        odd = np.argmax(~flags if n_removed == 2 else flags, axis=1)
        rows = np.arange(len(tri))[:, None]
        rolled = tri[rows, (odd[:, None] + np.arange(3)[None, :]) % 3]
        a, b, c = rolled[:, 0], rolled[:, 1], rolled[:, 2]
        pab, nab = edge_points(a, b)
        pac, nac = edge_points(a, c)
        k = len(tri)
        i_ab = base + np.arange(k)
        i_ac = base + k + np.arange(k)
        new_v += [pab, pac]
        new_n += [nab, nac]
        base += 2 * k
        if n_removed == 2:  # a kept: triangle (a, ab, ac)
            new_f.append(np.stack([a, i_ab, i_ac], axis=1))
        else:  # a removed: quad (ab, b, c, ac)
            new_f.append(np.stack([i_ab, b, c], axis=1))
            new_f.append(np.stack([i_ab, c, i_ac], axis=1))
    faces = np.concatenate(new_f).astype(np.int64)
    verts = np.concatenate(new_v)
    norms = np.concatenate(new_n)
    used = np.zeros(len(verts), dtype=bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return verts[used], norms[used], remap[faces]


# ---------------------------------------------------------------------------
# validation helpers
# ---------------------------------------------------------------------------


def _check_color(value: Sequence[float], name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be 3 numbers in [0, 1], got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or arr.min() < 0 or arr.max() > 1:
        raise InputError(f"{name} must be 3 numbers in [0, 1], got {value!r}")
    return arr


def _check_number(value: float, name: str, lo: float, hi: float, *, closed: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} must be a number, got {value!r}")
    v = float(value)
    ok = (lo <= v <= hi) if closed else (lo < v < hi)
    if not (math.isfinite(v) and ok):
        kind = "in" if closed else "strictly between"
        raise InputError(f"{name} must lie {kind} {lo} and {hi}, got {value}")
    return v


def _check_int(value: int, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name} must be an integer, got {value!r}")
    if not lo <= value <= hi:
        raise InputError(f"{name} must lie in [{lo}, {hi}], got {value}")
    return int(value)


def _check_names(value: Sequence[str], name: str, allowed: Sequence[str]) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise InputError(f"{name} must be a sequence of names from {list(allowed)}, got {value!r}")
    names = tuple(value)
    bad = [x for x in names if x not in allowed]
    if bad:
        raise InputError(f"{name}: unknown name(s) {bad}; choose from {list(allowed)}")
    if len(set(names)) != len(names):
        raise InputError(f"{name} lists a name twice: {list(names)}")
    return names


def _check_mesh(mesh: Any, name: str) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise InputError(f"{name} must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    if mesh.is_empty:
        raise InputError(f"cannot render an empty {name} mesh (it has no faces)")
    return mesh


# ---------------------------------------------------------------------------
# the public entry point
# ---------------------------------------------------------------------------


def render_views(
    tumor: Mesh,
    *,
    brain: Mesh | None = None,
    width: int = 640,
    height: int = 480,
    views: Sequence[str] = ANATOMICAL_VIEWS,
    cutaways: Sequence[str] = ("axial", "coronal"),
    turntable_frames: int = 24,
    turntable_elevation_deg: float = 20.0,
    color_rgb: Sequence[float] = (0.85, 0.35, 0.3),
    brain_color_rgb: Sequence[float] = (0.78, 0.78, 0.82),
    brain_opacity: float = 0.25,
    background_rgb: Sequence[float] = (1.0, 1.0, 1.0),
    ambient: float = 0.15,
    diffuse: float = 0.7,
    specular: float = 0.3,
    shininess: float = 32.0,
    annotate: bool = True,
    renderer: str = "numpy",
    timeout_s: float = _DEFAULT_TIMEOUT_S,
) -> RenderResult:
    """Render the tumour (inside the brain) from the anatomical directions.

    Parameters
    ----------
    tumor : Mesh
        Non-empty tumour surface in RAS mm, faces counter-clockwise seen
        from outside (as :func:`tumor3d.geometry.surface.extract_surface` gives).
    brain : Mesh, optional
        The brain surface in the same RAS frame, drawn translucent around
        the tumour (opaque and clipped in the cut-aways). Without it the
        tumour alone is framed and the cut-aways clip the tumour.
    width, height : int
        Image size in pixels, 64-4096 each.
    views : sequence of str
        Anatomical views to render, from :data:`ANATOMICAL_VIEWS`.
    cutaways : sequence of str
        Cut-away views, from :data:`CUTAWAYS` (``axial`` = transverse, seen
        from above; ``coronal`` seen from the front; ``sagittal`` from the
        right); images named ``cut_<plane>``.
    turntable_frames : int
        Number of turntable frames (0-360), evenly spaced in azimuth from 0.
    turntable_elevation_deg : float
        Camera elevation of the turntable, in [-89, 89] degrees.
    color_rgb, brain_color_rgb, background_rgb : sequence of 3 float
        Colours, components in [0, 1]. Background pixels equal
        ``round(255 * background_rgb)`` within one level.
    brain_opacity : float
        Opacity of the brain surface in (0, 1].
    ambient, diffuse, specular : float
        Phong coefficients ``k_a, k_d, k_s`` in [0, 1] ([A25]: 0.15, 0.7, 0.3).
    shininess : float
        Phong exponent ``s`` in [1, 1000] ([A25]: 32).
    annotate : bool
        Draw orientation labels and a scale bar onto each image.
    renderer : {"auto", "open3d", "numpy"}
        ``numpy`` (default), ``open3d``, or ``auto`` (Open3D, falling back to
        numpy); see the module docstring.
    timeout_s : float
        Give up on (and kill) the Open3D child after this many seconds.

    Returns
    -------
    RenderResult
        Images by name, turntable frames, cameras and provenance info.

    Raises
    ------
    InputError
        On an empty or non-mesh input or an invalid parameter.
    RuntimeError
        If ``renderer="open3d"`` and the offscreen renderer fails; the
        message carries the renderer's error output.
    """
    tumor = _check_mesh(tumor, "tumor")
    if brain is not None:
        brain = _check_mesh(brain, "brain")
    w = _check_int(width, "width", 64, 4096)
    h = _check_int(height, "height", 64, 4096)
    view_names = _check_names(views, "views", ANATOMICAL_VIEWS)
    cut_names = _check_names(cutaways, "cutaways", CUTAWAYS)
    n_turn = _check_int(turntable_frames, "turntable_frames", 0, 360)
    if not view_names and not cut_names and n_turn == 0:
        raise InputError("nothing to render: views, cutaways and turntable_frames are all empty")
    elev = _check_number(
        turntable_elevation_deg, "turntable_elevation_deg", -89.0, 89.0, closed=True
    )
    color = _check_color(color_rgb, "color_rgb")
    brain_color = _check_color(brain_color_rgb, "brain_color_rgb")
    background = _check_color(background_rgb, "background_rgb")
    opacity = _check_number(brain_opacity, "brain_opacity", 0.0, 1.0, closed=True)
    if opacity == 0.0:
        raise InputError("brain_opacity must lie in (0, 1], got 0 (omit the brain instead)")
    k_a = _check_number(ambient, "ambient", 0.0, 1.0, closed=True)
    k_d = _check_number(diffuse, "diffuse", 0.0, 1.0, closed=True)
    k_s = _check_number(specular, "specular", 0.0, 1.0, closed=True)
    s = _check_number(shininess, "shininess", 1.0, 1000.0, closed=True)
    if not isinstance(annotate, bool):
        raise InputError(f"annotate must be True or False, got {annotate!r}")
    if renderer not in RENDERERS:
        raise InputError(f"renderer must be one of {list(RENDERERS)}, got {renderer!r}")
    timeout = _check_number(timeout_s, "timeout_s", 0.0, math.inf)

    scene = _build_scene(
        tumor,
        brain,
        w,
        h,
        view_names,
        cut_names,
        n_turn,
        elev,
        color,
        brain_color,
        opacity,
        background,
    )
    lighting = np.array([k_a, k_d, k_s, s])
    t0 = time.perf_counter()
    fallback_reason = None
    used = renderer
    if renderer == "numpy":
        stack = _render_numpy(scene, lighting)
    else:
        try:
            stack = _run_worker(_open3d_request(scene, lighting), timeout)
            expected = (len(scene["cameras"]), h, w, 3)
            if stack.shape != expected or stack.dtype != np.uint8:
                raise RuntimeError(
                    f"offscreen renderer returned images of shape {stack.shape} and dtype "
                    f"{stack.dtype}, expected {expected} uint8"
                )
            used = "open3d"
        except RuntimeError as exc:
            if renderer == "open3d":
                raise
            fallback_reason = str(exc).splitlines()[0][:500]
            used = "numpy"
            stack = _render_numpy(scene, lighting)
    seconds = time.perf_counter() - t0

    names: list[str] = scene["names"]
    cameras: dict[str, Camera] = dict(zip(names, scene["cameras"], strict=True))
    px_mm = scene["cameras"][0].pixels_per_mm
    bar_mm = _scale_bar_length_mm(w, px_mm)
    images: dict[str, np.ndarray] = {}
    frames: list[np.ndarray] = []
    for name, img in zip(names, stack, strict=True):
        out = np.array(img)
        if annotate:
            out = _annotate(out, cameras[name], background, bar_mm)
        if name.startswith("turntable_"):
            frames.append(out)
        else:
            images[name] = out
    info = {
        "renderer": used,
        "fallback_reason": fallback_reason,
        "seconds": round(seconds, 3),
        "pixels_per_mm": px_mm,
        "scale_bar_mm": bar_mm,
        "n_faces_tumor": tumor.n_faces,
        "n_faces_brain": 0 if brain is None else brain.n_faces,
        "cut_plane_point_ras": [float(x) for x in scene["cut_point"]],
        "projection": "orthographic",
    }
    return RenderResult(images=images, turntable=tuple(frames), cameras=cameras, info=info)


def _build_scene(
    tumor: Mesh,
    brain: Mesh | None,
    width: int,
    height: int,
    view_names: tuple[str, ...],
    cut_names: tuple[str, ...],
    n_turn: int,
    elevation_deg: float,
    color: np.ndarray,
    brain_color: np.ndarray,
    opacity: float,
    background: np.ndarray,
) -> dict[str, Any]:
    """Geometries (each once), cameras and per-view visibility."""
    frame_mesh = brain if brain is not None else tumor
    fv = _used_vertices(frame_mesh)
    centre = 0.5 * (fv.min(axis=0) + fv.max(axis=0))
    all_v = [_used_vertices(tumor), fv]
    radius = max(float(np.linalg.norm(np.concatenate(all_v) - centre, axis=1).max()), 1e-6)
    # the bounding sphere of everything about the brain's centre fits the image
    px_mm = _FRAME_FILL * min(width, height) / 2.0 / radius
    cut_point = _surface_centroid(tumor)

    geoms: list[dict[str, Any]] = []

    def add(
        name: str, v: np.ndarray, n: np.ndarray, f: np.ndarray, rgb: np.ndarray, alpha: float
    ) -> int:
        geoms.append(
            {
                "name": name,
                "vertices": v,
                "normals": n,
                "faces": f,
                "color": np.asarray(rgb, dtype=np.float64),
                "opacity": float(alpha),
            }
        )
        return len(geoms) - 1

    tn = _vertex_normals(tumor.vertices, tumor.faces)
    g_tumor = add("tumor", tumor.vertices, tn, tumor.faces, color, 1.0)
    g_brain = None
    if brain is not None:
        bn = _vertex_normals(brain.vertices, brain.faces)
        g_brain = add("brain", brain.vertices, bn, brain.faces, brain_color, opacity)

    cameras: list[Camera] = []
    visible: list[list[int]] = []
    names: list[str] = []

    def camera(fwd: np.ndarray, up: np.ndarray) -> Camera:
        return Camera(
            centre=centre.copy(),
            forward=fwd,
            up=up,
            pixels_per_mm=px_mm,
            width=width,
            height=height,
        )

    base = [g_tumor] + ([g_brain] if g_brain is not None else [])
    for name in view_names:
        fwd, up = (np.array(x) for x in _ANATOMICAL[name])
        names.append(name)
        cameras.append(camera(fwd, up))
        visible.append(base)
    for cut in cut_names:
        fwd, up = (np.array(x) for x in _ANATOMICAL[_CUT_VIEW[cut]])
        normal = -fwd  # the removed half faces the camera
        if brain is not None:
            cv, cn, cf = _clip_by_plane(brain.vertices, bn, brain.faces, cut_point, normal)
            g_out = add(f"brain_cut_{cut}", cv, cn, cf, brain_color, 1.0)
            g_in = add(
                f"brain_cut_{cut}_inside", cv, -cn, cf[:, ::-1], _INTERIOR_FACTOR * brain_color, 1.0
            )
            vis = [g_tumor, g_out, g_in]
        else:
            cv, cn, cf = _clip_by_plane(tumor.vertices, tn, tumor.faces, cut_point, normal)
            g_out = add(f"tumor_cut_{cut}", cv, cn, cf, color, 1.0)
            g_in = add(
                f"tumor_cut_{cut}_inside", cv, -cn, cf[:, ::-1], _INTERIOR_FACTOR * color, 1.0
            )
            vis = [g_out, g_in]
        names.append(f"cut_{cut}")
        cameras.append(camera(fwd, up))
        visible.append(vis)
    e = math.radians(elevation_deg)
    for k in range(n_turn):
        a = 2.0 * math.pi * k / n_turn
        to_eye = np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])
        fwd = -to_eye
        z = np.array([0.0, 0.0, 1.0])
        up = z - (z @ fwd) * fwd
        up /= np.linalg.norm(up)
        names.append(f"turntable_{k:03d}")
        cameras.append(camera(fwd, up))
        visible.append(base)
    return {
        "geoms": geoms,
        "cameras": cameras,
        "visible": visible,
        "names": names,
        "radius": radius,
        "background": background,
        "cut_point": cut_point,
        "size": (width, height),
    }


# ---------------------------------------------------------------------------
# annotation (Pillow, after rendering)
# ---------------------------------------------------------------------------


def _scale_bar_length_mm(width: int, px_mm: float) -> float:
    """The largest 1-2-5 x 10^k mm length at most a quarter of the image width."""
    target = 0.25 * width / px_mm
    k = math.floor(math.log10(target))
    best = 10.0**k
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10.0**k <= target:
            best = m * 10.0**k
    return float(best)


def _font(size_px: int):  # noqa: ANN202 - a Pillow font object
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size_px)
    except (TypeError, OSError, ImportError):  # Pillow without FreeType
        return ImageFont.load_default()


def _annotate(img: np.ndarray, cam: Camera, background: np.ndarray, bar_mm: float) -> np.ndarray:
    """Draw edge orientation letters and a scale bar (bottom left)."""
    from PIL import Image, ImageDraw

    h, w = img.shape[:2]
    lum = float(background @ np.array([0.2126, 0.7152, 0.0722]))
    ink = (0, 0, 0) if lum > 0.5 else (255, 255, 255)
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    size = max(10, min(h, w) // 24)
    font = _font(size)
    pad = max(3, size // 4)
    labels = cam.edge_labels()
    anchors = {
        "left": ((pad, h / 2), "lm"),
        "right": ((w - 1 - pad, h / 2), "rm"),
        "top": ((w / 2, pad), "mt"),
        "bottom": ((w / 2, h - 1 - pad), "mb"),
    }
    for edge, ((x, y), anchor) in anchors.items():
        if labels[edge]:
            draw.text((x, y), labels[edge], fill=ink, font=font, anchor=anchor)
    bar_px = int(round(bar_mm * cam.pixels_per_mm))
    x0, y1 = pad, h - 1 - pad
    thick = max(2, size // 6)
    draw.rectangle([x0, y1 - thick + 1, x0 + bar_px - 1, y1], fill=ink)
    text = f"{bar_mm:g} mm"
    draw.text(
        (x0, y1 - thick - 2), text, fill=ink, font=_font(max(8, (size * 3) // 4)), anchor="lb"
    )
    return np.asarray(pil, dtype=np.uint8).copy()


def turntable_gif(frames: Sequence[np.ndarray], *, frame_ms: int = 100) -> bytes:
    """Encode turntable frames as a looping animated GIF (Pillow).

    Parameters
    ----------
    frames : sequence of (h, w, 3) uint8 ndarray
        The frames, all the same shape (``RenderResult.turntable``).
    frame_ms : int
        Display time per frame in milliseconds (10-10000).

    Returns
    -------
    bytes
        The GIF file content; the same frames give the same bytes.
    """
    from PIL import Image

    frames = list(frames)
    if not frames:
        raise InputError("turntable_gif needs at least one frame")
    shape = np.asarray(frames[0]).shape
    for k, f in enumerate(frames):
        a = np.asarray(f)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3 or a.shape != shape:
            raise InputError(f"frame {k} must be a uint8 (h, w, 3) array of shape {shape}")
    frame_ms = _check_int(frame_ms, "frame_ms", 10, 10000)
    # one shared palette from the first frame keeps the colours stable and the bytes deterministic
    first = Image.fromarray(np.asarray(frames[0])).quantize(
        colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
    )
    pal = [first] + [
        Image.fromarray(np.asarray(f)).quantize(palette=first, dither=Image.Dither.NONE)
        for f in frames[1:]
    ]
    buf = io.BytesIO()
    pal[0].save(
        buf,
        format="GIF",
        save_all=True,
        append_images=pal[1:],
        duration=frame_ms,
        loop=0,
        optimize=False,
        disposal=1,
    )
    return buf.getvalue()


# ---------------------------------------------------------------------------
# numpy renderer (fallback): numba scan conversion + numpy deferred Phong
# ---------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _raster(px, py, depth, faces, width, height, zbuf, fid, b1, b2, cull):  # noqa: D401
    """Scan-convert triangles into a z-buffer (numba).

    ``px, py, depth`` are per-vertex pixel coordinates (pixel centres at
    integers, row axis down) and depths; ``zbuf``, ``fid`` (face index, -1 =
    none) and the barycentric weights ``b1, b2`` of the nearest fragment are
    updated in place (they are this module's own buffers). A pixel is
    covered when its centre lies inside or on the triangle; the first face
    wins a depth tie, so the result does not depend on anything but the
    face order. With ``cull``, faces seen from behind are skipped.
    """
    for t in range(faces.shape[0]):
        i0 = faces[t, 0]
        i1 = faces[t, 1]
        i2 = faces[t, 2]
        x0, y0 = px[i0], py[i0]
        x1, y1 = px[i1], py[i1]
        x2, y2 = px[i2], py[i2]
        # signed area in image coordinates (row axis points down):
        # counter-clockwise as seen by the camera gives area < 0
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0 or (cull and area > 0.0):
            continue
        inv = 1.0 / area
        cmin = max(int(math.ceil(min(x0, x1, x2))), 0)
        cmax = min(int(math.floor(max(x0, x1, x2))), width - 1)
        rmin = max(int(math.ceil(min(y0, y1, y2))), 0)
        rmax = min(int(math.floor(max(y0, y1, y2))), height - 1)
        for r in range(rmin, rmax + 1):
            for c in range(cmin, cmax + 1):
                w0 = ((x1 - c) * (y2 - r) - (x2 - c) * (y1 - r)) * inv
                w1 = ((x2 - c) * (y0 - r) - (x0 - c) * (y2 - r)) * inv
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                z = w0 * depth[i0] + w1 * depth[i1] + w2 * depth[i2]
                if z < zbuf[r, c]:
                    zbuf[r, c] = z
                    fid[r, c] = t
                    b1[r, c] = w1
                    b2[r, c] = w2


@numba.njit(cache=True, nogil=True)
def _shade(img, fid, b1, b2, faces, normals, color, light, k_a, k_d, k_s, s, alpha):
    """Phong-shade the fragments of one layer into ``img`` (numba, in place).

    Per pixel with ``fid >= 0``: the vertex normals interpolated with the
    barycentric weights and renormalised, then
    ``rgb = color (k_a + k_d max(0, N.L)) + k_s max(0, R.V)^s`` with the
    headlight ``L = V = light`` and ``R = 2 (N.L) N - L``, clipped to [0, 1]
    and blended over ``img`` with ``alpha``.
    """
    h, w = fid.shape
    for r in range(h):
        for c in range(w):
            t = fid[r, c]
            if t < 0:
                continue
            wb1 = b1[r, c]
            wb2 = b2[r, c]
            wb0 = 1.0 - wb1 - wb2
            i0 = faces[t, 0]
            i1 = faces[t, 1]
            i2 = faces[t, 2]
            nx = wb0 * normals[i0, 0] + wb1 * normals[i1, 0] + wb2 * normals[i2, 0]
            ny = wb0 * normals[i0, 1] + wb1 * normals[i1, 1] + wb2 * normals[i2, 1]
            nz = wb0 * normals[i0, 2] + wb1 * normals[i1, 2] + wb2 * normals[i2, 2]
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            if norm > 1e-12:
                nx /= norm
                ny /= norm
                nz /= norm
            nl = nx * light[0] + ny * light[1] + nz * light[2]
            spec = 0.0
            if nl > 0.0:
                # R.V with V = L: (2 (N.L) N - L).L = 2 (N.L)^2 - 1
                rv = 2.0 * nl * nl - 1.0
                if rv > 0.0:
                    spec = k_s * rv**s
            else:
                nl = 0.0
            for k in range(3):
                v = color[k] * (k_a + k_d * nl) + spec
                v = min(max(v, 0.0), 1.0)
                img[r, c, k] = (1.0 - alpha) * img[r, c, k] + alpha * v


def _layer(
    geom: dict[str, Any], cam: Camera, zbuf: np.ndarray, img: np.ndarray, lighting: np.ndarray
) -> None:
    """Rasterise one geometry against ``zbuf`` and shade it into ``img`` (both updated)."""
    h, w = zbuf.shape
    p = cam.project(geom["vertices"])
    fid = np.full((h, w), -1, dtype=np.int64)
    b1 = np.zeros((h, w))
    b2 = np.zeros((h, w))
    faces = np.ascontiguousarray(geom["faces"], dtype=np.int64)
    _raster(
        np.ascontiguousarray(p[:, 0]),
        np.ascontiguousarray(p[:, 1]),
        np.ascontiguousarray(p[:, 2]),
        faces,
        w,
        h,
        zbuf,
        fid,
        b1,
        b2,
        True,
    )
    k_a, k_d, k_s, s = (float(x) for x in lighting)
    _shade(
        img,
        fid,
        b1,
        b2,
        faces,
        np.ascontiguousarray(geom["normals"], dtype=np.float64),
        np.ascontiguousarray(geom["color"], dtype=np.float64),
        np.ascontiguousarray(-cam.forward, dtype=np.float64),
        k_a,
        k_d,
        k_s,
        s,
        float(geom["opacity"]),
    )


def _render_numpy(scene: dict[str, Any], lighting: np.ndarray) -> np.ndarray:
    """All views of the scene with the numpy/numba z-buffer renderer.

    Opaque geometries first (one shared z-buffer), then each translucent
    one against a copy of the opaque z-buffer: only its nearest layer is
    blended (see the module docstring).
    """
    w, h = scene["size"]
    geoms = scene["geoms"]
    out = np.empty((len(scene["cameras"]), h, w, 3), dtype=np.uint8)
    for k, (cam, vis) in enumerate(zip(scene["cameras"], scene["visible"], strict=True)):
        img = np.empty((h, w, 3))
        img[:] = scene["background"]
        zbuf = np.full((h, w), np.inf)
        for g in (geoms[i] for i in vis if geoms[i]["opacity"] >= 1.0):
            _layer(g, cam, zbuf, img, lighting)
        for g in (geoms[i] for i in vis if geoms[i]["opacity"] < 1.0):
            _layer(g, cam, zbuf.copy(), img, lighting)
        out[k] = np.rint(img * 255.0).astype(np.uint8)
    return out


# ---------------------------------------------------------------------------
# Open3D renderer: the request and the child process
# ---------------------------------------------------------------------------


def _open3d_request(scene: dict[str, Any], lighting: np.ndarray) -> dict[str, np.ndarray]:
    """The scene as flat arrays for the child, vertices centred for float32 precision."""
    cams: list[Camera] = scene["cameras"]
    centre = cams[0].centre
    radius = scene["radius"]
    k_a, k_d, k_s, s = (float(x) for x in lighting)
    req: dict[str, np.ndarray] = {}
    for i, g in enumerate(scene["geoms"]):
        req[f"g{i}_vertices"] = np.asarray(g["vertices"] - centre, dtype=np.float32)
        req[f"g{i}_normals"] = np.asarray(g["normals"], dtype=np.float32)
        req[f"g{i}_faces"] = np.asarray(g["faces"], dtype=np.int32)
        req[f"g{i}_color"] = np.array([*g["color"], g["opacity"]])
    vis = np.zeros((len(cams), len(scene["geoms"])), dtype=bool)
    for k, v in enumerate(scene["visible"]):
        vis[k, v] = True
    w, h = scene["size"]
    half_w = w / 2.0 / cams[0].pixels_per_mm
    half_h = h / 2.0 / cams[0].pixels_per_mm
    dist = 3.0 * radius
    req.update(
        n_geoms=np.array(len(scene["geoms"])),
        visible=vis,
        forward=np.array([c.forward for c in cams]),
        up=np.array([c.up for c in cams]),
        size=np.array([w, h], dtype=np.int64),
        # left, right, bottom, top, near, far, eye distance
        ortho=np.array(
            [-half_w, half_w, -half_h, half_h, dist - 1.5 * radius, dist + 1.5 * radius, dist]
        ),
        background_srgb=_srgb_encode(scene["background"]),
        # sun illuminance, ambient (image-based light) intensity, roughness, reflectance
        light=np.array(
            [
                k_d * _SUN_LUX_PER_UNIT,
                k_a * _IBL_PER_UNIT,
                (2.0 / (s + 2.0)) ** 0.25,
                min(1.0, 0.5 * k_s / 0.3),
            ]
        ),
    )
    return req


def _srgb_encode(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def _run_worker(request: dict[str, np.ndarray], timeout_s: float) -> np.ndarray:
    """Render in a child process; return the stacked ``(k, h, w, 3)`` images."""
    buf = io.BytesIO()
    np.savez(buf, **request)
    env = dict(os.environ)
    package_root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH", "")) if p)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "tumor3d.visual.render"],
            input=buf.getvalue(),
            capture_output=True,
            timeout=timeout_s,
            env=env,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise RuntimeError(
            f"offscreen rendering did not finish within {timeout_s:g} s and was stopped"
        ) from None
    except OSError as exc:
        raise RuntimeError(f"offscreen rendering could not start {sys.executable}: {exc}") from None
    if proc.returncode != 0:
        raise RuntimeError(
            f"offscreen rendering failed (exit status {proc.returncode}): "
            f"{_error_tail(proc.stderr)}"
        )
    try:
        return np.load(io.BytesIO(proc.stdout), allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise RuntimeError(
            f"offscreen renderer sent no readable image ({exc}); its output: "
            f"{_error_tail(proc.stderr)}"
        ) from None


_NOISE = (
    "CircularBuffer",
    "FEngine",
    "Vulkan device driver",
    "Selected physical device",
    "Backend feature level",
    "FEngine feature level",
    "GLFWWindowSystem",
)


def _error_tail(stderr: bytes, n_lines: int = 20) -> str:
    lines = [
        ln
        for ln in stderr.decode("utf-8", errors="replace").splitlines()
        if ln.strip() and not any(tok in ln for tok in _NOISE)
    ]
    return "\n".join(lines[-n_lines:]) or "(no error output)"


def _worker_main() -> int:
    """Entry point of ``python -m tumor3d.visual.render``: stdin request -> stdout images."""
    out_fd = os.dup(1)  # private copy of the real stdout, for the images only
    os.dup2(2, 1)  # Filament prints on stdout: divert everything else to stderr
    sys.stdout = sys.stderr
    payload = sys.stdin.buffer.read()
    with np.load(io.BytesIO(payload), allow_pickle=False) as data:
        req = {k: data[k] for k in data.files}
    if os.environ.get("TUMOR3D_RENDER_FAIL"):  # test hook: simulate a broken driver
        raise RuntimeError("TUMOR3D_RENDER_FAIL is set: simulated renderer failure")

    import open3d as o3d  # only ever imported in the child

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    rendering = o3d.visualization.rendering
    width, height = (int(x) for x in req["size"])
    # Renderer first, geometry after (see the module docstring).
    renderer = rendering.OffscreenRenderer(width, height)
    scene = renderer.scene
    sun_lux, ibl, roughness, reflectance = (float(x) for x in req["light"])
    n_geoms = int(req["n_geoms"])
    for i in range(n_geoms):
        tri = o3d.t.geometry.TriangleMesh()
        tri.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(req[f"g{i}_vertices"]))
        tri.vertex.normals = o3d.core.Tensor(np.ascontiguousarray(req[f"g{i}_normals"]))
        tri.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(req[f"g{i}_faces"]))
        rgba = [float(c) for c in req[f"g{i}_color"]]
        material = rendering.MaterialRecord()
        material.shader = "defaultLit" if rgba[3] >= 1.0 else "defaultLitTransparency"
        material.base_color = rgba
        material.base_metallic = 0.0
        material.base_roughness = roughness
        material.base_reflectance = reflectance
        scene.add_geometry(f"g{i}", tri, material)
    scene.set_background([*(float(c) for c in req["background_srgb"]), 1.0])
    scene.view.set_post_processing(False)
    scene.view.set_shadowing(False)  # a headlight casts no visible shadow
    scene.scene.enable_indirect_light(True)
    scene.scene.set_indirect_light_intensity(ibl)
    scene.scene.enable_sun_light(True)

    left, right, bottom, top, near, far, dist = (float(x) for x in req["ortho"])
    camera = scene.camera
    camera.set_projection(rendering.Camera.Projection.Ortho, left, right, bottom, top, near, far)
    visible = req["visible"]
    shown = [True] * n_geoms
    images = np.empty((len(visible), height, width, 3), dtype=np.uint8)
    for k in range(len(visible)):
        for i in range(n_geoms):
            if bool(visible[k, i]) != shown[i]:
                scene.show_geometry(f"g{i}", bool(visible[k, i]))
                shown[i] = bool(visible[k, i])
        fwd = req["forward"][k].astype(np.float32)
        camera.look_at(np.zeros(3, np.float32), -dist * fwd, req["up"][k].astype(np.float32))
        scene.scene.set_sun_light(fwd, np.ones(3, dtype=np.float32), sun_lux)
        images[k] = np.asarray(renderer.render_to_image())[:, :, :3]
    encoded = io.BytesIO()
    np.save(encoded, images, allow_pickle=False)
    with os.fdopen(out_fd, "wb") as out:  # a pipe: not seekable, so write the bytes
        out.write(encoded.getvalue())
    return 0


if __name__ == "__main__":
    _code = _worker_main()
    sys.stderr.flush()
    os._exit(_code)  # skip Filament's teardown: the images are already written

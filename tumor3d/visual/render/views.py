"""The public entry point of :mod:`tumor3d.visual.render`: :func:`render_views`."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.visual.render.annotate import _annotate, _scale_bar_length_mm
from tumor3d.visual.render.camera import ANATOMICAL_VIEWS, CUTAWAYS, Camera
from tumor3d.visual.render.checks import (
    _check_color,
    _check_int,
    _check_mesh,
    _check_names,
    _check_number,
)
from tumor3d.visual.render.offscreen import _open3d_request, _run_worker
from tumor3d.visual.render.raster import _render_numpy
from tumor3d.visual.render.scene import _build_scene

RENDERERS = ("auto", "open3d", "numpy")


_DEFAULT_TIMEOUT_S = 600.0


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
        numpy); see :mod:`tumor3d.visual.render`.
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

"""The scene of one :func:`~tumor3d.visual.render.render_views` call (pure numpy).

Every geometry once (the tumour, the brain and the clipped cut-away
surfaces with their inner walls), with its vertex normals, and a camera and
the visible geometries per view; both renderers draw this scene.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.visual.render.camera import _ANATOMICAL, _CUT_VIEW, Camera

#: The bounding sphere of the framed geometry fills this fraction of the
#: smaller image half-side; the band outside holds the labels.
_FRAME_FILL = 0.85


#: Interior (cut-away inner wall) colour = this factor x the surface colour.
_INTERIOR_FACTOR = 0.7


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

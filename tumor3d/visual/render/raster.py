"""The numpy renderer: numba z-buffer scan conversion and deferred Phong shading.

Runs in the calling process, no graphics driver needed; see the
lighting and transparency sections of :mod:`tumor3d.visual.render`.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numba
import numpy as np

from tumor3d.visual.render.camera import Camera


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


@numba.njit(cache=True, nogil=True)
def _clear(img, background, zbuf):
    """Start a frame: every pixel of ``img`` the background colour, ``zbuf`` infinitely far."""
    h, w = zbuf.shape
    for r in range(h):
        for c in range(w):
            zbuf[r, c] = np.inf
            for k in range(3):
                img[r, c, k] = background[k]


@numba.njit(cache=True, nogil=True)
def _to_uint8(img, out):
    """``out[...] = rint(255 img)`` as uint8 (``img`` in [0, 1]), in one pass."""
    h, w = out.shape[0], out.shape[1]
    for r in range(h):
        for c in range(w):
            for k in range(3):
                out[r, c, k] = np.uint8(np.rint(img[r, c, k] * 255.0))


class _Geometry(NamedTuple):
    """One scene geometry in the kernels' types, converted once per render."""

    vertices: np.ndarray  # (n, 3) world mm
    faces: np.ndarray  # (m, 3) int64
    normals: np.ndarray  # (n, 3) float64
    color: np.ndarray  # (3,) float64
    opacity: float

    @classmethod
    def of(cls, geom: dict[str, Any]) -> _Geometry:
        # read-only whatever the caller's array (a Mesh's faces are, a cut-away's are
        # not): the kernels are typed on the flag, so one signature, one compilation
        faces = np.ascontiguousarray(geom["faces"], dtype=np.int64).view()
        faces.setflags(write=False)
        return cls(
            geom["vertices"],
            faces,
            np.ascontiguousarray(geom["normals"], dtype=np.float64),
            np.ascontiguousarray(geom["color"], dtype=np.float64),
            float(geom["opacity"]),
        )


def _layer(
    geom: _Geometry,
    cam: Camera,
    zbuf: np.ndarray,
    img: np.ndarray,
    lighting: np.ndarray,
    fid: np.ndarray,
    b1: np.ndarray,
    b2: np.ndarray,
) -> None:
    """Rasterise one geometry against ``zbuf`` and shade it into ``img`` (both updated).

    ``fid``, ``b1`` and ``b2`` (h, w) are the caller's scratch buffers: ``fid`` is
    reset here; the weights are read only where ``fid`` was written.
    """
    h, w = zbuf.shape
    p = cam.project(geom.vertices)
    fid.fill(-1)
    _raster(
        np.ascontiguousarray(p[:, 0]),
        np.ascontiguousarray(p[:, 1]),
        np.ascontiguousarray(p[:, 2]),
        geom.faces,
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
        geom.faces,
        geom.normals,
        geom.color,
        np.ascontiguousarray(-cam.forward, dtype=np.float64),
        k_a,
        k_d,
        k_s,
        s,
        geom.opacity,
    )


def _render_numpy(scene: dict[str, Any], lighting: np.ndarray) -> np.ndarray:
    """All views of the scene with the numpy/numba z-buffer renderer.

    Opaque geometries first (one shared z-buffer), then each translucent
    one against a copy of the opaque z-buffer: only its nearest layer is
    blended (see :mod:`tumor3d.visual.render`). The frame buffers are
    allocated once for all views.
    """
    w, h = scene["size"]
    geoms = [_Geometry.of(g) for g in scene["geoms"]]
    background = np.ascontiguousarray(scene["background"], dtype=np.float64)
    out = np.empty((len(scene["cameras"]), h, w, 3), dtype=np.uint8)
    img = np.empty((h, w, 3))
    zbuf = np.empty((h, w))
    zlayer = np.empty((h, w))
    fid = np.empty((h, w), dtype=np.int64)
    b1 = np.empty((h, w))
    b2 = np.empty((h, w))
    for k, (cam, vis) in enumerate(zip(scene["cameras"], scene["visible"], strict=True)):
        _clear(img, background, zbuf)
        for g in (geoms[i] for i in vis if geoms[i].opacity >= 1.0):
            _layer(g, cam, zbuf, img, lighting, fid, b1, b2)
        for g in (geoms[i] for i in vis if geoms[i].opacity < 1.0):
            np.copyto(zlayer, zbuf)
            _layer(g, cam, zlayer, img, lighting, fid, b1, b2)
        _to_uint8(img, out[k])
    return out

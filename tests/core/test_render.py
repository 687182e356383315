"""Tests of tumor3d.render (Open3D offscreen rendering in a child process).

These tests need a working offscreen renderer (open3d with Mesa); they fail,
not skip, where it is missing.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.mesh import Mesh
from tumor3d.render import _run_worker, render_views, vertex_normals
from tumor3d.surface import extract_surface

BG = (0.2, 0.4, 0.6)
BG_U8 = np.round(np.array(BG) * 255).astype(int)  # (51, 102, 153)
COLOR = (0.85, 0.35, 0.3)
W, H = 200, 150


def _balls_mask(balls, spacing_mm=1.0, size=48):
    """Union of balls ((x, y, z) centre mm, radius mm) on a cube grid centred at 0."""
    c = (size - 1) / 2
    z, y, x = np.ogrid[:size, :size, :size]
    mask = np.zeros((size, size, size), dtype=bool)
    for (bx, by, bz), r in balls:
        mask |= ((x - c) * spacing_mm - bx) ** 2 + ((y - c) * spacing_mm - by) ** 2 + (
            (z - c) * spacing_mm - bz
        ) ** 2 <= r * r
    aff = np.diag([spacing_mm, spacing_mm, spacing_mm, 1.0])
    aff[:3, 3] = -c * spacing_mm
    return mask, aff


def _render(mesh, azimuths, **kw):
    params = {
        "width": W,
        "height": H,
        "azimuths_deg": azimuths,
        "elevation_deg": 20.0,
        "field_of_view_deg": 40.0,
        "color_rgb": COLOR,
        "background_rgb": BG,
        **kw,
    }
    return render_views(mesh, **params)


def _foreground(img):
    return np.abs(img.astype(int) - BG_U8).max(axis=2) > 2


@pytest.fixture(scope="module")
def sphere_mesh():
    mask, aff = _balls_mask([((0.0, 0.0, 0.0), 10.0)], size=26)
    return extract_surface(mask, aff)


@pytest.fixture(scope="module")
def sphere_images(sphere_mesh):
    return _render(sphere_mesh, (0.0, 90.0))


@pytest.fixture(scope="module")
def two_ball_images():
    # a big ball at the origin and a small one 20 mm to the patient's right (+x)
    mask, aff = _balls_mask([((0.0, 0.0, 0.0), 8.0), ((20.0, 0.0, 0.0), 3.5)])
    return _render(extract_surface(mask, aff), (0.0, 90.0, 180.0))


def test_output_shape_and_dtype(sphere_images):
    assert len(sphere_images) == 2
    for img in sphere_images:
        assert img.shape == (H, W, 3)
        assert img.dtype == np.uint8


def test_background_exact_and_sphere_centred(sphere_images):
    for img in sphere_images:
        corners = img[[0, 0, -1, -1], [0, -1, 0, -1]].astype(int)
        assert np.abs(corners - BG_U8).max() <= 2
        fg = _foreground(img)
        assert fg[H // 2, W // 2]
        # whole object visible: nothing touches the image border
        assert not (fg[0].any() or fg[-1].any() or fg[:, 0].any() or fg[:, -1].any())
        rows, cols = np.nonzero(fg)
        assert abs(cols.mean() - (W - 1) / 2) < 0.05 * W
        assert abs(rows.mean() - (H - 1) / 2) < 0.08 * H
        # framed to a sensible size: the sphere fills a good part of the height
        assert 0.5 * H < np.ptp(rows) < H


def test_shading_is_smooth_and_headlit(sphere_images):
    img = sphere_images[0].astype(float)
    fg = _foreground(sphere_images[0])
    lum = img.mean(axis=2)
    assert lum[fg].std() > 10  # not flat
    dist = ndi.distance_transform_edt(fg)
    # the surface colour is applied: red dominates on the object (off the
    # silhouette, where grazing-angle reflections of the ambient light show)
    inner = dist > 3
    assert np.all(img[inner][:, 0] > img[inner][:, 1] + 20)
    # headlight: the part facing the camera is brighter than the silhouette rim
    rim = fg & (dist <= 3)
    core = dist >= 0.6 * dist.max()
    assert lum[core].mean() > lum[rim].mean() + 20


def test_asymmetric_mesh_silhouettes_and_orientation(two_ball_images):
    front, side, back = (_foreground(im) for im in two_ball_images)
    width = [np.ptp(np.nonzero(m)[1]) for m in (front, side, back)]
    # seen from the front/back both balls are side by side; from the right they overlap
    assert width[0] > 1.4 * width[1] and width[2] > 1.4 * width[1]
    assert ndi.label(front)[1] == 2 and ndi.label(back)[1] == 2
    assert ndi.label(side)[1] == 1

    def small_ball_column(mask):
        labels, _ = ndi.label(mask)
        sizes = np.bincount(labels.ravel())[1:]
        rows, cols = np.nonzero(labels == 1 + np.argmin(sizes))
        return cols.mean()

    # anterior view (azimuth 0): the patient's right is on the image left
    assert small_ball_column(front) < W / 2
    assert small_ball_column(back) > W / 2
    assert not np.array_equal(front, side)


def test_render_from_worker_thread_matches(sphere_mesh, sphere_images):
    with ThreadPoolExecutor(max_workers=1) as pool:
        images = pool.submit(_render, sphere_mesh, (0.0,)).result()
    assert np.abs(images[0].astype(int) - sphere_images[0].astype(int)).max() <= 2


def test_renderer_failure_is_reported():
    with pytest.raises(RuntimeError, match="offscreen rendering failed"):
        _run_worker({"nonsense": np.zeros(1)}, 120.0)


# ---------------------------------------------------------------------------
# vertex normals
# ---------------------------------------------------------------------------

OCTA_V = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float
)
OCTA_F = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
)


def test_vertex_normals_of_octahedron_are_radial():
    n = vertex_normals(Mesh(OCTA_V, OCTA_F))
    np.testing.assert_allclose(n, OCTA_V, atol=1e-12)


def test_vertex_normals_are_unweighted():
    # vertex 0 shared by a tiny face in the plane z = 0 and a big one in x = 0
    v = np.array([[0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0], [0, 5, 0], [0, 0, 5]], float)
    f = np.array([[0, 1, 2], [0, 3, 4]])
    n = vertex_normals(Mesh(v, f))
    np.testing.assert_allclose(n[0], np.array([1.0, 0.0, 1.0]) / np.sqrt(2), atol=1e-12)


def _naive_vertex_normals(v, f):
    out = np.zeros_like(v)
    for a, b, c in f:
        nrm = np.cross(v[b] - v[a], v[c] - v[a])
        nrm = nrm / np.linalg.norm(nrm)
        for i in (a, b, c):
            out[i] += nrm
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def test_vertex_normals_match_naive_reference(sphere_mesh):
    got = vertex_normals(sphere_mesh)
    want = _naive_vertex_normals(sphere_mesh.vertices, sphere_mesh.faces)
    np.testing.assert_allclose(got, want, atol=1e-12)
    # outward on the sphere
    radial = sphere_mesh.vertices - sphere_mesh.vertices.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", got, radial) > 0)


def test_vertex_normals_fallback_for_unused_vertex():
    v = np.vstack([OCTA_V, [[5.0, 5.0, 5.0]]])
    n = vertex_normals(Mesh(v, OCTA_F))
    np.testing.assert_allclose(n[6], [0.0, 0.0, 1.0])


# ---------------------------------------------------------------------------
# validation (no rendering happens)
# ---------------------------------------------------------------------------

_OCTA = Mesh(OCTA_V, OCTA_F)


@pytest.mark.parametrize(
    ("mesh", "kwargs", "match"),
    [
        ((OCTA_V, OCTA_F), {}, "tumor3d.mesh.Mesh"),
        (Mesh(np.zeros((0, 3)), np.zeros((0, 3), int)), {}, "empty mesh"),
        (_OCTA, {"width": 64.0}, "width must be an integer"),
        (_OCTA, {"height": 8}, r"height must lie in \[16, 8192\]"),
        (_OCTA, {"azimuths_deg": ["a"]}, "sequence of numbers"),
        (_OCTA, {"azimuths_deg": ()}, "non-empty sequence"),
        (_OCTA, {"elevation_deg": 90.0}, "elevation_deg must lie strictly between"),
        (_OCTA, {"field_of_view_deg": None}, "field_of_view_deg must be a number"),
        (_OCTA, {"color_rgb": (1.0, 0.5)}, "color_rgb must be 3 numbers"),
        (_OCTA, {"background_rgb": (1.0, 2.0, 0.0)}, "background_rgb must be 3 numbers"),
        (_OCTA, {"timeout_s": 0.0}, "timeout_s must lie strictly between"),
    ],
)
def test_render_views_validation(mesh, kwargs, match):
    with pytest.raises(InputError, match=match):
        _render(mesh, (0.0,), **kwargs)


def test_vertex_normals_rejects_non_mesh():
    with pytest.raises(InputError, match="tumor3d.mesh.Mesh"):
        vertex_normals(OCTA_V)


def test_importing_render_does_not_import_open3d():
    import subprocess
    import sys

    code = "import sys, tumor3d.render; sys.exit('open3d' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0

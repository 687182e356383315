"""Tests of tumor3d.visual.render: the tumour inside a translucent brain, cut-aways, labels.

Most tests use the numpy (numba z-buffer) renderer, which is exact and fast;
the Open3D tests need a working offscreen renderer (open3d with Mesa) and
fail, not skip, where it is missing.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from io import BytesIO

import numpy as np
import pytest
from PIL import Image, ImageDraw
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import extract_surface
from tumor3d.visual.render import (
    ANATOMICAL_VIEWS,
    render_views,
    turntable_gif,
    vertex_normals,
)
from tumor3d.visual.render.annotate import _font
from tumor3d.visual.render.offscreen import _run_worker
from tumor3d.visual.render.scene import _clip_by_plane, _surface_centroid, _vertex_normals

BG = (0.2, 0.4, 0.6)
BG_U8 = np.round(np.array(BG) * 255).astype(int)  # (51, 102, 153)
COLOR = (0.85, 0.35, 0.3)
BRAIN = (0.75, 0.75, 0.8)
W, H = 200, 150
# The tumour: 14 mm to the patient's right, 8 mm anterior, 6 mm superior.
TUMOR_CENTRE = (14.0, 8.0, 6.0)


def _ellipsoid_mask(centre, radii, size, spacing=1.0):
    c = (size - 1) / 2
    z, y, x = np.ogrid[:size, :size, :size]
    pts = [(x - c) * spacing, (y - c) * spacing, (z - c) * spacing]
    q = sum(((p - m) / r) ** 2 for p, m, r in zip(pts, centre, radii, strict=True))
    aff = np.diag([spacing, spacing, spacing, 1.0])
    aff[:3, 3] = -c * spacing
    return q <= 1.0, aff


def _balls_mask(balls, size=48):
    mask = np.zeros((size, size, size), dtype=bool)
    aff = None
    for centre, r in balls:
        m, aff = _ellipsoid_mask(centre, (r, r, r), size)
        mask |= m
    return mask, aff


def _render(mesh, **kw):
    params = {
        "width": W,
        "height": H,
        "color_rgb": COLOR,
        "brain_color_rgb": BRAIN,
        "background_rgb": BG,
        "turntable_frames": 0,
        "renderer": "numpy",
        **kw,
    }
    return render_views(mesh, **params)


def _foreground(img):
    return np.abs(img.astype(int) - BG_U8).max(axis=2) > 2


def _reddish(img):
    """Pixels of the tumour colour (red clearly above green and blue)."""
    rgb = img.astype(int)
    return (rgb[..., 0] > rgb[..., 1] + 40) & (rgb[..., 0] > rgb[..., 2] + 40)


@pytest.fixture(scope="module")
def brain_mesh():
    mask, aff = _ellipsoid_mask((0.0, 0.0, 0.0), (28.0, 32.0, 24.0), 70)
    return extract_surface(mask, aff)


@pytest.fixture(scope="module")
def tumor_mesh():
    mask, aff = _ellipsoid_mask(TUMOR_CENTRE, (7.0, 7.0, 7.0), 70)
    return extract_surface(mask, aff)


@pytest.fixture(scope="module")
def scene(tumor_mesh, brain_mesh):
    return _render(tumor_mesh, brain=brain_mesh, cutaways=("axial", "coronal", "sagittal"))


@pytest.fixture(scope="module")
def scene_plain(tumor_mesh, brain_mesh):
    return _render(
        tumor_mesh, brain=brain_mesh, cutaways=("axial", "coronal", "sagittal"), annotate=False
    )


@pytest.fixture(scope="module")
def sphere_mesh():
    mask, aff = _balls_mask([((0.0, 0.0, 0.0), 10.0)], size=26)
    return extract_surface(mask, aff)


# ---------------------------------------------------------------------------
# structure, non-blank, placement
# ---------------------------------------------------------------------------


def test_result_structure(scene):
    names = list(ANATOMICAL_VIEWS) + ["cut_axial", "cut_coronal", "cut_sagittal"]
    assert list(scene.images) == names
    for img in scene.images.values():
        assert img.shape == (H, W, 3) and img.dtype == np.uint8
    assert scene.turntable == ()
    assert set(scene.cameras) == set(names)
    assert scene.info["renderer"] == "numpy" and scene.info["fallback_reason"] is None
    assert scene.info["projection"] == "orthographic"


def test_renders_are_not_blank_and_background_is_exact(scene_plain):
    for name, img in scene_plain.images.items():
        corners = img[[0, 0, -1, -1], [0, -1, 0, -1]].astype(int)
        assert np.abs(corners - BG_U8).max() <= 1, name
        fg = _foreground(img)
        assert 0.2 < fg.mean() < 0.9, name
        # the framed brain does not touch the border (room for the labels)
        assert not (fg[:3].any() or fg[-3:].any() or fg[:, :3].any() or fg[:, -3:].any()), name


#: Image-right and image-up world axes of each view: (axis, sign), RAS axes 0, 1, 2.
EXPECTED_AXES = {
    "anterior": ((0, -1), (2, 1)),
    "posterior": ((0, 1), (2, 1)),
    "right": ((1, 1), (2, 1)),
    "left": ((1, -1), (2, 1)),
    "superior": ((0, 1), (1, 1)),
    "inferior": ((0, -1), (1, 1)),
    "cut_axial": ((0, 1), (1, 1)),
    "cut_coronal": ((0, -1), (2, 1)),
    "cut_sagittal": ((1, 1), (2, 1)),
}


def test_tumour_appears_where_its_projected_centroid_says(scene_plain):
    # independent of Camera.project: the brain is centred on the origin, so the
    # tumour centre projects to image centre + (its right, -its up) x scale
    for name, ((ax_r, sg_r), (ax_u, sg_u)) in EXPECTED_AXES.items():
        img = scene_plain.images[name]
        scale = scene_plain.cameras[name].pixels_per_mm
        col = (W - 1) / 2 + sg_r * TUMOR_CENTRE[ax_r] * scale
        row = (H - 1) / 2 - sg_u * TUMOR_CENTRE[ax_u] * scale
        red = _reddish(img)
        assert red.sum() > 100, name
        rows, cols = np.nonzero(red)
        assert abs(cols.mean() - col) < 1.5, (name, cols.mean(), col)
        assert abs(rows.mean() - row) < 1.5, (name, rows.mean(), row)
        # and it has the projected size: a 7 mm ball, 14 mm across
        assert abs(np.ptp(cols) + 1 - 14.0 * scale) < 3.0, name
        # Camera.project agrees
        c2, r2, _ = scene_plain.cameras[name].project(np.array([TUMOR_CENTRE]))[0]
        assert abs(c2 - col) < 1e-6 and abs(r2 - row) < 1e-6


def test_anatomical_directions(scene_plain, tumor_mesh):
    # the tumour lies right (+x), anterior (+y), superior (+z) of the centre
    cx, cy = (W - 1) / 2, (H - 1) / 2

    def where(name):
        rows, cols = np.nonzero(_reddish(scene_plain.images[name]))
        return cols.mean() - cx, rows.mean() - cy

    assert where("anterior")[0] < -5  # radiological: patient's right on image left
    assert where("posterior")[0] > 5
    assert where("right")[0] > 3  # seen from the right, anterior is image right
    assert where("left")[0] < -3
    for name in ("anterior", "posterior", "right", "left"):
        assert where(name)[1] < -2  # superior is up
    assert where("superior")[1] < -3 and where("inferior")[1] < -3  # anterior is up
    assert where("superior")[0] > 5 and where("inferior")[0] < -5


def test_scale_is_exact_in_every_view(scene_plain):
    # the brain ellipsoid (radii 28, 32, 24 mm) has a known extent in every view
    radii = np.array([28.0, 32.0, 24.0])
    for name in ANATOMICAL_VIEWS:
        cam = scene_plain.cameras[name]
        fg = _foreground(scene_plain.images[name])
        rows, cols = np.nonzero(fg)
        want_w = 2 * radii[np.argmax(np.abs(cam.right))] * cam.pixels_per_mm
        want_h = 2 * radii[np.argmax(np.abs(cam.up))] * cam.pixels_per_mm
        # marching cubes at 0.5 sits within half a voxel of the analytic surface
        assert abs(np.ptp(cols) + 1 - want_w) < 1.5 * cam.pixels_per_mm + 1, name
        assert abs(np.ptp(rows) + 1 - want_h) < 1.5 * cam.pixels_per_mm + 1, name


def test_translucent_brain_tints_the_tumour(tumor_mesh, brain_mesh):
    alone = _render(tumor_mesh, views=("anterior",), cutaways=(), annotate=False)
    within = _render(tumor_mesh, brain=brain_mesh, views=("anterior",), cutaways=(), annotate=False)
    opaque = _render(
        tumor_mesh,
        brain=brain_mesh,
        views=("anterior",),
        cutaways=(),
        annotate=False,
        brain_opacity=1.0,
    )
    # the same framing is used when the brain is given: compare at the tumour's place
    cam = within.cameras["anterior"]
    col, row, _ = np.rint(cam.project(_surface_centroid(tumor_mesh)[None])[0]).astype(int)
    a = within.images["anterior"][row, col].astype(float)
    o = opaque.images["anterior"][row, col].astype(float)
    assert a[0] - a[1] > 30  # still red through the translucent brain
    assert abs(o[0] - o[1]) < 10  # hidden behind an opaque brain
    # one translucent layer (numpy renderer): out = (1 - a) tumour + a brain, so the
    # tinted pixel lies between the bare tumour's and the opaque brain's
    # behind that pixel the tumour faces the camera: Phong gives color (k_a + k_d) + k_s
    t = 255 * np.clip(np.array(COLOR) * 0.85 + 0.3, 0, 1)
    np.testing.assert_allclose(a, 0.75 * t + 0.25 * o, atol=4.0)
    assert _reddish(alone.images["anterior"]).sum() > 100


# ---------------------------------------------------------------------------
# cut-aways
# ---------------------------------------------------------------------------


def test_cutaway_reveals_the_tumour_and_the_interior(tumor_mesh, brain_mesh):
    res = _render(
        tumor_mesh,
        brain=brain_mesh,
        views=("superior",),
        cutaways=("axial",),
        annotate=False,
        brain_opacity=1.0,
        specular=0.0,
    )
    uncut, cut = res.images["superior"], res.images["cut_axial"]
    # opaque brain hides the tumour; the axial cut through its centroid shows it
    assert _reddish(uncut).sum() == 0
    assert _reddish(cut).sum() > 100
    # the inner wall is drawn in the interior colour (0.7 x brain colour, headlit):
    # a grey darker than any point of the outer surface seen in the uncut view
    fg_cut = _foreground(cut) & ~_reddish(cut)
    fg_uncut = _foreground(uncut)
    lum_cut = cut.astype(float).mean(axis=2)
    lum_uncut = uncut.astype(float).mean(axis=2)
    interior = fg_cut & (lum_cut < 0.72 * lum_uncut[fg_uncut].max())
    assert interior.sum() > 0.5 * fg_cut.sum()
    # facing the camera, the inner floor has the Phong value k_a + k_d of that colour
    cam = res.cameras["cut_axial"]
    centre_col, centre_row, _ = np.rint(cam.project(cam.centre[None])[0]).astype(int)
    floor = cut[centre_row, centre_col].astype(float) / 255
    np.testing.assert_allclose(floor, 0.7 * np.array(BRAIN) * 0.85, atol=0.03)


def test_cutaway_without_brain_clips_the_tumour(tumor_mesh):
    res = _render(tumor_mesh, views=(), cutaways=("coronal",), annotate=False, specular=0.0)
    img = res.images["cut_coronal"]
    cam = res.cameras["cut_coronal"]
    col, row, _ = np.rint(cam.project(_surface_centroid(tumor_mesh)[None])[0]).astype(int)
    # the camera looks into the hollow half-shell: its back wall in the interior colour
    np.testing.assert_allclose(
        img[row, col].astype(float) / 255, 0.7 * np.array(COLOR) * 0.85, atol=0.03
    )


def test_clip_by_plane_is_exact(sphere_mesh):
    v, f = sphere_mesh.vertices, sphere_mesh.faces
    n = _vertex_normals(v, f)
    point = np.array([0.0, 0.0, 2.5])
    normal = np.array([0.0, 0.0, 1.0])
    cv, cn, cf = _clip_by_plane(v, n, f, point, normal)
    assert np.all(cv[:, 2] <= 2.5 + 1e-9)
    assert np.allclose(np.linalg.norm(cn, axis=1), 1.0)

    # the area below the plane is kept exactly: compare with a naive per-face clip
    def area(vv, ff):
        t = vv[ff]
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()

    def naive(tri):
        s = tri[:, 2] - 2.5
        pts = []
        for i in range(3):
            a, b = tri[i], tri[(i + 1) % 3]
            if s[i] <= 0:
                pts.append(a)
            if (s[i] <= 0) != (s[(i + 1) % 3] <= 0):
                t = s[i] / (s[i] - s[(i + 1) % 3])
                pts.append(a + t * (b - a))
        tot = 0.0
        for k in range(1, len(pts) - 1):
            tot += 0.5 * np.linalg.norm(np.cross(pts[k] - pts[0], pts[k + 1] - pts[0]))
        return tot

    want = sum(naive(v[face]) for face in f)
    assert area(cv, cf) == pytest.approx(want, rel=1e-9)
    # winding preserved: the kept faces' normals still point outward
    fn = np.cross(cv[cf[:, 1]] - cv[cf[:, 0]], cv[cf[:, 2]] - cv[cf[:, 0]])
    assert np.einsum("ij,ij->i", fn, cv[cf].mean(axis=1)).min() > -1e-9


# ---------------------------------------------------------------------------
# lighting (numpy renderer: the Phong formula exactly)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(("ka", "kd", "ks"), [(0.15, 0.7, 0.3), (0.3, 0.5, 0.0)])
def test_phong_value_where_the_surface_faces_the_camera(sphere_mesh, ka, kd, ks):
    res = _render(
        sphere_mesh,
        views=("anterior",),
        cutaways=(),
        annotate=False,
        ambient=ka,
        diffuse=kd,
        specular=ks,
    )
    img = res.images["anterior"]
    cam = res.cameras["anterior"]
    col, row, _ = np.rint(cam.project(np.array([[0.0, 10.0, 0.0]]))[0]).astype(int)
    # N = L = V at the sphere's front pole: I = color (k_a + k_d) + k_s
    want = np.clip(np.array(COLOR) * (ka + kd) + ks, 0, 1)
    np.testing.assert_allclose(img[row, col].astype(float) / 255, want, atol=0.02)
    # and it darkens towards the silhouette (headlight)
    fg = _foreground(img)
    dist = ndi.distance_transform_edt(fg)
    lum = img.astype(float).mean(axis=2)
    assert lum[fg & (dist <= 2)].mean() < lum[dist >= 0.6 * dist.max()].mean() - 20


def _uv_sphere(radius, n_lat=90, n_lon=180):
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    ring = np.stack([np.sin(la) * np.cos(lo), np.sin(la) * np.sin(lo), np.cos(la)], -1)
    v = np.vstack([[0, 0, 1], ring.reshape(-1, 3), [0, 0, -1]]) * radius
    idx = 1 + np.arange((n_lat - 1) * n_lon).reshape(n_lat - 1, n_lon)
    nxt = np.roll(idx, -1, axis=1)
    faces = [np.stack([np.zeros(n_lon, int), idx[0], nxt[0]], 1)]
    for i in range(n_lat - 2):
        faces.append(np.stack([idx[i], idx[i + 1], nxt[i + 1]], 1))
        faces.append(np.stack([idx[i], nxt[i + 1], nxt[i]], 1))
    last = len(v) - 1
    faces.append(np.stack([np.full(n_lon, last), nxt[-1], idx[-1]], 1))
    return Mesh(v, np.concatenate(faces))


def test_phong_profile_matches_the_formula():
    sphere = _uv_sphere(10.0)
    assert vertex_normals(sphere)[0] @ [0, 0, 1] > 0.999
    ka, kd, ks, s = 0.15, 0.7, 0.3, 32.0
    res = _render(sphere, views=("anterior",), cutaways=(), annotate=False)
    img = res.images["anterior"].astype(float) / 255
    scale = res.cameras["anterior"].pixels_per_mm
    row = int(round((H - 1) / 2))
    cols = np.arange(W)
    rho = np.abs(cols - (W - 1) / 2) / scale  # mm from the axis, in the image row
    inside = rho < 0.95 * 10.0
    nl = np.sqrt(1 - (rho[inside] / 10.0) ** 2)  # N.L on a sphere, headlight
    want = np.array(COLOR)[None] * (ka + kd * nl)[:, None]
    want = want + (ks * np.clip(2 * nl**2 - 1, 0, None) ** s)[:, None]
    np.testing.assert_allclose(img[row, cols[inside]], np.clip(want, 0, 1), atol=0.02)


def test_numpy_renders_are_deterministic(tumor_mesh, brain_mesh, scene):
    again = _render(tumor_mesh, brain=brain_mesh, cutaways=("axial", "coronal", "sagittal"))
    for name, img in scene.images.items():
        assert img.tobytes() == again.images[name].tobytes(), name


def test_frame_start_and_8_bit_conversion_are_numpys():
    # the numpy renderer starts each frame and converts it with numba kernels; they
    # must be numpy's ``img[:] = background`` / ``zbuf[:] = inf`` and
    # ``rint(255 img).astype(uint8)``, exact ties (k + 0.5) rounded to even included
    from tumor3d.visual.render.raster import _clear, _to_uint8

    rng = np.random.default_rng(3)
    img = rng.random((40, 30, 3))
    ties = [x for k in range(255) if (x := (k + 0.5) / 255.0) * 255.0 == k + 0.5]
    assert len(ties) > 100
    img.reshape(-1)[: len(ties)] = ties
    img.reshape(-1)[-2:] = (0.0, 1.0)
    out = np.zeros(img.shape, dtype=np.uint8)
    _to_uint8(img, out)
    assert np.array_equal(out, np.rint(img * 255.0).astype(np.uint8))
    background = np.array([0.1, 0.5, 0.9])
    zbuf = rng.random((40, 30))
    _clear(img, background, zbuf)
    assert np.array_equal(img, np.broadcast_to(background, img.shape)) and np.all(zbuf == np.inf)


# ---------------------------------------------------------------------------
# orientation labels and scale bar
# ---------------------------------------------------------------------------


def _label_mask(text, anchor_xy, anchor, size):
    img = Image.new("L", (W, H), 0)
    ImageDraw.Draw(img).text(anchor_xy, text, fill=255, font=_font(size), anchor=anchor)
    return np.asarray(img) > 0


def _drawn_letter(annotated, plain, side):
    """Which of the six letters is drawn at an image edge (best template match)."""
    ink = np.abs(annotated.astype(int) - plain.astype(int)).max(axis=2) > 0
    size = max(10, min(H, W) // 24)
    pad = max(3, size // 4)
    where = {
        "left": ((pad, H / 2), "lm"),
        "right": ((W - 1 - pad, H / 2), "rm"),
        "top": ((W / 2, pad), "mt"),
        "bottom": ((W / 2, H - 1 - pad), "mb"),
    }[side]
    band = np.zeros_like(ink)
    band[int(H / 2 - 2 * size) : int(H / 2 + 2 * size), :] = side in ("left", "right")
    band[:, int(W / 2 - 2 * size) : int(W / 2 + 2 * size)] |= side in ("top", "bottom")
    if side == "left":
        band[:, W // 4 :] = False
    elif side == "right":
        band[:, : 3 * W // 4] = False
    elif side == "top":
        band[H // 4 :] = False
    else:
        band[: 3 * H // 4] = False
    ink &= band

    def iou(letter):
        tpl = _label_mask(letter, *where, size) & band
        return (ink & tpl).sum() / max((ink | tpl).sum(), 1)

    scores = {letter: iou(letter) for letter in "RLAPSI"}
    best = max(scores, key=scores.get)
    assert scores[best] > 0.6, scores
    return best


def _lps_equivalent(mask, aff):
    """The same object stored in LPS voxel order: x and y voxel axes flipped."""
    nz, ny, nx = mask.shape
    flipped = mask[:, ::-1, ::-1]
    lps = aff @ np.array(
        [[-1, 0, 0, nx - 1], [0, -1, 0, ny - 1], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float
    )
    return flipped, lps


@pytest.mark.parametrize("order", ["RAS", "LPS"])
def test_orientation_labels_follow_world_directions(order):
    # a big ball and a small one 20 mm to the patient's right
    mask, aff = _balls_mask([((0.0, 0.0, 0.0), 8.0), ((20.0, 0.0, 0.0), 3.5)])
    if order == "LPS":
        mask, aff = _lps_equivalent(mask, aff)
        assert np.linalg.det(aff[:3, :3]) > 0 and aff[0, 0] < 0  # voxel x runs to the left
    mesh = extract_surface(mask, aff)
    kw = {"views": ("anterior", "superior"), "cutaways": ()}
    annotated = _render(mesh, **kw)
    plain = _render(mesh, annotate=False, **kw)
    for view in ("anterior", "superior"):
        labels, _ = ndi.label(_foreground(plain.images[view]))
        sizes = np.bincount(labels.ravel())[1:]
        small_col = np.nonzero(labels == 1 + np.argmin(sizes))[1].mean()
        right_side = "left" if small_col < W / 2 else "right"
        other = "right" if right_side == "left" else "left"
        a, p = annotated.images[view], plain.images[view]
        assert _drawn_letter(a, p, right_side) == "R", (order, view)
        assert _drawn_letter(a, p, other) == "L", (order, view)
        assert annotated.cameras[view].edge_labels()[right_side] == "R"
    assert _drawn_letter(annotated.images["anterior"], plain.images["anterior"], "top") == "S"
    assert _drawn_letter(annotated.images["superior"], plain.images["superior"], "top") == "A"
    # anterior view is radiological: the patient's right (the small ball) on the image left
    assert annotated.cameras["anterior"].edge_labels()["left"] == "R"


def test_lps_and_ras_inputs_give_the_same_picture():
    mask, aff = _balls_mask([((0.0, 0.0, 0.0), 8.0), ((20.0, 5.0, 0.0), 3.5)])
    a = _render(extract_surface(mask, aff), views=("anterior",), cutaways=())
    b = _render(extract_surface(*_lps_equivalent(mask, aff)), views=("anterior",), cutaways=())
    assert np.mean(_foreground(a.images["anterior"]) != _foreground(b.images["anterior"])) < 0.002


def test_scale_bar_has_the_stated_length(scene, scene_plain):
    img, plain = scene.images["anterior"], scene_plain.images["anterior"]
    ink = np.abs(img.astype(int) - plain.astype(int)).max(axis=2) > 0
    bottom_left = ink[int(0.85 * H) :, : W // 2]
    longest = max(
        max((len(run) for run in "".join("1" if x else "0" for x in row).split("0")), default=0)
        for row in bottom_left
    )
    want = scene.info["scale_bar_mm"] * scene.info["pixels_per_mm"]
    assert abs(longest - want) <= 1.0
    assert scene.info["scale_bar_mm"] in (1, 2, 5, 10, 20, 50, 100)
    assert want <= 0.25 * W


def test_turntable_frames_and_gif(sphere_mesh):
    res = _render(sphere_mesh, views=(), cutaways=("axial",), turntable_frames=6)
    assert len(res.turntable) == 6
    cams = [res.cameras[f"turntable_{k:03d}"] for k in range(6)]
    np.testing.assert_allclose(cams[0].forward[1], -np.cos(np.radians(20.0)), atol=1e-12)
    gif = turntable_gif(res.turntable, frame_ms=80)
    assert gif == turntable_gif(res.turntable, frame_ms=80)
    with Image.open(BytesIO(gif)) as im:
        assert im.format == "GIF" and im.n_frames == 6
        im.seek(3)
        assert im.size == (W, H)
    with pytest.raises(InputError, match="at least one frame"):
        turntable_gif([])


# ---------------------------------------------------------------------------
# Open3D renderer and the fallback
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def open3d_scene(tumor_mesh, brain_mesh):
    return _render(
        tumor_mesh,
        brain=brain_mesh,
        views=("anterior", "right", "superior"),
        cutaways=("axial",),
        renderer="open3d",
        annotate=False,
    )


def test_open3d_renders_the_same_layout(open3d_scene, scene_plain, tumor_mesh):
    assert open3d_scene.info["renderer"] == "open3d"
    centroid = _surface_centroid(tumor_mesh)
    for name, img in open3d_scene.images.items():
        corners = img[[0, 0, -1, -1], [0, -1, 0, -1]].astype(int)
        assert np.abs(corners - BG_U8).max() <= 2, name
        ref = _foreground(scene_plain.images[name])
        fg = _foreground(img)
        assert (fg & ref).sum() / (fg | ref).sum() > 0.95, name
        red = _reddish(img)
        col, row, _ = open3d_scene.cameras[name].project(centroid[None])[0]
        rows, cols = np.nonzero(red)
        assert red.sum() > 100 and abs(cols.mean() - col) < 2.5 and abs(rows.mean() - row) < 2.5


def test_open3d_from_a_worker_thread_is_deterministic(open3d_scene, tumor_mesh, brain_mesh):
    def again():
        return _render(
            tumor_mesh,
            brain=brain_mesh,
            views=("anterior", "right", "superior"),
            cutaways=("axial",),
            renderer="open3d",
            annotate=False,
        )

    with ThreadPoolExecutor(max_workers=1) as pool:
        res = pool.submit(again).result()
    for name, img in open3d_scene.images.items():
        assert img.tobytes() == res.images[name].tobytes(), name


def test_auto_falls_back_to_numpy_and_says_why(monkeypatch, sphere_mesh):
    monkeypatch.setenv("TUMOR3D_RENDER_FAIL", "1")
    res = _render(sphere_mesh, views=("anterior",), cutaways=(), renderer="auto")
    assert res.info["renderer"] == "numpy"
    assert "offscreen rendering failed" in res.info["fallback_reason"]
    ref = _render(sphere_mesh, views=("anterior",), cutaways=(), renderer="numpy")
    assert res.images["anterior"].tobytes() == ref.images["anterior"].tobytes()
    with pytest.raises(RuntimeError, match="simulated renderer failure"):
        _render(sphere_mesh, views=("anterior",), cutaways=(), renderer="open3d")


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
_EMPTY = Mesh(np.zeros((0, 3)), np.zeros((0, 3), int))


@pytest.mark.parametrize(
    ("mesh", "kwargs", "match"),
    [
        ((OCTA_V, OCTA_F), {}, "tumor must be a tumor3d.geometry.mesh.Mesh"),
        (_EMPTY, {}, "empty tumor mesh"),
        (_OCTA, {"brain": _EMPTY}, "empty brain mesh"),
        (_OCTA, {"width": 64.0}, "width must be an integer"),
        (_OCTA, {"height": 8}, r"height must lie in \[64, 4096\]"),
        (_OCTA, {"views": ["front"]}, r"views: unknown name\(s\) \['front'\]"),
        (_OCTA, {"views": "anterior"}, "views must be a sequence of names"),
        (_OCTA, {"cutaways": ["axial", "axial"]}, "cutaways lists a name twice"),
        (_OCTA, {"views": (), "cutaways": ()}, "nothing to render"),
        (_OCTA, {"turntable_frames": -1}, r"turntable_frames must lie in \[0, 360\]"),
        (_OCTA, {"turntable_elevation_deg": 90.0}, "turntable_elevation_deg must lie in"),
        (_OCTA, {"color_rgb": (1.0, 0.5)}, "color_rgb must be 3 numbers"),
        (_OCTA, {"background_rgb": (1.0, 2.0, 0.0)}, "background_rgb must be 3 numbers"),
        (_OCTA, {"brain_opacity": 0.0}, "brain_opacity must lie in"),
        (_OCTA, {"specular": 1.5}, "specular must lie in"),
        (_OCTA, {"shininess": None}, "shininess must be a number"),
        (_OCTA, {"annotate": 1}, "annotate must be True or False"),
        (_OCTA, {"renderer": "vtk"}, "renderer must be one of"),
        (_OCTA, {"timeout_s": 0.0}, "timeout_s must lie strictly between"),
    ],
)
def test_render_views_validation(mesh, kwargs, match):
    with pytest.raises(InputError, match=match):
        _render(mesh, **kwargs)


def test_vertex_normals_rejects_non_mesh():
    with pytest.raises(InputError, match="tumor3d.geometry.mesh.Mesh"):
        vertex_normals(OCTA_V)


def test_importing_render_does_not_import_open3d():
    import subprocess
    import sys

    code = "import sys, tumor3d.visual.render; sys.exit('open3d' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


# ---------------------------------------------------------------------------
# the brain surface from a thick-slice brain mask
# ---------------------------------------------------------------------------


def test_brain_surface_from_thick_slices_matches_the_ellipsoid():
    from tumor3d.geometry.surface import is_watertight, mesh_volume_mm3
    from tumor3d.visual.render import brain_surface

    radii = np.array([40.0, 48.0, 36.0])  # x, y, z mm
    # acquired slices: 1 mm pixels, 5 mm slice step, LPS-like flipped in-plane axes
    nz, ny, nx = 19, 110, 90
    z = (np.arange(nz) - (nz - 1) / 2) * 5.0
    y = -(np.arange(ny) - (ny - 1) / 2)
    x = -(np.arange(nx) - (nx - 1) / 2)
    q = (x[None, None, :] / radii[0]) ** 2 + (y[None, :, None] / radii[1]) ** 2
    mask = q + (z[:, None, None] / radii[2]) ** 2 <= 1.0
    aff = np.diag([-1.0, -1.0, 5.0, 1.0])
    aff[:3, 3] = ((nx - 1) / 2, (ny - 1) / 2, -(nz - 1) / 2 * 5.0)
    brain = brain_surface(mask, aff, spacing_mm=2.0)
    assert is_watertight(brain)
    want = 4 / 3 * np.pi * radii.prod()
    assert mesh_volume_mm3(brain) == pytest.approx(want, rel=0.04)
    # every vertex lies near the analytic surface (within a voxel and a bit)
    r = np.linalg.norm(brain.vertices / radii, axis=1)
    assert np.abs(r - 1).max() < 0.09
    # between slices the shape is interpolated, not a 5 mm staircase (which would put
    # vertices at z = 32.5 mm at the radius of slice 30 or 35, r - 1 ~ +-0.2); the ends
    # are flat at the last slices holding brain (z = +-35 mm)
    assert brain.vertices[:, 2].max() == pytest.approx(35.0, abs=0.5)
    mid = np.abs(brain.vertices[:, 2] - 32.5) < 0.6
    assert mid.sum() > 20 and np.abs(r[mid] - 1).max() < 0.06
    with pytest.raises(InputError, match="brain_mask is empty"):
        brain_surface(np.zeros((3, 4, 4), bool), aff)

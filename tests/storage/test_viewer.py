"""Tests of tumor3d.storage.viewer: the slice-and-3-D viewer page and its shared JavaScript."""

from __future__ import annotations

import hashlib
import html
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
from headless_chromium import needs_chromium, open_page, serious_console_messages

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import extract_surface
from tumor3d.storage.nifti import decode_nifti
from tumor3d.storage.viewer import (
    ASSETS_DIR,
    NIIVUE_FILE,
    NIIVUE_LICENSES_FILE,
    NIIVUE_SHA256,
    NIIVUE_VERSION,
    viewer_assets,
    viewer_html,
    viewer_volume,
    write_viewer_assets,
)

# A head on a thick-slice grid (1.5 x 1.5 x 5 mm), the tumour on the patient's right
# (x > centre: +x is R in RAS) and posterior (y < centre: +y is A).
SHAPE = (24, 96, 96)
AFFINE = np.array([[1.5, 0, 0, -72.0], [0, 1.5, 0, -72.0], [0, 0, 5.0, -60.0], [0, 0, 0, 1]])


@pytest.fixture(scope="module")
def head():
    z, y, x = np.mgrid[: SHAPE[0], : SHAPE[1], : SHAPE[2]]
    skull = ((x - 48) / 44) ** 2 + ((y - 48) / 46) ** 2 + ((z - 12) / 11.5) ** 2 <= 1
    brain = ((x - 48) / 36) ** 2 + ((y - 48) / 38) ** 2 + ((z - 12) / 9) ** 2 <= 1
    tumour = ((x - 66) / 8) ** 2 + ((y - 40) / 8) ** 2 + ((z - 13) / 3) ** 2 <= 1
    rng = np.random.default_rng(3)
    image = 200.0 * skull + 300.0 * brain + 500.0 * tumour + rng.normal(0, 20, SHAPE)
    return {
        "image": image,
        "brain": brain,
        "tumour": tumour,
        "tumour_mesh": extract_surface(tumour, AFFINE),
        "brain_mesh": extract_surface(brain, AFFINE),
    }


def _page(head, **kw):
    args = {
        "brain_zyx": head["brain"],
        "tumour_mesh": head["tumour_mesh"],
        "brain_mesh": head["brain_mesh"],
        "title": "patient <1>",
    }
    args.update(kw)
    return viewer_html(head["image"], AFFINE, head["tumour"], **args)


def _embedded(page: str) -> dict:
    m = re.search(r'<script type="application/json" id="t3d-data">(.*?)</script>', page, re.S)
    assert m is not None
    return json.loads(m.group(1))


def _mm(affine, zyx):
    """RAS mm of (z, y, x) voxel indices, shape (n, 3)."""
    zyx = np.asarray(zyx, dtype=float)
    return (affine[:3, :3] @ zyx[:, ::-1].T).T + affine[:3, 3]


# ---------------------------------------------------------------------------
# the display volume


def test_display_volume_is_the_brain_box_in_the_same_millimetres(head):
    img, (tum, brain), aff = viewer_volume(
        head["image"], AFFINE, [head["tumour"], head["brain"]], margin_mm=10
    )
    assert img.dtype == np.uint8 and tum.shape == brain.shape == img.shape
    # nothing of either mask is cut off, and they land on the same millimetres
    assert tum.sum() == head["tumour"].sum() and brain.sum() == head["brain"].sum()
    for full, small in ((head["tumour"], tum), (head["brain"], brain)):
        assert np.allclose(
            np.sort(_mm(AFFINE, np.argwhere(full)), axis=0),
            np.sort(_mm(aff, np.argwhere(small)), axis=0),
        )
    # the box is the brain's plus 10 mm (7 in-plane voxels of 1.5 mm, 2 slices of 5 mm),
    # clipped to the image: smaller than the image in-plane
    zz, yy, xx = (np.flatnonzero(head["brain"].any(axis=a)) for a in ((1, 2), (0, 2), (0, 1)))
    expect = (
        min(SHAPE[0], zz[-1] + 3) - max(0, zz[0] - 2),
        min(SHAPE[1], yy[-1] + 8) - max(0, yy[0] - 7),
        min(SHAPE[2], xx[-1] + 8) - max(0, xx[0] - 7),
    )
    assert img.shape == expect and img.shape[1] < SHAPE[1]
    # 8-bit display copy: the 0.5th-99.5th percentile range spread over 0..255
    assert img.min() == 0 and img.max() == 255
    assert abs(np.mean(img == 0) - 0.005) < 0.004 and abs(np.mean(img == 255) - 0.005) < 0.004


def test_large_images_are_subsampled_along_the_finest_axis_first(head):
    mask = [np.ones(SHAPE, bool)]  # the whole image is the box
    img, (m,), aff = viewer_volume(head["image"], AFFINE, mask, max_voxels=60_000)
    # 24 x 96 x 96 = 221,184 voxels: the 1.5 mm axes are halved, the 5 mm slices all kept
    assert img.shape == (24, 48, 48) and m.all()
    assert np.allclose(np.linalg.norm(aff[:3, :3], axis=0), [3.0, 3.0, 5.0])
    assert np.allclose(_mm(aff, [[5, 7, 9]]), _mm(AFFINE, [[5, 14, 18]]))
    img2, _, _ = viewer_volume(head["image"], AFFINE, mask, max_voxels=20_000)
    assert np.prod(img2.shape) <= 20_000 and img2.shape[0] == 24  # in-plane 6 and 4.5 mm
    img3, _, aff3 = viewer_volume(head["image"], AFFINE, mask, max_voxels=2_000)
    assert np.prod(img3.shape) <= 2_000 and img3.shape[0] < 24  # then the slices too
    assert np.linalg.norm(aff3[:3, :3], axis=0).min() >= 5.0


def test_without_masks_the_whole_image_is_shown():
    img = np.arange(2 * 3 * 4, dtype=np.int16).reshape(2, 3, 4)
    out, masks, aff = viewer_volume(img, np.eye(4), [np.zeros(img.shape, bool)])
    assert out.shape == img.shape and np.array_equal(aff, np.eye(4))
    assert np.all(np.diff(out.ravel().astype(int)) >= 0)  # monotonic scaling
    const, _, _ = viewer_volume(np.full((2, 2, 2), np.nan), np.eye(4), [])
    assert not const.any()  # no finite value: a black image, not an error


# ---------------------------------------------------------------------------
# the page


def test_page_embeds_the_crop_the_masks_and_the_meshes_and_loads_only_the_shared_script(head):
    page = _page(head)
    assert page == _page(head)  # same inputs, same bytes
    assert page.startswith("<!DOCTYPE html>")
    assert "<title>patient &lt;1&gt;</title>" in page and "patient <1>" not in page
    srcs = re.findall(r'<script[^>]+src="([^"]+)"', page)
    assert srcs == [f"../{ASSETS_DIR}/{NIIVUE_FILE}"]
    assert "http://" not in page and "https://" not in page
    data = _embedded(page)
    img, aff = decode_nifti(__import__("base64").b64decode(data["image"]))
    tum, aff_t = decode_nifti(__import__("base64").b64decode(data["tumour_mask"]))
    brain, _ = decode_nifti(__import__("base64").b64decode(data["brain_mask"]))
    assert img.dtype == np.uint8 and np.array_equal(aff, aff_t)
    assert tum.sum() == head["tumour"].sum() and brain.sum() == head["brain"].sum()
    # the NIfTI (x, y, z) voxels of the tumour are at the input's millimetres
    ijk = np.argwhere(tum > 0)
    got = (aff[:3, :3] @ ijk.T).T + aff[:3, 3]
    assert np.allclose(
        np.sort(got, axis=0), np.sort(_mm(AFFINE, np.argwhere(head["tumour"])), axis=0)
    )
    # the cross-hair starts in the tumour, at the voxel nearest its centre
    tumour_mm = _mm(AFFINE, np.argwhere(head["tumour"]))
    centre = tumour_mm.mean(axis=0)
    assert any(np.allclose(data["centre_mm"], p) for p in tumour_mm)
    assert (
        np.linalg.norm(data["centre_mm"] - centre)
        <= np.linalg.norm(tumour_mm - centre, axis=1).min() + 1e-6
    )
    names = [m["name"] for m in data["meshes"]]
    assert names == ["tumour surface", "brain surface"]
    b64 = __import__("base64").b64decode
    for m, mesh in zip(data["meshes"], (head["tumour_mesh"], head["brain_mesh"]), strict=True):
        v = np.frombuffer(b64(m["vertices"]), "<f4").reshape(-1, 3)
        f = np.frombuffer(b64(m["faces"]), "<u2" if m["index_bytes"] == 2 else "<u4")
        assert np.allclose(v, mesh.vertices, atol=0.006)
        assert np.array_equal(f.reshape(-1, 3), mesh.faces)


def test_the_cross_hair_starts_inside_a_tumour_of_two_parts(head):
    two = np.zeros(SHAPE, bool)
    two[10:14, 30:40, 20:30] = True
    two[10:14, 30:40, 60:70] = True  # the centroid lies between them, outside the mask
    data = _embedded(viewer_html(head["image"], AFFINE, two))
    inside = _mm(AFFINE, np.argwhere(two))
    assert any(np.allclose(data["centre_mm"], p) for p in inside)


def test_the_display_convention_is_a_choice(head):
    assert _embedded(_page(head))["radiological"] is True
    page = _page(head, radiological=False)
    assert _embedded(page)["radiological"] is False
    assert 'id="t3d-radiological">' in page and 'id="t3d-radiological" checked>' in _page(head)


def test_page_without_brain_or_meshes(head):
    page = viewer_html(head["image"], AFFINE, np.zeros(SHAPE, bool))
    data = _embedded(page)
    assert "brain_mask" not in data and data["meshes"] == [] and data["centre_mm"] is None
    assert 'id="t3d-brainmask"' not in page


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"tumour_zyx": np.zeros((2, 2, 2), bool)}, "tumour mask has shape"),
        ({"brain_zyx": np.zeros((2, 2, 2), bool)}, "brain mask has shape"),
        ({"affine": np.zeros((4, 4))}, "affine"),
        ({"tumour_mesh": np.zeros((3, 3))}, "tumour_mesh must be a tumor3d.geometry.mesh.Mesh"),
        ({"brain_opacity": 0.0}, "brain_opacity"),
        ({"tumor_color_rgb": (2, 0, 0)}, "tumor_color_rgb"),
        ({"assets_href": "https://cdn.example/x"}, "relative URL"),
        ({"assets_href": "/abs"}, "relative URL"),
        ({"max_voxels": 0}, "max_voxels"),
        ({"radiological": "yes"}, "radiological must be True or False"),
        ({"margin_mm": -1.0}, "margin_mm"),
        ({"image_zyx": np.zeros((3, 3)), "tumour_zyx": np.zeros((3, 3))}, "3-D"),
    ],
)
def test_bad_input_is_an_input_error(head, kwargs, match):
    args = {"image_zyx": head["image"], "affine": AFFINE, "tumour_zyx": head["tumour"]}
    for k in ("image_zyx", "affine", "tumour_zyx"):
        if k in kwargs:
            args[k] = kwargs.pop(k)
    with pytest.raises(InputError, match=match):
        viewer_html(args["image_zyx"], args["affine"], args["tumour_zyx"], **kwargs)


def test_empty_meshes_are_left_out(head):
    empty = Mesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    data = _embedded(_page(head, tumour_mesh=empty, brain_mesh=None))
    assert data["meshes"] == []


# ---------------------------------------------------------------------------
# the shared JavaScript


def test_the_vendored_script_is_the_recorded_niivue_release():
    files = viewer_assets()
    assert set(files) == {NIIVUE_FILE, NIIVUE_LICENSES_FILE}
    assert NIIVUE_VERSION in NIIVUE_FILE
    assert hashlib.sha256(files[NIIVUE_FILE]).hexdigest() == NIIVUE_SHA256
    assets = Path(__file__).parents[2] / "storage" / "assets"
    readme = (assets / "README.md").read_text()
    assert NIIVUE_SHA256 in readme and f"**{NIIVUE_VERSION}**" in readme
    licences = files[NIIVUE_LICENSES_FILE].decode()
    assert "BSD 2-Clause License" in licences and "Copyright (c) 2021, Niivue" in licences
    assert files[NIIVUE_FILE].startswith(b"(function(")  # the UMD bundle (global `niivue`)


def test_a_broken_installation_is_one_environment_error(monkeypatch, tmp_path):
    import tumor3d.storage.viewer as viewer_mod
    from tumor3d.storage.refs import StoreError

    monkeypatch.setattr(viewer_mod, "NIIVUE_SHA256", "0" * 64)
    with pytest.raises(StoreError, match="is not NiiVue 0.69.0.*reinstall tumor3d"):
        write_viewer_assets(tmp_path)
    assert not (tmp_path / ASSETS_DIR).exists()  # nothing written


def test_assets_are_written_once_and_repaired_when_changed(tmp_path):
    assert write_viewer_assets(tmp_path) == [NIIVUE_FILE, NIIVUE_LICENSES_FILE]
    folder = tmp_path / ASSETS_DIR
    js = folder / NIIVUE_FILE
    assert hashlib.sha256(js.read_bytes()).hexdigest() == NIIVUE_SHA256
    os.utime(js, (1_000_000, 1_000_000))
    assert write_viewer_assets(tmp_path) == []  # identical: not rewritten
    assert js.stat().st_mtime == 1_000_000
    js.write_bytes(b"truncated")
    assert write_viewer_assets(tmp_path) == [NIIVUE_FILE]
    assert hashlib.sha256(js.read_bytes()).hexdigest() == NIIVUE_SHA256
    assert sorted(p.name for p in folder.iterdir()) == sorted([NIIVUE_FILE, NIIVUE_LICENSES_FILE])


# ---------------------------------------------------------------------------
# in the browser


def _status(dom: str) -> dict[str, str]:
    m = re.search(r'<p id="t3d-status"([^>]*)>', dom)
    assert m is not None, dom[-2000:]
    return {k: html.unescape(v) for k, v in re.findall(r'(data-[\w-]+)="([^"]*)"', m.group(1))}


def _status_text(dom: str) -> str:
    """What the status element says (not the page's script, which holds every message)."""
    m = re.search(r'<p id="t3d-status"[^>]*>(.*?)</p>', dom, flags=re.S)
    assert m is not None
    return html.unescape(m.group(1))


def _red(img: np.ndarray) -> np.ndarray:
    """The tumour overlay's colour: red well above green and blue."""
    rgb = img.astype(int)
    return (rgb[..., 0] - rgb[..., 1] > 60) & (rgb[..., 0] - rgb[..., 2] > 60)


#: Headless Chromium's viewport is shorter with --dump-dom than with --screenshot: a fixed
#: pane height gives both runs the same layout, so the DOM's tile boxes fit the screenshot.
_FIXED_PANE = "<style>#t3d-pane { flex: none; height: 560px; }</style></head>"


def _publish(tmp_path: Path, page: str) -> Path:
    folder = tmp_path / "out" / "p1"
    folder.mkdir(parents=True)
    page = page.replace("</head>", _FIXED_PANE, 1)
    (folder / "viewer.html").write_text(page, encoding="utf-8")
    write_viewer_assets(tmp_path / "out")
    return folder / "viewer.html"


@needs_chromium
def _cursor(dom: str) -> str:
    m = re.search(r'<span id="t3d-where">([^<]*)</span>', dom)
    assert m is not None
    return html.unescape(m.group(1))


def test_viewer_shows_the_mask_on_three_planes_beside_the_3d_view(head, tmp_path):
    page = _page(head)
    shown = open_page(_publish(tmp_path, page), tmp_path, size=(1000, 800))
    assert shown.js_errors == []
    assert serious_console_messages(shown.console) == []
    status = _status(shown.dom)
    assert status["data-state"] == "ready", shown.dom[-3000:]
    # what the page read back from the embedded NIfTI: every voxel of both masks
    assert int(status["data-tumour-voxels"]) == int(head["tumour"].sum())
    assert int(status["data-brain-voxels"]) == int(head["brain"].sum())
    assert status["data-meshes"] == "tumour surface,brain surface"
    # the view opens on the tumour: the cursor's voxel is in both masks, at the centre given
    centre = ", ".join(f"{c:.1f}" for c in _embedded(page)["centre_mm"])
    assert _cursor(shown.dom).startswith(f"cursor RAS {centre} mm; MR ")
    assert _cursor(shown.dom).endswith("; tumour mask: yes; brain mask: yes")
    tiles = {t["plane"]: t["box"] for t in json.loads(status["data-tiles"])}
    assert set(tiles) == {"axial", "coronal", "sagittal", "3-D"}
    red = _red(shown.screenshot)
    centre_side = {}
    for plane, (left, top, w, h) in tiles.items():
        box = red[int(top) : int(top + h), int(left) : int(left + w)]
        assert box.sum() > 100, (plane, box.sum())
        cols = np.nonzero(box)[1]
        centre_side[plane] = (cols.mean() - w / 2) / w
    # radiological display (as the overlays and renders): the patient's right on the left
    # of the axial and coronal planes; posterior on the left of the sagittal one
    assert status["data-radiological"] == "true"
    assert centre_side["axial"] < -0.1 and centre_side["coronal"] < -0.1
    assert centre_side["sagittal"] < -0.03
    # outside the four panes nothing is red (the overlay stays inside its planes)
    inside = np.zeros(red.shape, bool)
    for left, top, w, h in tiles.values():
        inside[int(top) : int(top + h) + 1, int(left) : int(left + w) + 1] = True
    assert not (red & ~inside)[60:].any()


@needs_chromium
def test_without_a_tumour_no_plane_shows_red(head, tmp_path):
    page = viewer_html(
        head["image"], AFFINE, np.zeros(SHAPE, bool), brain_zyx=head["brain"],
        brain_mesh=head["brain_mesh"],
    )  # fmt: skip
    shown = open_page(_publish(tmp_path, page), tmp_path, size=(1000, 800))
    assert shown.js_errors == []
    status = _status(shown.dom)
    assert status["data-state"] == "ready" and status["data-tumour-voxels"] == "0"
    assert _cursor(shown.dom).endswith("; tumour mask: no; brain mask: yes")  # in the brain
    tiles = json.loads(status["data-tiles"])
    red = _red(shown.screenshot)
    for t in tiles:
        left, top, w, h = (int(v) for v in t["box"])
        assert red[top : top + h, left : left + w].sum() < 20, t["plane"]


@needs_chromium
def test_a_page_moved_out_of_its_output_folder_says_what_it_misses(head, tmp_path):
    path = tmp_path / "moved" / "viewer.html"
    path.parent.mkdir()
    path.write_text(_page(head), encoding="utf-8")
    shown = open_page(path, tmp_path, budget_ms=3000)
    status = _status(shown.dom)
    assert status["data-state"] == "error"
    said = _status_text(shown.dom)
    assert f"../_assets/{NIIVUE_FILE}" in said and "is missing" in said
    assert "t3d-gl" in shown.dom and 'id="t3d-pane" style="display: none;"' in shown.dom


@needs_chromium
def test_a_browser_without_webgl2_says_so(head, tmp_path):
    no_webgl2 = (
        "<head><script>var g = HTMLCanvasElement.prototype.getContext;"
        "HTMLCanvasElement.prototype.getContext = function (t, o) {"
        "return t === 'webgl2' ? null : g.call(this, t, o); };</script>"
    )
    path = _publish(tmp_path, _page(head).replace("<head>", no_webgl2, 1))
    shown = open_page(path, tmp_path, budget_ms=3000)
    assert shown.js_errors == []
    assert _status(shown.dom)["data-state"] == "error"
    assert "it needs WebGL2" in _status_text(shown.dom)


@needs_chromium
def test_browser_check_catches_a_broken_page(tmp_path):
    # the test harness itself can fail: a page whose script throws
    path = tmp_path / "broken.html"
    path.write_text(
        "<html><head></head><body><script>undefinedFunction();</script></body></html>",
        encoding="utf-8",
    )
    page = open_page(path, tmp_path, budget_ms=2000)
    assert page.js_errors and "undefinedFunction" in page.js_errors[0]

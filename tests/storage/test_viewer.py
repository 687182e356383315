"""Tests of storage.viewer: the self-contained interactive viewer page."""

from __future__ import annotations

import re

import numpy as np
import pytest
from headless_chromium import needs_chromium, open_page, serious_console_messages

from storage.viewer import viewer_html
from tumor3d.errors import InputError
from tumor3d.mesh import Mesh
from tumor3d.surface import extract_surface


def _ellipsoid(centre, radii, size=48):
    c = (size - 1) / 2
    z, y, x = np.ogrid[:size, :size, :size]
    q = ((x - c - centre[0]) / radii[0]) ** 2 + ((y - c - centre[1]) / radii[1]) ** 2
    q = q + ((z - c - centre[2]) / radii[2]) ** 2
    aff = np.eye(4)
    aff[:3, 3] = -c
    return extract_surface(q <= 1.0, aff)


@pytest.fixture(scope="module")
def meshes():
    return _ellipsoid((6.0, 4.0, 3.0), (5.0, 5.0, 5.0)), _ellipsoid((0, 0, 0), (20.0, 22.0, 17.0))


def test_page_is_self_contained_and_deterministic(meshes):
    tumor, brain = meshes
    page = viewer_html(tumor, brain, title="patient <1>")
    assert page == viewer_html(tumor, brain, title="patient <1>")
    assert page.lstrip().lower().startswith("<!doctype html>")
    assert "<title>patient &lt;1&gt;</title>" in page
    # plotly.js is embedded, nothing is fetched from the network
    assert "plotly.js v" in page or "Plotly" in page
    assert not re.search(r"<script[^>]+src=", page)
    assert "cdn.plot.ly" not in page.split("</script>")[-1]
    assert "patient &lt;1&gt;" in page and "patient <1>" not in page
    # both surfaces are there, toggle buttons too
    assert '"name":"tumour"' in page and '"name":"brain"' in page
    assert "tumour only" in page
    # face indices as uint16 typed arrays (the meshes have < 65,536 vertices), not int32
    assert page.count('"dtype":"u2"') == 6 and '"dtype":"i4"' not in page


def test_plotlyjs_is_embedded_compressed_and_unpacks_to_plotlyjs(meshes):
    import base64
    import gzip

    from plotly.offline import get_plotlyjs

    page = viewer_html(*meshes)
    packed = re.search(r'<script type="application/octet-stream" id="t3d-plotlyjs">([^<]+)<', page)
    assert packed is not None
    assert gzip.decompress(base64.b64decode(packed.group(1))).decode() == get_plotlyjs()
    plain = viewer_html(*meshes, compress_plotlyjs=False)
    assert get_plotlyjs() in plain and "t3d-plotlyjs" not in plain
    assert len(page) < 0.5 * len(plain)
    # the figure is the same in both: only the way plotly.js travels differs
    assert re.search(r"Plotly\.newPlot\(", page) and re.search(r"Plotly\.newPlot\(", plain)


def test_tumour_only_page(meshes):
    page = viewer_html(meshes[0])
    assert '"name":"tumour"' in page and '"name":"brain"' not in page


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        ((np.zeros((3, 3)),), {}, "tumor must be a tumor3d.mesh.Mesh"),
        ((Mesh(np.zeros((0, 3)), np.zeros((0, 3), int)),), {}, "tumor mesh is empty"),
        ((None,), {"brain_opacity": 0.0}, "brain_opacity"),
        ((None,), {"decimals": 9}, "decimals"),
        ((None,), {"tumor_color_rgb": (2, 0, 0)}, "tumor_color_rgb"),
    ],
)
def test_validation(meshes, args, kwargs, match):
    args = tuple(meshes[0] if a is None else a for a in args)
    with pytest.raises(InputError, match=match):
        viewer_html(*args, **kwargs)


def _colourful(img):
    rgb = img.astype(int)
    return (rgb.max(axis=2) - rgb.min(axis=2)) > 60


@needs_chromium
@pytest.mark.parametrize("compress", [True, False])
def test_viewer_loads_in_headless_chromium_and_shows_the_mesh(meshes, tmp_path, compress):
    tumor, brain = meshes
    path = tmp_path / "viewer.html"
    path.write_text(viewer_html(tumor, brain, compress_plotlyjs=compress), encoding="utf-8")
    page = open_page(path, tmp_path)
    assert page.js_errors == []
    assert serious_console_messages(page.console) == []
    # plotly built its WebGL scene
    assert 'class="gl-container"' in page.dom or "gl-canvas" in page.dom
    # the screenshot shows the red tumour (saturated pixels), not a blank page
    red = _colourful(page.screenshot) & (page.screenshot[..., 0] > page.screenshot[..., 1] + 40)
    assert red.sum() > 200, red.sum()
    rows, cols = np.nonzero(red)
    h, w = red.shape
    assert 0.1 * w < cols.mean() < 0.9 * w and 0.1 * h < rows.mean() < 0.9 * h


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
    assert not _colourful(page.screenshot).any()


@needs_chromium
def test_a_browser_without_decompression_says_so(meshes, tmp_path):
    page = viewer_html(*meshes).replace(
        "<head>", "<head><script>window.DecompressionStream = undefined;</script>", 1
    )
    path = tmp_path / "old_browser.html"
    path.write_text(page, encoding="utf-8")
    shown = open_page(path, tmp_path, budget_ms=3000)
    assert shown.js_errors == []
    assert "cannot unpack the embedded 3-D viewer" in shown.dom
    assert not _colourful(shown.screenshot).any()  # no plot, and not a silent blank either

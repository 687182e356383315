"""Tests of tumor3d.storage.report_html: patient report, markdown summary, cohort page."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import numpy as np
import pytest
from headless_chromium import (
    needs_chromium,
    open_page,
    serious_console_messages,
    unresolved_links,
)

from tumor3d.errors import InputError
from tumor3d.geometry.surface import extract_surface
from tumor3d.storage.formats import encode_png
from tumor3d.storage.report_html import (
    EQ7_PRECISION_DEFINITION,
    VOLUME_DEFINITIONS,
    cohort_report_html,
    patient_report_html,
    patient_report_markdown,
    patient_summary_table,
)
from tumor3d.visual.render import render_views, turntable_gif


def _data(**extra):
    data = {
        "patient_id": "pat<01>",
        "status": "ok",
        "volumes_mm3": {"eq7": 12345.6, "voxel": 12000.0, "mesh": 11890.25},
        "measurements": {"longest diameter": "31.2 mm"},
        "n_slices": 24,
        "abnormal_slices": [9, 10, 11],
        "slab_height_mm": 6.5,
        "faces_before": 25000,
        "faces_after": 10000,
        "stage_seconds": {"segment": 1.25, "render-views": 0.75},
        "renders": {"anterior": "render_anterior.png", "cut_axial": "render_cut_axial.png"},
        "turntable": "render_turntable.gif",
        "overlays": {"tumour contour": "overlay_tumor.png"},
        "viewer": "viewer.html",
        "provenance": {"renderer": "numpy", "versions": {"tumor3d": "0.1.0"}},
    }
    data.update(extra)
    return data


class _Collector(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags, self.imgs, self.links, self.text = [], [], [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a["src"])
        if tag == "a":
            self.links.append(a["href"])

    def handle_data(self, data):
        self.text.append(data)


def _parse(page):
    c = _Collector()
    c.feed(page)
    return c, " ".join(c.text)


def test_patient_report_contents():
    page = patient_report_html(_data())
    c, text = _parse(page)
    assert "script" not in c.tags  # no JavaScript
    assert "pat<01>" in text and "<01>" not in page  # escaped
    # the three estimators in mm3 and mL, with their definitions
    assert "12,345.6" in text and "12.346" in text
    assert "12,000.0" in text and "12.000" in text
    assert "11,890.2" in text or "11,890.3" in text
    for key in ("eq7", "voxel", "mesh"):
        assert VOLUME_DEFINITIONS[key][1] in text
    assert "3 (9, 10, 11)" in text and "24" in text
    # the detection's flags are named as such, not as the slices with tumour (an audit
    # read "Abnormal slices: 11" beside 8 slices with tumour as a contradiction)
    assert "Slices flagged abnormal (detection) 3 (9, 10, 11)" in text
    assert "25000" in text and "10000" in text
    assert "2.00" in text  # total stage time
    assert c.imgs == [
        "render_anterior.png",
        "render_cut_axial.png",
        "render_turntable.gif",
        "overlay_tumor.png",
    ]
    assert c.links == ["viewer.html"]
    assert '"renderer": "numpy"' in text


def test_no_tumour_is_said_first_in_words_and_only_then():
    _, text = _parse(patient_report_html(_data(tumour_found=False, n_slices=31)))
    text = re.sub(r"\s+", " ", text)
    assert "No tumour found on any of the 31 acquired slices" in text
    assert text.index("No tumour found") < text.index("Volume")
    _, found = _parse(patient_report_html(_data(tumour_found=True)))
    assert "No tumour found" not in found


def test_precision_cache_hits_counts_and_notes():
    data = _data(
        eq7_precision={"ce": 0.0412, "ci95_low_mm3": 11348.9, "ci95_high_mm3": 13342.3},
        stage_cached={"segment": True, "render-views": False},
        slice_counts={"Slices summed by Eq. 7": 5},
        notes=["skipped 1 unreadable file(s): x.dcm"],
    )
    c, text = _parse(patient_report_html(data))
    assert "11,348.9 to 13,342.3 (CE 4.1 %)" in text  # in the Eq. 7 row
    assert "11.349 to 13.342 mL" in text
    assert EQ7_PRECISION_DEFINITION in text
    assert "cache hit" in text and "computed" in text
    assert "Slices summed by Eq. 7" in text and "x.dcm" in text
    assert text.index("Notes:") < text.index("x.dcm")  # headed, not under "What is measured"
    md = patient_report_markdown(data)
    assert "CE 4.1 %, 95 % interval 11,348.9 to 13,342.3 mm³" in md
    assert "| segment | 1.25 | cache hit |" in md and "| render-views | 0.75 | computed |" in md
    rows = {r["quantity"]: r["value"] for r in patient_summary_table(data)}
    assert rows["Eq. 7 coefficient of error"] == "0.0412"
    assert rows["Eq. 7 95 % interval, high"] == "13,342.3"
    with pytest.raises(InputError, match="low <= high"):
        patient_report_html(_data(eq7_precision={"ce": 0.1, "ci95_low_mm3": 2, "ci95_high_mm3": 1}))


def test_markdown_summary_has_the_same_numbers():
    md = patient_report_markdown(_data())
    assert md.startswith("# Tumour reconstruction: pat<01>")
    assert "| Eq. 7 (slab sum) | 12,345.6 | 12.346 |" in md
    assert "| Voxel count | 12,000.0 | 12.000 |" in md
    assert "Abnormal slices: 3 (9, 10, 11)" in md
    assert "| render-views | 0.75 |" in md


def test_summary_table_rows():
    rows = patient_summary_table(_data())
    table = {(r["quantity"], r["unit"]): r["value"] for r in rows}
    assert table[("volume, Eq. 7 (slab sum)", "mm³")] == "12,345.6"
    assert table[("volume, Eq. 7 (slab sum)", "mL")] == "12.346"
    assert table[("abnormal slices", "")] == "3"
    assert table[("time, segment", "s")] == "1.25"
    assert all(set(r) == {"quantity", "value", "unit"} for r in rows)


def test_missing_values_and_nan_show_as_na():
    page = patient_report_html({"patient_id": "p", "volumes_mm3": {"eq7": float("nan")}})
    _, text = _parse(page)
    assert "n/a" in text


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"patient_id": ""}, "patient_id"),
        (_data(volumes_mm3={"bogus": 1.0}), "unknown estimator"),
        (_data(volumes_mm3={"eq7": "big"}), "volumes_mm3.eq7 must be a number"),
        (_data(renders={"a": "../../etc/passwd"}), "relative path inside"),
        (_data(viewer="javascript:alert(1)"), "relative path inside"),
        (_data(abnormal_slices=[-1]), "non-negative integers"),
        (_data(provenance={"x": object()}), "JSON-able"),
    ],
)
def test_patient_report_validation(data, match):
    with pytest.raises(InputError, match=match):
        patient_report_html(data)


def _rows():
    return [
        {
            "patient_id": f"p{k}",
            "status": "ok" if k != 2 else "failed: no brain",
            "volumes_mm3": {"eq7": 1000.0 * (k + 1), "voxel": 900.0 * (k + 1)},
            "thumbnail": f"p{k}/render_anterior.png",
            "report": f"p{k}/report.html",
        }
        for k in range(4)
    ]


def test_cohort_page_rows_links_and_plot():
    page = cohort_report_html(_rows(), title="test cohort")
    c, text = _parse(page)
    assert "4 patient(s)" in text
    assert c.imgs == [f"p{k}/render_anterior.png" for k in range(4)]
    assert c.links == [f"p{k}/report.html" for k in range(4)]
    assert "failed: no brain" in text
    # the distribution plot has one dot per patient, at x proportional to the volume
    cx = [float(x) for x in re.findall(r'<circle cx="([0-9.]+)"', page)]
    assert len(cx) == 4
    steps = np.diff(cx)
    np.testing.assert_allclose(steps, steps[0], rtol=1e-2)  # volumes 1, 2, 3, 4 mL
    assert "4.000" in text  # p3's Eq. 7 volume in mL in the table


@pytest.mark.parametrize(
    "volumes_ml", [[3.1, 12.7, 45.0, 46.2, 80.4], [0.3, 0.35], [5.0] * 30, [0.012], [0.0, 2.0]]
)
def test_cohort_histogram_bins_start_on_the_ticks_and_count_each_dot(volumes_ml):
    """Each tick of the volume axis is a bin edge, labelled with the volume at its x, and
    every patient's dot lies over the bin that counts it."""
    from tumor3d.storage.report_html.cohort import _distribution_svg

    svg = _distribution_svg([(f"p{i}", v) for i, v in enumerate(volumes_ml)])
    ticks = [(float(x), float(label)) for x, label in re.findall(
        r'<text x="([0-9.]+)" y="[0-9.]+" font-size="11" text-anchor="middle">([^<]+)<', svg
    )]  # fmt: skip
    bars = [(float(x), float(w), int(c)) for x, w, c in re.findall(
        r'<rect x="([0-9.]+)" y="[0-9.]+" width="([0-9.]+)" height="[0-9.]+" fill="#d9a39a">'
        r"<title>(\d+) patient", svg
    )]  # fmt: skip
    dots = [float(x) for x in re.findall(r'<circle cx="([0-9.]+)"', svg)]
    assert ticks[0][1] == 0 and ticks[-1][1] >= max(volumes_ml)
    (x0, v0), (x1, v1) = ticks[0], ticks[-1]
    mm_per_ml = (x1 - x0) / (v1 - v0)
    for x, label in ticks:  # labels are the axis' values
        assert x == pytest.approx(x0 + label * mm_per_ml, abs=0.15)
    width = bars[0][1] + 1  # bars are a pixel narrower than their bins
    for x, _ in ticks:  # every tick on a bin edge
        k = (x - x0) / width
        assert k == pytest.approx(round(k), abs=0.02), (x, width)
    assert sum(c for _, _, c in bars) == len(volumes_ml)
    for v, cx in zip(volumes_ml, dots, strict=True):
        assert cx == pytest.approx(x0 + v * mm_per_ml, abs=0.15)
        assert any(bx - 0.15 <= cx <= bx + width + 0.15 for bx, _, _ in bars), (v, cx)


def test_cohort_validation():
    with pytest.raises(InputError, match="sequence of per-patient mappings"):
        cohort_report_html({"patient_id": "p"})
    with pytest.raises(InputError, match="patient_id"):
        cohort_report_html([{"status": "ok"}])


@pytest.fixture(scope="module")
def rendered_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("patient")
    size, c = 48, 23.5
    z, y, x = np.ogrid[:size, :size, :size]
    aff = np.eye(4)
    aff[:3, 3] = -c
    tumor = extract_surface((x - c - 5) ** 2 + (y - c) ** 2 + (z - c) ** 2 <= 36, aff)
    brain = extract_surface(
        ((x - c) / 20) ** 2 + ((y - c) / 22) ** 2 + ((z - c) / 17) ** 2 <= 1, aff
    )
    res = render_views(
        tumor,
        brain=brain,
        width=240,
        height=180,
        views=("anterior",),
        cutaways=("axial",),
        turntable_frames=4,
        renderer="numpy",
    )
    (folder / "render_anterior.png").write_bytes(encode_png(res.images["anterior"]))
    (folder / "render_cut_axial.png").write_bytes(encode_png(res.images["cut_axial"]))
    (folder / "render_turntable.gif").write_bytes(turntable_gif(res.turntable))
    (folder / "overlay_tumor.png").write_bytes(encode_png(np.full((40, 80, 3), 90, np.uint8)))
    (folder / "viewer.html").write_text("<html><body>viewer</body></html>")
    return folder


@needs_chromium
def test_report_loads_in_headless_chromium_and_shows_the_renders(rendered_folder, tmp_path):
    path = rendered_folder / "report.html"
    path.write_text(patient_report_html(_data()), encoding="utf-8")
    page = open_page(path, tmp_path, size=(1000, 1400), budget_ms=3000)
    assert page.js_errors == []
    assert serious_console_messages(page.console) == []
    shot = page.screenshot.astype(int)
    red = (shot[..., 0] > shot[..., 1] + 40) & (shot[..., 0] > shot[..., 2] + 40)
    assert red.sum() > 300  # the tumour in the renders is on screen
    # every image loaded and has pixels, every link resolves to a file beside the page
    assert "Volume" in page.dom and "render_anterior.png" in page.dom
    assert sorted(src for src, _ in page.images) == sorted(
        ["render_anterior.png", "render_cut_axial.png", "render_turntable.gif", "overlay_tumor.png"]
    )
    assert all(width > 0 for _, width in page.images), page.images
    assert unresolved_links(path) == []


@needs_chromium
def test_a_missing_image_is_caught(rendered_folder, tmp_path):
    path = rendered_folder / "report_missing.html"
    path.write_text(patient_report_html(_data(renders={"x": "no_such.png"})), encoding="utf-8")
    page = open_page(path, tmp_path, budget_ms=2000)
    assert any("no_such.png" in e for e in page.js_errors)
    # the checks the published-report tests rely on see it too
    assert dict(page.images)["no_such.png"] == 0
    assert dict(page.images)["render_turntable.gif"] > 0
    assert unresolved_links(path) == ["no_such.png"]


@needs_chromium
def test_cohort_page_loads_in_headless_chromium(rendered_folder, tmp_path):
    rows = [
        {
            "patient_id": "p0",
            "status": "ok",
            "volumes_mm3": {"eq7": 900.0},
            "thumbnail": "render_anterior.png",
            "report": "report.html",
        }
    ]
    path = rendered_folder / "cohort.html"
    path.write_text(cohort_report_html(rows), encoding="utf-8")
    page = open_page(path, tmp_path, budget_ms=2000)
    assert page.js_errors == [] and serious_console_messages(page.console) == []
    shot = page.screenshot.astype(int)
    assert ((shot[..., 0] > shot[..., 1] + 40) & (shot[..., 0] > shot[..., 2] + 40)).sum() > 50
    assert page.images == [("render_anterior.png", 240)]
    assert unresolved_links(path) == []


def test_a_result_to_check_says_so_and_why_in_every_summary():
    reason = "the brain mask (2,886 mL) is larger than any skull: the volume is unreliable"
    data = _data(status="check", review_reasons=[reason],
                 notes=[reason, "brain mask given (m.nii.gz)"])  # fmt: skip
    page = patient_report_html(data)
    assert '<strong class="status-check">check</strong>' in page
    assert page.count("larger than any skull") == 1  # said once, as the reason
    assert "brain mask given (m.nii.gz)" in page
    md = patient_report_markdown(data)
    assert "Status: **check**" in md and f"- Check: {reason}" in md
    assert "Note: brain mask given" in md and md.count("larger than any skull") == 1
    rows = patient_summary_table(data)
    assert {"quantity": "check", "value": reason, "unit": ""} in rows
    ok = patient_report_html(_data())
    assert '<strong class="status-ok">ok</strong>' in ok and "Check before" not in ok


def test_the_pages_name_the_volume_methods_as_the_console_and_the_tables_do():
    """report.html and cohort.html called Eq. 7 "(slices)" where the console, cohort.md and
    the summary said "(slab sum)": one name per method, capitalised in the pages."""
    from tumor3d.storage.derivatives import VOLUME_LABELS
    from tumor3d.storage.report_html import VOLUME_DEFINITIONS

    pages = [label for label, _ in VOLUME_DEFINITIONS.values()]
    assert pages == [label[0].upper() + label[1:] for label in VOLUME_LABELS.values()]

"""Report items of issue 33: renders shown at least 480 px wide, provenance collapsed."""

from __future__ import annotations

from html.parser import HTMLParser

import numpy as np
from headless_chromium import needs_chromium, open_page, serious_console_messages

from tumor3d.storage.formats import encode_png
from tumor3d.storage.report_html import patient_report_html

MAGENTA = (255, 0, 255)


def _data(**extra):
    data = {
        "patient_id": "p1",
        "status": "ok",
        "volumes_mm3": {"eq7": 1000.0},
        "renders": {"anterior": "render_anterior.png", "left": "render_left.png"},
        "provenance": {"versions": {"tumor3d": "0.1.0"}, "marker": "PROVENANCE-TEXT"},
    }
    data.update(extra)
    return data


class _Nesting(HTMLParser):
    """The open tags around each piece of text."""

    def __init__(self):
        super().__init__()
        self.stack, self.found = [], []

    def handle_starttag(self, tag, attrs):
        self.stack.append((tag, dict(attrs)))

    def handle_endtag(self, tag):
        while self.stack and self.stack.pop()[0] != tag:
            pass

    def handle_data(self, data):
        if "PROVENANCE-TEXT" in data:
            self.found.append(list(self.stack))


def test_the_raw_provenance_is_inside_a_closed_details_element():
    parser = _Nesting()
    parser.feed(patient_report_html(_data()))
    assert len(parser.found) == 1
    tags = [t for t, _ in parser.found[0]]
    assert tags[-1] == "pre" and "details" in tags
    details = dict(parser.found[0])["details"]
    assert "open" not in details  # collapsed until clicked


@needs_chromium
def test_renders_are_shown_at_least_480_px_wide(tmp_path):
    folder = tmp_path / "patient"
    folder.mkdir()
    tile = np.zeros((480, 640, 3), np.uint8)
    tile[:] = MAGENTA
    for name in ("render_anterior.png", "render_left.png"):
        (folder / name).write_bytes(encode_png(tile))
    page_path = folder / "report.html"
    page_path.write_text(patient_report_html(_data()), encoding="utf-8")
    page = open_page(page_path, tmp_path, size=(1200, 1400), budget_ms=3000)
    assert page.js_errors == [] and serious_console_messages(page.console) == []
    shot = page.screenshot.astype(int)
    mag = (shot[..., 0] > 200) & (shot[..., 1] < 60) & (shot[..., 2] > 200)
    assert mag.any(), "no render on screen"
    widest = int(mag.sum(axis=1).max())  # both renders side by side on one screen row
    row = mag[int(np.argmax(mag.sum(axis=1)))]
    runs = np.diff(np.concatenate([[0], row.astype(np.int8), [0]]))
    widths = np.flatnonzero(runs == -1) - np.flatnonzero(runs == 1)
    assert widest >= 2 * 470 and all(w >= 470 for w in widths), widths  # 480 px less border
    # the provenance JSON takes no room until opened
    assert "PROVENANCE-TEXT" in page.dom

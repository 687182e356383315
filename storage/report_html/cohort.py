"""The cohort's ``cohort.html`` page.

One row a patient, and the volume distribution as an inline SVG.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from tumor3d.errors import InputError
from tumor3d.storage.report_html.fields import (
    _CSS,
    VOLUME_DEFINITIONS,
    _check_mapping,
    _e,
    _fmt,
    _link,
    _notes,
    _patient_id,
    _status_class,
    _volumes,
)


def _nice_step(span: float, n_intervals: int = 5) -> float:
    """A tick step of 1, 2, 2.5 or 5 times a power of ten giving about ``n_intervals``.

    >>> [_nice_step(s) for s in (1.0, 7.3, 12.0, 130.0, 0.04)]
    [0.2, 2.0, 2.5, 50.0, 0.01]
    """
    raw = span / n_intervals
    power = 10.0 ** math.floor(math.log10(raw))
    return next(m * power for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * power >= raw * (1 - 1e-9))


def _distribution_svg(
    values_ml: list[tuple[str, float]], width: int = 640, height: int = 180
) -> str:
    """A strip plot with a histogram of the Eq. 7 volumes (mL), as inline SVG.

    The axis runs from 0 to a whole number of tick steps (1, 2, 2.5 or 5 times a
    power of ten) and the bins split each step into 1, 2 or 5, so that every
    tick is a bin edge; about ``sqrt(n)`` bins, at most 20.
    """
    if not values_ml:
        return "<p>No volumes to plot.</p>"
    vals = [v for _, v in values_ml]
    step = _nice_step(max(vals) or 1.0)
    n_steps = max(1, math.ceil(max(vals) / step - 1e-9))
    lo, hi = 0.0, n_steps * step
    left, right, top, bottom = 50, 20, 15, 35
    pw, ph = width - left - right, height - top - bottom

    def x(v: float) -> float:
        return left + (v - lo) / (hi - lo) * pw

    wanted = max(n_steps, min(20, math.ceil(math.sqrt(len(vals)))))
    n_bins = n_steps * max(k for k in (1, 2, 5) if n_steps * k <= wanted)
    counts = [0] * n_bins
    for v in vals:
        counts[min(n_bins - 1, int((v - lo) / (hi - lo) * n_bins))] += 1
    cmax = max(counts)
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'role="img" aria-label="distribution of tumour volumes">'
    ]
    bw = pw / n_bins
    for i, c in enumerate(counts):
        if c:
            bh = (ph - 20) * c / cmax
            out.append(
                f'<rect x="{left + i * bw:.1f}" y="{top + ph - bh:.1f}" width="{bw - 1:.1f}" '
                f'height="{bh:.1f}" fill="#d9a39a"><title>{c} patient(s)</title></rect>'
            )
    for pid, v in values_ml:
        out.append(
            f'<circle cx="{x(v):.1f}" cy="{top + 8}" r="4" fill="#b03a2e">'
            f"<title>{_e(pid)}: {v:.3f} mL</title></circle>"
        )
    out.append(
        f'<line x1="{left}" y1="{top + ph}" x2="{left + pw}" y2="{top + ph}" stroke="#333"/>'
    )
    for k in range(n_steps + 1):
        v = lo + k * step
        out.append(
            f'<line x1="{x(v):.1f}" y1="{top + ph}" x2="{x(v):.1f}" y2="{top + ph + 4}" '
            f'stroke="#333"/><text x="{x(v):.1f}" y="{top + ph + 16}" font-size="11" '
            f'text-anchor="middle">{round(v, 9):g}</text>'
        )
    out.append(
        f'<text x="{left + pw / 2}" y="{height - 3}" font-size="12" text-anchor="middle">'
        "tumour volume, Eq. 7 (mL)</text></svg>"
    )
    return "".join(out)


def cohort_report_html(
    rows: Sequence[Mapping[str, Any]], *, title: str = "tumor3d cohort", removed: Sequence[str] = ()
) -> str:
    """The cohort page: one row per patient and a volume distribution plot.

    Parameters
    ----------
    rows : sequence of mapping
        Per patient: ``patient_id``, ``status``, ``volumes_mm3`` (estimator ->
        mm³), ``notes`` (list of str), ``thumbnail`` and ``report`` (relative
        paths), all but the id optional.
    title : str
        Page title.
    removed : sequence of str
        Patients published by an earlier run and no longer in the manifest (their
        folders kept), listed as ``cohort.md`` lists them.

    Returns
    -------
    str
        A complete HTML5 document.
    """
    if isinstance(rows, (str, bytes, Mapping)) or not isinstance(rows, Sequence):
        raise InputError(
            f"rows must be a sequence of per-patient mappings, got {type(rows).__name__}"
        )
    if not isinstance(title, str):
        raise InputError(f"title must be a string, got {type(title).__name__}")
    keys = [
        k
        for k in VOLUME_DEFINITIONS
        if any(k in _check_mapping(r, "row").get("volumes_mm3", {}) for r in rows)
    ]
    head = "".join(f"<th>{_e(VOLUME_DEFINITIONS[k][0])} (mL)</th>" for k in keys)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{_e(title)}</h1><p>{len(rows)} patient(s).</p>",
    ]
    points: list[tuple[str, float]] = []
    table = [f"<table><tr><th>Render</th><th>Patient</th><th>Status</th>{head}<th>Notes</th></tr>"]
    for r in rows:
        pid = _patient_id(r)
        status = str(r.get("status", "ok"))
        vol = {key: v for key, _, v in _volumes(r)}
        thumb = (
            f'<img class="thumb" src="{_link(r["thumbnail"], "thumbnail")}" alt="{_e(pid)}">'
            if r.get("thumbnail")
            else ""
        )
        name = (
            f'<a href="{_link(r["report"], "report")}">{_e(pid)}</a>'
            if r.get("report")
            else _e(pid)
        )
        cells = "".join(
            f"<td class='num'>{_fmt(None if vol.get(k) is None else vol[k] / 1000.0, 3)}</td>"
            for k in keys
        )
        notes = "".join(f"<li>{_e(n)}</li>" for n in _notes(r))
        table.append(
            f"<tr><td>{thumb}</td><td>{name}</td>"
            f'<td class="{_status_class(status)}">{_e(status)}</td>{cells}'
            f'<td class="notes">{"<ul>" + notes + "</ul>" if notes else ""}</td></tr>'
        )
        if vol.get("eq7") is not None:
            points.append((pid, vol["eq7"] / 1000.0))
    table.append("</table>")
    parts.append("<h2>Volume distribution</h2>" + _distribution_svg(points))
    parts.append("<h2>Patients</h2>")
    parts += table
    if removed:
        parts.append(
            f"<h2>Removed from the manifest</h2><p>{len(removed)} patient(s) published by an "
            "earlier run are no longer in the manifest; their folders are kept (not deleted): "
            + _e(", ".join(removed)) + ".</p>"
        )  # fmt: skip
    parts.append("<h2>Definitions</h2><ul>")
    parts += [
        f"<li><b>{_e(VOLUME_DEFINITIONS[k][0])}</b>: {_e(VOLUME_DEFINITIONS[k][1])}</li>"
        for k in keys
    ]
    parts.append("</ul></body></html>")
    return "\n".join(parts) + "\n"

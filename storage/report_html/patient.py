"""The per-patient ``report.html`` page."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from tumor3d.errors import InputError
from tumor3d.storage.report_html.fields import (
    _CSS,
    EQ7_PRECISION_DEFINITION,
    VOLUME_DEFINITIONS,
    _abnormal,
    _check_mapping,
    _e,
    _fmt,
    _link,
    _number,
    _other_notes,
    _patient_id,
    _precision,
    _precision_text,
    _reasons,
    _status_class,
    _volumes,
)


def patient_report_html(data: Mapping[str, Any]) -> str:
    """The per-patient ``report.html`` as a string.

    Parameters
    ----------
    data : mapping
        See the module docstring for the keys.

    Returns
    -------
    str
        A complete HTML5 document; links are relative to the patient folder.

    Raises
    ------
    InputError
        On a missing patient id, a non-numeric volume, an unsafe link.
    """
    data = _check_mapping(data, "report data")
    pid = _patient_id(data)
    status = str(data.get("status", "ok"))
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>tumor3d report: {_e(pid)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>Tumour reconstruction: {_e(pid)}</h1>",
        f'<p>Status: <strong class="{_status_class(status)}">{_e(status)}</strong></p>',
    ]
    if data.get("tumour_found") is False:  # said first, in words: the zeros below follow
        n = data.get("n_slices")
        on = f"any of the {int(n)} acquired slices" if n else "any slice"
        parts.append(
            f"<p><strong>No tumour found</strong> on {on}: every volume below is 0 and "
            "there is no surface to render.</p>"
        )
    reasons = _reasons(data)
    if reasons:
        parts.append(
            "<p>Check before using the result; the tool's own checks doubt it:</p>"
            '<ul class="status-check">' + "".join(f"<li>{_e(n)}</li>" for n in reasons) + "</ul>"
        )
    if data.get("measured"):
        parts.append(f"<p>What is measured: {_e(data['measured'])}</p>")
    read = [
        f"segmentation method {_e(data['method'])}" if data.get("method") else "",
        f"input orientation {_e(data['orientation'])}" if data.get("orientation") else "",
    ]
    if any(read):
        text = "; ".join(r for r in read if r)
        parts.append(f"<p>{text[0].upper()}{text[1:]}.</p>")
    notes = _other_notes(data)
    if notes:  # headed: not read as part of what is measured, just above
        parts.append(
            "<p>Notes:</p><ul>" + "".join(f"<li>{_e(n)}</li>" for n in notes) + "</ul>"
        )
    vols = _volumes(data)
    prec = _precision(data)
    if vols:
        parts.append(
            "<h2>Volume</h2><table><tr><th>Estimator</th><th>mm³</th><th>mL</th>"
            "<th>95 % interval of slice sampling (mm³)</th><th>Definition</th></tr>"
        )
        for key, label, v in vols:
            interval = (
                f"{_fmt(prec[1])} to {_fmt(prec[2])} (CE {100 * prec[0]:.1f} %)"
                if key == "eq7" and prec is not None
                else ""
            )
            parts.append(
                f"<tr><td>{_e(label)}</td><td class='num'>{_fmt(v)}</td>"
                f"<td class='num'>{_fmt(None if v is None else v / 1000.0, 3)}</td>"
                f"<td class='num'>{interval}</td>"
                f"<td>{_e(VOLUME_DEFINITIONS[key][1])}</td></tr>"
            )
        parts.append("</table>")
        if prec is not None:
            parts.append(
                f"<p>Eq. 7 precision: {_e(_precision_text(prec))}. "
                f"{_e(EQ7_PRECISION_DEFINITION)}</p>"
            )
    meas = _check_mapping(data.get("measurements", {}), "measurements")
    if meas:
        parts.append("<h2>Measurements</h2><table>")
        for label, value in meas.items():
            parts.append(f"<tr><th>{_e(label)}</th><td class='num'>{_e(value)}</td></tr>")
        parts.append("</table>")
    abnormal = _abnormal(data)
    rows = []
    if "n_slices" in data:
        rows.append(("Acquired slices", _e(data["n_slices"])))
    if "abnormal_slices" in data:
        shown = ", ".join(str(k) for k in abnormal) if abnormal else "none"
        rows.append(("Slices flagged abnormal (detection)", f"{len(abnormal)} ({_e(shown)})"))
    for label, count in _check_mapping(data.get("slice_counts", {}), "slice_counts").items():
        rows.append((_e(label), _e(count)))
    for key, label in (
        ("slab_height_mm", "Slab height (Eq. 7)"),
        ("slice_thickness_mm", "Slice thickness"),
        ("slice_gap_mm", "Slice gap"),
    ):
        if key in data:
            value = _number(data[key], key)
            said = " (the slices overlap)" if value is not None and value < 0 else ""
            rows.append((label, f"{_fmt(value, 2)} mm{said}"))
    if "faces_before" in data:
        rows.append(("Faces (marching cubes)", _e(data["faces_before"])))
    if "faces_after" in data:
        rows.append(("Faces (simplified)", _e(data["faces_after"])))
    if rows:
        parts.append("<h2>Slices and surface</h2><table>")
        parts += [f"<tr><th>{k}</th><td class='num'>{v}</td></tr>" for k, v in rows]
        parts.append("</table>")
    secs = _check_mapping(data.get("stage_seconds", {}), "stage_seconds")
    cached = _check_mapping(data.get("stage_cached", {}), "stage_cached")
    if secs:
        total = 0.0
        head = "<th>this run</th>" if cached else ""
        parts.append(
            f"<h2>Time per stage</h2><table><tr><th>Stage</th><th>compute (s)</th>{head}</tr>"
        )
        for stage, s in secs.items():
            v = _number(s, f"stage_seconds.{stage}")
            total += v or 0.0
            hit = ""
            if cached:
                hit = f"<td>{'cache hit' if cached.get(stage) else 'computed'}</td>"
            parts.append(f"<tr><td>{_e(stage)}</td><td class='num'>{_fmt(v, 2)}</td>{hit}</tr>")
        parts.append(
            f"<tr><th>total</th><th class='num'>{_fmt(total, 2)}</th>"
            f"{'<th></th>' if cached else ''}</tr></table>"
        )
        if cached:
            parts.append(
                "<p>Compute time is that of the run that computed the stage (kept on cache "
                "hits).</p>"
            )
    renders = _check_mapping(data.get("renders", {}), "renders")
    if renders or data.get("turntable") or data.get("viewer"):
        parts.append("<h2>3-D renders</h2>")
        if data.get("viewer"):
            parts.append(
                f'<p><a href="{_link(data["viewer"], "viewer")}">Open the viewer</a>: the MR '
                "slices with the tumour mask in three planes beside the 3-D view (it loads "
                "its script from the output folder's <code>_assets</code>)</p>"
            )
        parts.append('<div class="grid">')
        for name, path in renders.items():
            parts.append(
                f'<figure><img src="{_link(path, f"renders.{name}")}" alt="{_e(name)} view">'
                f"<figcaption>{_e(name.replace('_', ' '))}</figcaption></figure>"
            )
        if data.get("turntable"):
            parts.append(
                f'<figure><img src="{_link(data["turntable"], "turntable")}" '
                'alt="turntable"><figcaption>turntable</figcaption></figure>'
            )
        parts.append("</div>")
    overlays = _check_mapping(data.get("overlays", {}), "overlays")
    if overlays:
        parts.append("<h2>Slice overlays</h2>")
        for caption, path in overlays.items():
            parts.append(
                f'<figure><img class="wide" src="{_link(path, f"overlays.{caption}")}" '
                f'alt="{_e(caption)}"><figcaption>{_e(caption)}</figcaption></figure>'
            )
    if "provenance" in data:
        try:
            prov = json.dumps(data["provenance"], indent=2, sort_keys=True, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise InputError(f"provenance must be JSON-able: {exc}") from None
        parts.append(
            "<h2>Provenance</h2><details><summary>versions, input digests, configuration "
            f"and stages as recorded in provenance.json</summary><pre>{_e(prov)}</pre></details>"
        )
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"

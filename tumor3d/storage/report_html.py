"""Report pages: ``report.html`` per patient, ``cohort.html``, and a markdown summary.

Pure string builders from plain dicts: no file is read or written here (the
publishing step writes the strings beside the images they link to). Every
value taken from the input is HTML-escaped; image and page links must be
relative paths inside the output folder (no scheme, no ``..``), and are
URL-quoted. The pages use no JavaScript and no network; the cohort's volume
distribution is an inline SVG.

Patient input (:func:`patient_report_html`, :func:`patient_report_markdown`)
--------------------------------------------------------------------------
A mapping with the keys (all but ``patient_id`` optional)::

    patient_id        str
    status            str: "ok", "check" or "failed" (:mod:`tumor3d.segmentation.review`)
    review_reasons    list of str: why a human should check (status "check")
    measured          str, what the mask (every volume) holds, in words
                      (:func:`tumor3d.segmentation.segment.lesion_definition`)
    volumes_mm3       {"eq7": float, "voxel": float, "mesh": float,
                       "mesh_simplified": float}  (any subset; None = n/a)
    eq7_precision     {"ce": float, "ci95_low_mm3": float, "ci95_high_mm3": float}
                      (the predicted coefficient of error of Eq. 7 and its 95 % interval)
    measurements      {label: value-with-unit str or number}  (e.g. RANO diameters)
    notes             list of str
    n_slices          int
    abnormal_slices   list of int (0-based slice indices)
    slab_height_mm    float
    faces_before      int   (marching cubes)
    faces_after       int   (after simplification)
    stage_seconds     {stage name: seconds}
    stage_cached      {stage name: bool}  (the stage was a cache hit this run)
    slice_counts      {label: int}  (e.g. slices with tumour, slices Eq. 7 summed)
    renders           {view name: relative PNG path}  (e.g. "render_anterior.png")
    turntable         relative GIF path
    overlays          {caption: relative PNG path}  (tumour and brain-mask mosaics)
    viewer            relative path of viewer.html
    provenance        JSON-able dict (shown as JSON)

Cohort input (:func:`cohort_report_html`): a sequence of mappings with
``patient_id``, ``status``, ``volumes_mm3`` (as above), ``notes`` (list of
str: why to check, then the other notes), ``thumbnail`` and ``report``
(relative paths).
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Mapping, Sequence
from typing import Any
from urllib.parse import quote

from tumor3d.errors import InputError

__all__ = [
    "EQ7_PRECISION_DEFINITION",
    "VOLUME_DEFINITIONS",
    "cohort_report_html",
    "patient_report_html",
    "patient_report_markdown",
    "patient_summary_table",
]

#: Volume estimators: key -> (label, definition).
VOLUME_DEFINITIONS: dict[str, tuple[str, str]] = {
    "eq7": (
        "Eq. 7 (slices)",
        "V = h · Σᵢ Aᵢ: the tumour area Aᵢ = nᵢ·Δx·Δy on each acquired slice times the "
        "slab height h (slice thickness plus gap), the Cavalieri estimator of the paper's Eq. 7.",
    ),
    "voxel": (
        "Voxel count",
        "Number of tumour voxels in the interpolated mask times the volume of one "
        "interpolated voxel (Δx·Δy·Δz/(m+1)).",
    ),
    "mesh": (
        "Mesh",
        "Volume enclosed by the marching-cubes surface, by the divergence theorem "
        "(Σ over faces of v₀·(v₁×v₂)/6).",
    ),
    "mesh_simplified": (
        "Simplified mesh",
        "Volume enclosed by the simplified surface (same formula).",
    ),
}

#: What the Eq. 7 precision means (shown under the volume table).
EQ7_PRECISION_DEFINITION = (
    "Eq. 7 is the Cavalieri estimator with the slab height as sampling interval; its "
    "coefficient of error (CE) is predicted from the per-slice tumour areas (Gundersen and "
    "Jensen 1987; Garcia-Finana and Cruz-Orive 2000), and the 95 % interval is "
    "V (1 ± 1.96 CE). It is the error of sampling the tumour with slices, not of the "
    "segmentation."
)

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:1.5rem;color:#222}
h1{font-size:1.5rem;margin:0 0 .3rem}h2{font-size:1.15rem;margin:1.6rem 0 .5rem;
border-bottom:1px solid #ddd;padding-bottom:.2rem}
table{border-collapse:collapse;margin:.3rem 0}td,th{border:1px solid #ccc;padding:.25rem .6rem;
text-align:left;vertical-align:top}th{background:#f3f3f3}td.num{text-align:right;
font-variant-numeric:tabular-nums}
.grid{display:flex;flex-wrap:wrap;gap:.6rem}.grid figure{margin:0}
.grid img{width:480px;max-width:100%;border:1px solid #ddd}figcaption{font-size:.95rem;color:#444}
img.wide{max-width:100%;border:1px solid #ddd}pre{background:#f7f7f7;padding:.6rem;
overflow:auto;font-size:.8rem}
details{margin:.3rem 0}summary{cursor:pointer;color:#1a4d8f}
.status-ok{color:#17692b}.status-bad{color:#a31515}
.status-check{color:#8a5a00}td.notes{font-size:.85rem;max-width:40rem}
img.thumb{width:120px}
"""


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _link(path: Any, key: str) -> str:
    """A safe, URL-quoted relative link."""
    if not isinstance(path, str) or not path:
        raise InputError(f"{key} must be a non-empty relative path, got {path!r}")
    parts = path.replace("\\", "/").split("/")
    if ":" in path or path.startswith("/") or ".." in parts:
        raise InputError(f"{key} must be a relative path inside the output folder, got {path!r}")
    return quote(path, safe="/")


def _number(value: Any, key: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{key} must be a number or None, got {value!r}")
    v = float(value)
    if math.isnan(v):
        return None
    if not math.isfinite(v):
        raise InputError(f"{key} must be finite, got {value!r}")
    return v


def _fmt(v: float | None, digits: int = 1) -> str:
    return "n/a" if v is None else f"{v:,.{digits}f}"


def _check_mapping(data: Any, name: str) -> Mapping[str, Any]:
    if not isinstance(data, Mapping):
        raise InputError(f"{name} must be a mapping, got {type(data).__name__}")
    return data


def _volumes(data: Mapping[str, Any]) -> list[tuple[str, str, float | None]]:
    vols = _check_mapping(data.get("volumes_mm3", {}), "volumes_mm3")
    unknown = sorted(set(vols) - set(VOLUME_DEFINITIONS))
    if unknown:
        raise InputError(
            f"volumes_mm3 has unknown estimator(s) {unknown}; known: {list(VOLUME_DEFINITIONS)}"
        )
    return [
        (key, VOLUME_DEFINITIONS[key][0], _number(vols[key], f"volumes_mm3.{key}"))
        for key in VOLUME_DEFINITIONS
        if key in vols
    ]


def _precision(data: Mapping[str, Any]) -> tuple[float, float, float] | None:
    """(CE, 95 % low, 95 % high in mm3) from ``eq7_precision``, or None."""
    if data.get("eq7_precision") is None:
        return None
    p = _check_mapping(data["eq7_precision"], "eq7_precision")
    vals = [_number(p.get(k), f"eq7_precision.{k}") for k in _PRECISION_KEYS]
    if any(v is None for v in vals):
        return None
    ce, lo, hi = (float(v) for v in vals)  # type: ignore[arg-type]
    if ce < 0 or lo > hi:
        raise InputError(f"eq7_precision must have CE >= 0 and low <= high, got {dict(p)}")
    return ce, lo, hi


_PRECISION_KEYS = ("ce", "ci95_low_mm3", "ci95_high_mm3")


def _precision_text(prec: tuple[float, float, float]) -> str:
    ce, lo, hi = prec
    return (
        f"CE {100 * ce:.1f} %, 95 % interval {_fmt(lo)} to {_fmt(hi)} mm³ "
        f"({_fmt(lo / 1000, 3)} to {_fmt(hi / 1000, 3)} mL)"
    )


def _notes(data: Mapping[str, Any]) -> list[str]:
    notes = data.get("notes", [])
    if isinstance(notes, str) or not isinstance(notes, Sequence):
        raise InputError(f"notes must be a list of strings, got {notes!r}")
    return [str(n) for n in notes if str(n)]


def _patient_id(data: Mapping[str, Any]) -> str:
    pid = data.get("patient_id")
    if not isinstance(pid, str) or not pid:
        raise InputError(f"patient_id must be a non-empty string, got {pid!r}")
    return pid


def _status_class(status: str) -> str:
    word = status.lower().split(":")[0].strip()
    if word == "check":
        return "status-check"
    ok = word in ("ok", "done", "completed", "success")
    return "status-ok" if ok else "status-bad"


def _reasons(data: Mapping[str, Any]) -> list[str]:
    """Why a human should check the result (``review_reasons``)."""
    reasons = data.get("review_reasons", [])
    if isinstance(reasons, str) or not isinstance(reasons, Sequence):
        raise InputError(f"review_reasons must be a list of strings, got {reasons!r}")
    return [str(n) for n in reasons if str(n)]


def _other_notes(data: Mapping[str, Any]) -> list[str]:
    """The notes that are not already said as review reasons."""
    reasons = set(_reasons(data))
    return [n for n in _notes(data) if n not in reasons]


def _abnormal(data: Mapping[str, Any]) -> list[int]:
    ab = data.get("abnormal_slices", [])
    if not isinstance(ab, Sequence) or isinstance(ab, str):
        raise InputError(f"abnormal_slices must be a list of slice indices, got {ab!r}")
    out = []
    for k in ab:
        if isinstance(k, bool) or not isinstance(k, int) or k < 0:
            raise InputError(f"abnormal_slices must hold non-negative integers, got {k!r}")
        out.append(int(k))
    return out


# ---------------------------------------------------------------------------
# per patient
# ---------------------------------------------------------------------------


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
    reasons = _reasons(data)
    if reasons:
        parts.append(
            "<p>Check before using the result; the tool's own checks doubt it:</p>"
            '<ul class="status-check">' + "".join(f"<li>{_e(n)}</li>" for n in reasons) + "</ul>"
        )
    if data.get("measured"):
        parts.append(f"<p>What is measured: {_e(data['measured'])}</p>")
    notes = _other_notes(data)
    if notes:
        parts.append("<ul>" + "".join(f"<li>{_e(n)}</li>" for n in notes) + "</ul>")
    vols = _volumes(data)
    prec = _precision(data)
    if vols:
        parts.append(
            "<h2>Volume</h2><table><tr><th>Estimator</th><th>mm³</th><th>mL</th>"
            "<th>95 % interval (mm³)</th><th>Definition</th></tr>"
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
        rows.append(("Abnormal slices", f"{len(abnormal)} ({_e(shown)})"))
    for label, count in _check_mapping(data.get("slice_counts", {}), "slice_counts").items():
        rows.append((_e(label), _e(count)))
    if "slab_height_mm" in data:
        rows.append(
            ("Slab height", f"{_fmt(_number(data['slab_height_mm'], 'slab_height_mm'), 2)} mm")
        )
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


def patient_report_markdown(data: Mapping[str, Any]) -> str:
    """The same summary as markdown (for a Prefect markdown artifact).

    Parameters
    ----------
    data : mapping
        As for :func:`patient_report_html`; images and provenance are left
        out (a Prefect artifact cannot show local files).

    Returns
    -------
    str
        Markdown text with a volume table.
    """
    data = _check_mapping(data, "report data")
    pid = _patient_id(data)

    def md(value: Any) -> str:
        return str(value).replace("|", "\\|").replace("\n", " ")

    lines = [
        f"# Tumour reconstruction: {md(pid)}",
        "",
        f"Status: **{md(data.get('status', 'ok'))}**",
        "",
    ]
    for reason in _reasons(data):
        lines.append(f"- Check: {md(reason)}")
    if _reasons(data):
        lines.append("")
    if data.get("measured"):
        lines += [f"What is measured: {md(data['measured'])}", ""]
    vols = _volumes(data)
    if vols:
        lines += ["| Estimator | mm³ | mL |", "|---|---:|---:|"]
        for _key, label, v in vols:
            lines.append(f"| {label} | {_fmt(v)} | {_fmt(None if v is None else v / 1000, 3)} |")
        lines.append("")
        prec = _precision(data)
        if prec is not None:
            lines += [f"Eq. 7 precision: {_precision_text(prec)}.", ""]
        lines += [
            f"- **{VOLUME_DEFINITIONS[k][0]}**: {VOLUME_DEFINITIONS[k][1]}" for k, _, _ in vols
        ]
        if prec is not None:
            lines.append(f"- **Eq. 7 precision**: {EQ7_PRECISION_DEFINITION}")
        lines.append("")
    for note in _other_notes(data):
        lines.append(f"- Note: {md(note)}")
    for label, value in _check_mapping(data.get("measurements", {}), "measurements").items():
        lines.append(f"- {md(label)}: {md(value)}")
    abnormal = _abnormal(data)
    if "n_slices" in data:
        lines.append(f"- Acquired slices: {md(data['n_slices'])}")
    if "abnormal_slices" in data:
        lines.append(
            f"- Abnormal slices: {len(abnormal)} ({', '.join(map(str, abnormal)) or 'none'})"
        )
    for label, count in _check_mapping(data.get("slice_counts", {}), "slice_counts").items():
        lines.append(f"- {md(label)}: {md(count)}")
    if "faces_before" in data or "faces_after" in data:
        lines.append(
            f"- Faces: {md(data.get('faces_before', 'n/a'))} (marching cubes), "
            f"{md(data.get('faces_after', 'n/a'))} (simplified)"
        )
    secs = _check_mapping(data.get("stage_seconds", {}), "stage_seconds")
    cached = _check_mapping(data.get("stage_cached", {}), "stage_cached")
    if secs:
        if cached:
            lines += ["", "| Stage | s | this run |", "|---|---:|---|"]
        else:
            lines += ["", "| Stage | s |", "|---|---:|"]
        for stage, s in secs.items():
            hit = ""
            if cached:
                hit = f" {'cache hit' if cached.get(stage) else 'computed'} |"
            lines.append(f"| {md(stage)} | {_fmt(_number(s, f'stage_seconds.{stage}'), 2)} |{hit}")
    return "\n".join(lines).rstrip() + "\n"


def patient_summary_table(data: Mapping[str, Any]) -> list[dict[str, str]]:
    """The summary as table rows, for a Prefect table artifact.

    Parameters
    ----------
    data : mapping
        As for :func:`patient_report_html`.

    Returns
    -------
    list of dict
        Rows ``{"quantity": ..., "value": ..., "unit": ...}``: each volume in
        mm³ and mL, slice and face counts, stage times.
    """
    data = _check_mapping(data, "report data")
    rows = [{"quantity": "patient", "value": _patient_id(data), "unit": ""}]
    rows.append({"quantity": "status", "value": str(data.get("status", "ok")), "unit": ""})
    for reason in _reasons(data):
        rows.append({"quantity": "check", "value": reason, "unit": ""})
    if data.get("measured"):
        rows.append({"quantity": "what is measured", "value": str(data["measured"]), "unit": ""})
    for _key, label, v in _volumes(data):
        rows.append({"quantity": f"volume, {label}", "value": _fmt(v), "unit": "mm³"})
        ml = None if v is None else v / 1000.0
        rows.append({"quantity": f"volume, {label}", "value": _fmt(ml, 3), "unit": "mL"})
    prec = _precision(data)
    if prec is not None:
        rows.append(
            {"quantity": "Eq. 7 coefficient of error", "value": f"{prec[0]:.4f}", "unit": ""}
        )
        rows.append({"quantity": "Eq. 7 95 % interval, low", "value": _fmt(prec[1]), "unit": "mm³"})
        rows.append(
            {"quantity": "Eq. 7 95 % interval, high", "value": _fmt(prec[2]), "unit": "mm³"}
        )
    for label, value in _check_mapping(data.get("measurements", {}), "measurements").items():
        rows.append({"quantity": str(label), "value": str(value), "unit": ""})
    abnormal = _abnormal(data)
    if "n_slices" in data:
        rows.append({"quantity": "acquired slices", "value": str(data["n_slices"]), "unit": ""})
    if "abnormal_slices" in data:
        rows.append({"quantity": "abnormal slices", "value": str(len(abnormal)), "unit": ""})
    for label, count in _check_mapping(data.get("slice_counts", {}), "slice_counts").items():
        rows.append({"quantity": str(label), "value": str(count), "unit": ""})
    for key, label in (
        ("faces_before", "faces, marching cubes"),
        ("faces_after", "faces, simplified"),
    ):
        if key in data:
            rows.append({"quantity": label, "value": str(data[key]), "unit": ""})
    for stage, sec in _check_mapping(data.get("stage_seconds", {}), "stage_seconds").items():
        v = _number(sec, f"stage_seconds.{stage}")
        rows.append({"quantity": f"time, {stage}", "value": _fmt(v, 2), "unit": "s"})
    return rows


# ---------------------------------------------------------------------------
# cohort
# ---------------------------------------------------------------------------


def _distribution_svg(
    values_ml: list[tuple[str, float]], width: int = 640, height: int = 180
) -> str:
    """A strip plot with a histogram of the Eq. 7 volumes (mL), as inline SVG."""
    if not values_ml:
        return "<p>No volumes to plot.</p>"
    vals = [v for _, v in values_ml]
    lo, hi = 0.0, max(vals) * 1.05 or 1.0
    left, right, top, bottom = 50, 20, 15, 35
    pw, ph = width - left - right, height - top - bottom

    def x(v: float) -> float:
        return left + (v - lo) / (hi - lo) * pw

    n_bins = max(1, min(20, int(math.ceil(math.sqrt(len(vals))))))
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
    for k in range(6):
        v = lo + (hi - lo) * k / 5
        out.append(
            f'<line x1="{x(v):.1f}" y1="{top + ph}" x2="{x(v):.1f}" y2="{top + ph + 4}" '
            f'stroke="#333"/><text x="{x(v):.1f}" y="{top + ph + 16}" font-size="11" '
            f'text-anchor="middle">{v:.2f}</text>'
        )
    out.append(
        f'<text x="{left + pw / 2}" y="{height - 3}" font-size="12" text-anchor="middle">'
        "tumour volume, Eq. 7 (mL)</text></svg>"
    )
    return "".join(out)


def cohort_report_html(rows: Sequence[Mapping[str, Any]], *, title: str = "tumor3d cohort") -> str:
    """The cohort page: one row per patient and a volume distribution plot.

    Parameters
    ----------
    rows : sequence of mapping
        Per patient: ``patient_id``, ``status``, ``volumes_mm3`` (estimator ->
        mm³), ``notes`` (list of str), ``thumbnail`` and ``report`` (relative
        paths), all but the id optional.
    title : str
        Page title.

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
    parts.append("<h2>Definitions</h2><ul>")
    parts += [
        f"<li><b>{_e(VOLUME_DEFINITIONS[k][0])}</b>: {_e(VOLUME_DEFINITIONS[k][1])}</li>"
        for k in keys
    ]
    parts.append("</ul></body></html>")
    return "\n".join(parts) + "\n"

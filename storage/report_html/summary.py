"""The per-patient markdown summary and its table of values.

``run`` and ``demo`` print them; Prefect shows them as the run's artifact.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from tumor3d.storage.report_html.fields import (
    EQ7_PRECISION_DEFINITION,
    VOLUME_DEFINITIONS,
    _abnormal,
    _check_mapping,
    _fmt,
    _number,
    _other_notes,
    _patient_id,
    _precision,
    _precision_text,
    _reasons,
    _volumes,
)


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
    for key, label in (("method", "Segmentation method"), ("orientation", "Input orientation")):
        if data.get(key):
            lines += [f"{label}: {md(data[key])}", ""]
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
    for key, quantity in (("method", "segmentation method"), ("orientation", "input orientation")):
        if data.get(key):
            rows.append({"quantity": quantity, "value": str(data[key]), "unit": ""})
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

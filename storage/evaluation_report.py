"""``REPORT.md`` and the Bland-Altman plots of an evaluation run.

Tables (one row per patient, one column group per configuration, side by
side):

* cases: group (reference kind, acquisition), image, the run's status (``ok``,
  ``check``: the run's own doubts, or ``failed``); when to check: of the volumes
  off by more than 25 % and of those within 10 %, how many the status flagged;
* Table 2 (as in the paper): slices, reference-abnormal slices, and per
  configuration TP / FN / FP / TN of the published segmentation ("slice has
  tumour"), pooled per group, with recall and specificity; the detector's
  own flags in a second table;
* Table 3 (as in the paper): ``N_g``, ``N_p`` and Eq. 9 per case;
* each evaluation's table per case, of the columns it declares
  (:class:`tumor3d.evaluation.registry.ReportColumns`): for ``segmentation``, Dice
  (mean per-slice Dice on the reference's tumour slices, pooled Dice on the
  acquired slices, 3-D Dice on the reference's grid) and surface distances
  (HD95 and maximum Hausdorff distance, mm);
* volumes: reference volume (mL), signed % error of Eq. 7, voxel and mesh
  volumes; Bland-Altman bias and 95 % limits of agreement (mL and %), one
  PNG per configuration;
* summary per group (the means of the columns each evaluation declares for it);
  registered evaluations; provenance (command, configurations, versions, input
  digests).

Tables 2 and 3 and the volumes are the ``segmentation`` evaluation's own sections.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from tumor3d.evaluation.metrics import SliceConfusion, bland_altman
from tumor3d.evaluation.registry import Evaluation, ReportColumn, ReportColumns
from tumor3d.storage.atomic import atomic_write_bytes
from tumor3d.storage.patient_outputs import split_notes
from tumor3d.storage.versions import versions

__all__ = ["bland_altman_png", "run_status_cell", "write_report"]

_VOLUMES = {
    "volume_eq7_mm3": "Eq. 7",
    "volume_voxel_mm3": "voxel",
    "volume_mesh_mm3": "mesh",
}


def _f(v: Any, fmt: str = "{:.3f}") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)) or v is pd.NA:
        return "–"
    try:
        if pd.isna(v):
            return "–"
    except (TypeError, ValueError):
        pass
    return fmt.format(v)


def _pct(v: Any) -> str:
    return _f(v, "{:+.1f} %")


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _get(df: pd.DataFrame, cfg: str, pid: str, col: str) -> Any:
    sel = df[(df["config"] == cfg) & (df["patient_id"] == pid)]
    if sel.empty or col not in sel.columns:
        return None
    return sel.iloc[0][col]


def run_status_cell(row: Mapping[str, Any]) -> str:
    """A case's status in words, from its ``evaluation.parquet`` row.

    The run's own ``ok`` / ``check``; ``failed (error)`` for a run that failed; a run
    that completed but could not be compared with its reference keeps its status,
    with ``(evaluation failed: error)``.

    Examples
    --------
    >>> run_status_cell({"status": "ok", "run_status": "check"})
    'check'
    >>> run_status_cell({"status": "failed", "run_status": "failed", "error": "no brain"})
    'failed (no brain)'
    >>> run_status_cell({"status": "failed", "run_status": "ok", "error": "no label"})
    'ok (evaluation failed: no label)'
    """
    run = row.get("run_status")
    run = run if isinstance(run, str) and run else None
    if row.get("status") == "ok":
        return run or "ok"
    if run in ("ok", "check"):
        return f"{run} (evaluation failed: {row.get('error')})"
    return f"failed ({row.get('error')})"


def _run_status(df: pd.DataFrame, cfg: str, pid: str) -> str:
    return run_status_cell({k: _get(df, cfg, pid, k) for k in ("status", "run_status", "error")})


def _share(cases: pd.Series, check: pd.Series, what: str) -> str:
    n = int(cases.sum())
    if n == 0:
        return f"none {what}"
    return f"{int((cases & check).sum())} of the {n} volumes {what} flagged `check`"


def _flagged_lines(ok: pd.DataFrame, names: list[str]) -> list[str]:
    """How many volumes the status flagged, per configuration.

    Of the evaluated cases with tumour in the reference: those off by more than 25 %
    (Eq. 7) and those within 10 %, and how many of each have status ``check``.
    """
    col = "volume_eq7_error_percent"
    if col not in ok.columns or "run_status" not in ok.columns:
        return []
    out = []
    for n in names:
        sel = ok[ok["config"] == n]
        if "ref_volume_mm3" in sel.columns:  # a tumour-free reference has no % error
            sel = sel[pd.to_numeric(sel["ref_volume_mm3"], errors="coerce").fillna(0) > 0]
        err = pd.to_numeric(sel[col], errors="coerce").abs()
        check = sel["run_status"] == "check"
        bad, good = err > 25.0, err <= 10.0
        if not (bad.any() or good.any()):
            continue
        out.append(
            f"- {n}: {_share(bad, check, 'off by > 25 %')}; {_share(good, check, 'within 10 %')}"
        )
    return out


def _conf(df: pd.DataFrame, prefix: str = "") -> SliceConfusion:
    cols = [f"{prefix}{k}" for k in ("tp", "fp", "tn", "fn")]
    if not set(cols) <= set(df.columns):
        return SliceConfusion(0, 0, 0, 0)
    d = df[cols].dropna()
    return SliceConfusion(*(int(d[c].sum()) for c in cols))


def bland_altman_png(ok: pd.DataFrame, title: str) -> bytes:
    """A Bland-Altman plot (PNG bytes): difference vs mean, in mL, one marker per method."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    ref = ok["ref_volume_mm3"].to_numpy(dtype=float) / 1000.0
    markers = {"volume_eq7_mm3": "o", "volume_voxel_mm3": "s", "volume_mesh_mm3": "^"}
    for col, label in _VOLUMES.items():
        if col not in ok.columns:
            continue
        est = ok[col].to_numpy(dtype=float) / 1000.0
        ba = bland_altman(est, ref)
        (line,) = ax.plot((est + ref) / 2, est - ref, markers[col], alpha=0.75,
                          label=f"{label}: bias {ba.bias:+.1f} mL")  # fmt: skip
        if ba.n > 1:
            for y, ls in ((ba.bias, "-"), (ba.loa_low, ":"), (ba.loa_high, ":")):
                ax.axhline(y, color=line.get_color(), ls=ls, lw=1)
    ax.axhline(0.0, color="black", lw=0.8)
    ax.set_xlabel("mean of method and reference volume (mL)")
    ax.set_ylabel("method - reference (mL)")
    ax.set_title(title + "\n(solid: mean bias; dotted: 95 % limits of agreement)", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def _cell(df: pd.DataFrame, cfg: str, pid: str, column: ReportColumn) -> str:
    return " / ".join(_f(_get(df, cfg, pid, k), column.fmt) for k in column.keys)


def _case_table(
    df: pd.DataFrame, names: list[str], pids: list[str], shown: ReportColumns, title: str
) -> list[str]:
    """An evaluation's table per case: one cell per configuration and declared column."""
    parts = ["", f"## {shown.title or title}", ""]
    if shown.intro:
        parts += [shown.intro, ""]
    header = ["patient"] + [f"{n}: {c.label}" for n in names for c in shown.table]
    rows = [[pid, *(_cell(df, n, pid, c) for n in names for c in shown.table)] for pid in pids]
    return [*parts, _table(header, rows)]


def _summary_parts(
    ok: pd.DataFrame,
    names: list[str],
    pids: list[str],
    groups: dict[str, str],
    evaluations: Mapping[str, Evaluation],
) -> list[str]:
    """The summary per group: the mean of each column the evaluations declare for it."""
    shown = [c for ev in evaluations.values() for c in ev.columns.summary]
    if not shown:
        return []
    parts = ["", "## Summary per group (mean over the cases of each group)", ""]
    header = ["group", "configuration", "n ok"] + [c.label for c in shown]
    rows = []
    for g in _ordered(groups[p] for p in pids):
        members = [p for p in pids if groups[p] == g]
        for n in names:
            sel = ok[(ok["config"] == n) & ok["patient_id"].isin(members)]
            cells = [" / ".join(_f(_mean(sel, k), c.fmt) for k in c.keys) for c in shown]
            rows.append([g, n, f"{len(sel)}/{len(members)}", *cells])
    return [*parts, _table(header, rows)]


def _evaluation_parts(
    ev: Evaluation,
    df: pd.DataFrame,
    names: list[str],
    pids: list[str],
    groups: dict[str, str],
    out_dir: Path,
) -> list[str]:
    """An evaluation's sections: the segmentation's own, or its table per case, if any."""
    if ev.name == "segmentation":
        return _segmentation_parts(df, names, pids, groups, out_dir, ev.columns)
    return _case_table(df, names, pids, ev.columns, ev.name) if ev.columns.table else []


def _segmentation_parts(
    df: pd.DataFrame,
    names: list[str],
    pids: list[str],
    groups: dict[str, str],
    out_dir: Path,
    shown: ReportColumns,
) -> list[str]:
    """The segmentation evaluation's sections of ``REPORT.md``.

    Tables 2 and 3, its table per case (``shown``: overlap and surface distance) and
    volumes (the Bland-Altman figures written to ``out_dir``).
    """
    parts: list[str] = []
    ok = df[df["status"] == "ok"]
    with_ref = [pid for pid in pids if groups[pid].split(",")[0] != "unspecified"]
    # ---------------------------------------------------------------- Table 2
    parts += ["", "## Table 2: recognition of abnormal slices", ""]
    parts.append("Per configuration: TP / FN / FP / TN (TP: abnormal slice recognised, FN: "
                 "abnormal slice missed, FP: normal slice called abnormal, TN: normal slice "
                 "passed).")  # fmt: skip
    parts.append("")
    header = ["patient", "slices", "abnormal (ref.)"] + [f"{n}: TP / FN / FP / TN" for n in names]
    rows = []
    for pid in with_ref:
        first = next((_get(df, n, pid, "n_slices") for n in names if _get(df, n, pid, "n_slices")
                      is not None), None)  # fmt: skip
        ref_ab = next((int(_get(df, n, pid, "tp")) + int(_get(df, n, pid, "fn")) for n in names
                       if _num(_get(df, n, pid, "tp"))), None)  # fmt: skip
        cells = []
        for n in names:
            if not _num(_get(df, n, pid, "tp")):
                cells.append("–")
                continue
            counts = (int(_get(df, n, pid, k)) for k in ("tp", "fn", "fp", "tn"))
            cells.append(" / ".join(map(str, counts)))
        rows.append([pid, _f(first, "{:.0f}"), _f(ref_ab, "{:d}"), *cells])
    parts.append(_table(header, rows))
    parts += ["", "Pooled per group (recall = TP/(TP+FN), specificity = TN/(TN+FP)):", ""]
    header = (
        ["group"]
        + [f"{n}: TP / FN / FP / TN" for n in names]
        + [f"{n}: recall / specificity" for n in names]
    )
    rows = []
    for g in _ordered(groups[p] for p in with_ref):
        members = [p for p in with_ref if groups[p] == g]
        counts = [_conf(ok[(ok["config"] == n) & ok["patient_id"].isin(members)]) for n in names]
        rows.append([g, *(f"{c.tp} / {c.fn} / {c.fp} / {c.tn}" for c in counts),
                     *(f"{_f(c.sensitivity, '{:.1%}')} / {_f(c.specificity, '{:.1%}')}"
                       for c in counts)])  # fmt: skip
    parts.append(_table(header, rows))
    if "det_tp" in ok.columns:
        parts += ["", "The abnormal-slice detector alone (before segmentation), pooled per group:",
                  ""]  # fmt: skip
        rows = []
        for g in _ordered(groups[p] for p in with_ref):
            members = [p for p in with_ref if groups[p] == g]
            counts = [
                _conf(ok[(ok["config"] == n) & ok["patient_id"].isin(members)], "det_")
                for n in names
            ]
            rows.append([g, *(f"{c.tp} / {c.fn} / {c.fp} / {c.tn}" for c in counts),
                         *(f"{_f(c.sensitivity, '{:.1%}')} / {_f(c.specificity, '{:.1%}')}"
                           for c in counts)])  # fmt: skip
        parts.append(_table(header, rows))

    # ---------------------------------------------------------------- Table 3
    parts += ["", "## Table 3: tumour pixels on the acquired slices (Eq. 9)", ""]
    header = ["patient", "N_g (ref.)"] + [h for n in names for h in (f"{n}: N_p", f"{n}: Eq. 9")]
    rows = []
    for pid in with_ref:
        ng = next((_get(df, n, pid, "n_g") for n in names if _num(_get(df, n, pid, "n_g"))), None)
        cells = []
        for n in names:
            cells += [_f(_get(df, n, pid, "n_p"), "{:.0f}"),
                      _f(_get(df, n, pid, "eq9_percent"), "{:.1f} %")]  # fmt: skip
        rows.append([pid, _f(ng, "{:.0f}"), *cells])
    parts.append(_table(header, rows))

    # ---------------------------------------------------------------- Dice / HD
    tumour_pids = [pid for pid in with_ref if not groups[pid].startswith("tumor_free")]
    parts += _case_table(df, names, tumour_pids, shown, "segmentation")

    # ---------------------------------------------------------------- volumes
    parts += ["", "## Volumes", ""]
    header = ["patient", "reference (mL)"] + [
        f"{n}: {lab} error" for n in names for lab in _VOLUMES.values()
    ]
    rows = []
    for pid in with_ref:
        refv = next((_get(df, n, pid, "ref_volume_mm3") for n in names
                     if _num(_get(df, n, pid, "ref_volume_mm3"))), None)  # fmt: skip
        cells = []
        for n in names:
            for col in _VOLUMES:
                if refv == 0:
                    v = _get(df, n, pid, col)
                    cells.append(_f(None if v is None else v / 1000.0, "{:.2f} mL found"))
                else:
                    cells.append(_pct(_get(df, n, pid, col.replace("_mm3", "_error_percent"))))
        rows.append([pid, _f(None if refv is None else refv / 1000.0, "{:.2f}"), *cells])
    parts.append(_table(header, rows))
    parts += [
        "",
        "Agreement over the cases with tumour in the reference (Bland-Altman: "
        "d = method - reference; bias = mean d; 95 % limits = bias -/+ 1.96 sd):",
        "",
    ]
    header = ["configuration", "method", "n", "bias (mL)", "95 % LoA (mL)", "bias (%)",
              "95 % LoA (%)"]  # fmt: skip
    rows = []
    pngs = []
    for n in names:
        sel = ok[(ok["config"] == n)]
        if "ref_volume_mm3" not in sel.columns:
            continue
        sel = sel[sel["ref_volume_mm3"].fillna(0) > 0]
        for col, lab in _VOLUMES.items():
            if col not in sel.columns or sel.empty:
                continue
            ref = sel["ref_volume_mm3"].to_numpy(dtype=float)
            est = sel[col].to_numpy(dtype=float)
            ba = bland_altman(est / 1000.0, ref / 1000.0)
            bp = bland_altman(100.0 * est / ref, np.full(ref.shape, 100.0))
            rows.append([n, lab, str(ba.n), _f(ba.bias, "{:+.2f}"),
                         f"{_f(ba.loa_low, '{:+.2f}')} to {_f(ba.loa_high, '{:+.2f}')}",
                         _f(bp.bias, "{:+.1f}"),
                         f"{_f(bp.loa_low, '{:+.1f}')} to "
                         f"{_f(bp.loa_high, '{:+.1f}')}"])  # fmt: skip
        if not sel.empty:
            png = f"bland_altman_{n}.png"
            atomic_write_bytes(out_dir / png, bland_altman_png(sel, f"Volume agreement, {n}"))
            pngs.append((n, png))
    parts.append(_table(header, rows))
    for n, png in pngs:
        parts += ["", f"![Bland-Altman, {n}]({png})"]
    return parts


def write_report(
    out_dir: Path,
    patients: pd.DataFrame,
    slices: pd.DataFrame,
    *,
    configs: dict[str, dict[str, Any]],
    config_files: dict[str, str | None],
    prepared: list[Any],
    skipped: list[dict[str, Any]],
    evaluations: Mapping[str, Evaluation],
    command: str | None,
    elapsed_s: float,
) -> Path:
    """Write ``REPORT.md`` and ``bland_altman_<config>.png`` in ``out_dir``; return the former.

    Each of ``evaluations`` (name -> registered evaluation) adds its sections and the
    columns it declares (:class:`tumor3d.evaluation.registry.ReportColumns`).
    """
    del slices  # per-slice rows are in evaluation_slices.parquet
    names = list(configs)
    pids = [p.source.patient_id for p in prepared]
    # one group per kind of reference, acquisition and modality: pooled figures never mix
    # FLAIR with T1c, whose targets differ (whole tumour against rim and core)
    groups = {
        p.source.patient_id: f"{p.reference_kind}, {p.acquisition}, {p.source.modality}"
        for p in prepared
    }
    df = patients if len(patients) else pd.DataFrame(columns=["config", "patient_id", "status"])
    ok = df[df["status"] == "ok"]
    parts: list[str] = ["# Evaluation report", ""]
    parts.append(
        f"Generated {datetime.now(UTC).isoformat(timespec='seconds')} in {elapsed_s:.0f} s; "
        f"configurations: {', '.join(f'`{n}`' for n in names)}."
    )
    parts += ["", "```", command or "(called from Python)", "```", ""]
    parts.append(
        "Definitions: a slice is truly abnormal iff the reference has tumour on it; the "
        "method calls a slice abnormal iff its published segmentation "
        "(`tumor_mask_slices.nii.gz`) has tumour on it. Eq. 9: |N_p - N_g| / N_g x 100 "
        "with N = tumour pixels on the acquired slices. Emulated cases: the image is "
        "resampled to thick slices (mean over the thickness) before the pipeline; the "
        "per-slice reference is emulated the same way (tumour where the mean >= 0.5); the "
        "3-D comparison (3-D Dice, HD) samples the interpolated mask at the full-resolution "
        "reference's voxel centres (nearest neighbour). HD: symmetric distances between "
        "boundary voxels in mm; HD95 = max of the two directed 95th percentiles. Volume "
        "error: (method - reference) / reference x 100, reference = reference voxels x "
        "voxel volume."
    )

    # ---------------------------------------------------------------- cases
    parts += ["", "## Cases", ""]
    rows = []
    for p in prepared:
        pid = p.source.patient_id
        status = ", ".join(f"{n}: {_run_status(df, n, pid)}" for n in names)
        rows.append([pid, groups[pid], p.source.modality, p.source.image.name, status])
    parts.append(_table(["patient", "reference, acquisition", "modality", "image", "status"], rows))
    parts += ["", "Status: the run's own (`ok`; `check`: its doubts or its segmentation's "
              "review ask a human to look, the reasons in `review_reasons` of "
              "`evaluation.parquet`; `failed`)."]  # fmt: skip
    flagged = _flagged_lines(ok, names)
    if flagged:
        parts += ["", "When to check, judged on these cases (Eq. 7 against the reference, "
                  "every case with tumour in it: phantoms and algorithm-made references "
                  "included; the learned method was trained on some of them: its "
                  "cross-validated figures are in `reports/learned_cv.md`):", "",
                  *flagged]  # fmt: skip
    if skipped:
        parts += ["", "Skipped rows:", ""]
        for s in skipped:
            tag = "file absent" if s["missing_file"] else "invalid"
            parts.append(f"- {s['patient_id'] or ('row ' + str(s['row']))} ({tag}): {s['reason']}")
    # the notes each run said about its own result (tumor3d.segmentation.caveats, "no tumour
    # found", a
    # brain mask larger than a skull, ...), one line per configuration and note, with the
    # cases that said it, so that a reader can see whether they point at the worst cases
    noted: dict[tuple[str, str], list[str]] = {}
    for n in names:
        for pid in pids:
            if _get(df, n, pid, "status") != "ok":
                continue
            notes = split_notes(_get(df, n, pid, "notes"))
            # a segmentation's own review reasons are not among the notes: said as well
            reasons = [f"review: {r}" for r in split_notes(_get(df, n, pid, "review_reasons"))
                       if r not in notes]  # fmt: skip
            for note in notes + reasons:
                noted.setdefault((n, note), []).append(pid)
    if noted:
        parts += ["", "Notes of the runs (said by the pipeline itself, without the reference):", ""]
        parts += [f"- {n}, {', '.join(cases)}: {note}" for (n, note), cases in noted.items()]
    algo = [p.source.patient_id for p in prepared if p.reference_kind == "algorithmic"]
    if algo:
        parts += ["", f"**Note:** the reference of {', '.join(algo)} was made by a segmentation "
                  "ALGORITHM, not an expert: agreement with it is not accuracy."]  # fmt: skip

    for ev in evaluations.values():  # a geometry-only run has no segmentation tables to fill
        parts += _evaluation_parts(ev, df, names, pids, groups, out_dir)
    parts += _summary_parts(ok, names, pids, groups, evaluations)

    # ---------------------------------------------------------------- registry
    parts += ["", "## Registered evaluations", ""]
    for ev in evaluations.values():
        parts.append(f"- `{ev.name}`: {ev.description}")
    for ev in evaluations.values():
        if ev.summarize is not None:
            for n in names:
                sel = ok[ok["config"] == n]
                parts += ["", f"### {ev.name} ({n})", "", ev.summarize(sel.to_dict("records"))]

    # ---------------------------------------------------------------- provenance
    parts += ["", "## Provenance", "", "Versions:", "", "```json",
              json.dumps(versions(), indent=2), "```", ""]  # fmt: skip
    parts += ["Input digests (SHA-256 of the files):", ""]
    dig_rows = []
    for p in prepared:
        row = p.source
        ref = "–" if row.reference is None else _sha256(row.reference)[:16]
        run = "–" if p.emulation is None else _sha256(p.run_row.image)[:16]
        dig_rows.append([row.patient_id, row.image.name, _sha256(row.image)[:16] if
                         row.image.is_file() else "(folder)", ref, run])  # fmt: skip
    parts.append(_table(["patient", "image", "image sha256[:16]", "reference sha256[:16]",
                         "emulated image sha256[:16]"], dig_rows))  # fmt: skip
    for n, cfg in configs.items():
        src = config_files.get(n) or "(defaults)"
        parts += ["", f"Configuration `{n}` (from `{src}`), in full:", "", "```yaml",
                  yaml.safe_dump(cfg, sort_keys=True).rstrip(), "```"]  # fmt: skip
    report = out_dir / "REPORT.md"
    atomic_write_bytes(report, ("\n".join(parts) + "\n").encode())
    return report


def _num(v: Any) -> bool:
    try:
        return v is not None and math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


def _mean(sel: pd.DataFrame, col: str) -> float | None:
    if col not in sel.columns:
        return None
    v = pd.to_numeric(sel[col], errors="coerce").dropna()
    return float(v.mean()) if len(v) else None


def _ordered(items: Any) -> list[str]:
    out: list[str] = []
    for i in items:
        if i not in out:
            out.append(i)
    return out

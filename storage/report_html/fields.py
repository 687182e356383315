"""The values a report shows, each formatted once.

Escaping, links, numbers, volumes with their definitions, Eq. 7's precision,
notes and review reasons.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from typing import Any
from urllib.parse import quote

from tumor3d.errors import InputError

#: Volume estimators: key -> (label, definition); the labels are
#: :data:`tumor3d.storage.derivatives.VOLUME_LABELS` capitalised (a test holds them equal).
VOLUME_DEFINITIONS: dict[str, tuple[str, str]] = {
    "eq7": (
        "Eq. 7 (slab sum)",
        "V = h · Σᵢ Aᵢ: the tumour area Aᵢ = nᵢ·Δx·Δy on each acquired slice times the "
        "slab height h (slice thickness plus gap), the Cavalieri estimator of the paper's Eq. 7.",
    ),
    "voxel": (
        "Voxel count",
        "Number of tumour voxels in the interpolated mask times the volume of one "
        "interpolated voxel (Δx·Δy·Δz/(m+1)).",
    ),
    "mesh": (
        "Mesh (marching cubes)",
        "Volume enclosed by the marching-cubes surface, by the divergence theorem "
        "(Σ over faces of v₀·(v₁×v₂)/6).",
    ),
    "mesh_simplified": (
        "Mesh (simplified)",
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

"""Cohort manifest: a CSV listing one input scan per patient.

Columns (header names exact, any order):

==================  ========  ==============================================
column              required  meaning
==================  ========  ==============================================
patient_id          yes       folder-safe id, unique in the manifest
image               yes       NIfTI file or DICOM / image-stack folder
modality            yes       ``t2``, ``flair`` or ``t1c`` (case-insensitive)
reference           no        reference tumour label volume (NIfTI, any grid
                              in the same world space)
reference_labels    no        label values forming the tumour, e.g. ``"1,2,4"``
                              (default: every value > 0); needs ``reference``
slice_thickness_mm  no        overrides the input's slice thickness (> 0)
slice_gap_mm        no        overrides the input's inter-slice gap (>= 0)
==================  ========  ==============================================

Relative paths are relative to the manifest's folder. An empty optional cell
means "not given". Errors name the manifest, the data row (1-based, the
header excluded; the file line is given too) and the column.
"""

from __future__ import annotations

import csv
import math
import os
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from tumor3d.errors import InputError
from tumor3d.scan import MODALITIES, validate_patient_id

__all__ = ["MANIFEST_COLUMNS", "REQUIRED_COLUMNS", "ManifestRow", "read_manifest", "write_manifest"]

REQUIRED_COLUMNS = ("patient_id", "image", "modality")
MANIFEST_COLUMNS = (
    *REQUIRED_COLUMNS,
    "reference",
    "reference_labels",
    "slice_thickness_mm",
    "slice_gap_mm",
)
_Fail = Callable[[str, str], InputError]


@dataclass(frozen=True)
class ManifestRow:
    """One patient of a cohort manifest.

    Parameters
    ----------
    patient_id : str
        Folder-safe id (:func:`tumor3d.scan.validate_patient_id`).
    image : Path
        Absolute path of the input scan (file or folder).
    modality : str
        ``"t2"``, ``"flair"`` or ``"t1c"``.
    reference : Path or None
        Absolute path of a reference label volume, if any.
    reference_labels : tuple of int or None
        Label values that form the tumour; ``None`` means every value > 0.
    slice_thickness_mm, slice_gap_mm : float or None
        Overrides of the input's slice thickness and gap, in mm.
    """

    patient_id: str
    image: Path
    modality: str
    reference: Path | None = None
    reference_labels: tuple[int, ...] | None = None
    slice_thickness_mm: float | None = None
    slice_gap_mm: float | None = None

    def __post_init__(self) -> None:
        validate_patient_id(self.patient_id)
        object.__setattr__(self, "image", Path(self.image))
        if self.reference is not None:
            object.__setattr__(self, "reference", Path(self.reference))
        modality = self.modality.strip().lower() if isinstance(self.modality, str) else None
        if modality not in MODALITIES:
            raise InputError(
                f"unknown modality {self.modality!r}: expected one of {', '.join(MODALITIES)}"
            )
        object.__setattr__(self, "modality", modality)
        if self.reference_labels is not None:
            labels = tuple(int(v) for v in self.reference_labels)
            if not labels or min(labels) <= 0 or len(set(labels)) != len(labels):
                raise InputError(
                    f"reference_labels must be distinct positive integers, got {labels!r}"
                )
            if self.reference is None:
                raise InputError("reference_labels given without a reference")
            object.__setattr__(self, "reference_labels", labels)


def read_manifest(path: str | os.PathLike[str]) -> list[ManifestRow]:
    """Read and validate a cohort manifest CSV.

    Parameters
    ----------
    path : str or path-like
        The CSV file (UTF-8, optional BOM).

    Returns
    -------
    list of ManifestRow
        One row per data line, in file order, with absolute resolved paths.

    Raises
    ------
    InputError
        Missing file, missing or unknown column, no data rows, or a row with
        an empty required value, an unsafe or duplicate ``patient_id``, an
        unknown modality, a non-numeric or negative thickness or gap, a bad
        label list, or an image/reference path that does not exist.
    """
    p = Path(path)
    where = str(p)
    if not p.is_file():
        raise InputError("no such manifest file", where)
    base = p.resolve().parent
    try:
        with p.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            header = [(h or "").strip() for h in (reader.fieldnames or [])]
            _check_header(header, where)
            reader.fieldnames = header
            records = [(reader.line_num, rec) for rec in reader]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(
            f"not a readable CSV manifest ({type(exc).__name__}: {exc})", where
        ) from exc
    if not records:
        raise InputError("no data rows below the header", where)

    rows: list[ManifestRow] = []
    seen: dict[str, int] = {}
    for index, (line, rec) in enumerate(records, start=1):

        def fail(column: str, problem: str, _i: int = index, _line: int = line) -> InputError:
            return InputError(f"data row {_i} (line {_line}), column {column!r}: {problem}", where)

        if None in rec:
            raise fail("(extra)", f"the row has more values than the {len(header)} columns")
        cells = {k: (v or "").strip() for k, v in rec.items()}
        for column in REQUIRED_COLUMNS:
            if not cells.get(column):
                raise fail(column, "empty value")
        pid = cells["patient_id"]
        try:
            validate_patient_id(pid)
        except InputError as exc:
            raise fail("patient_id", exc.problem) from None
        if pid in seen:
            raise fail("patient_id", f"duplicate patient_id {pid!r} (also in data row {seen[pid]})")
        seen[pid] = index
        modality = cells["modality"].lower()
        if modality not in MODALITIES:
            raise fail(
                "modality",
                f"unknown modality {cells['modality']!r}: expected one of {', '.join(MODALITIES)}",
            )
        image = _resolve(base, cells["image"])
        if not image.exists():
            raise fail("image", f"{image} does not exist")
        reference = None
        if cells.get("reference"):
            reference = _resolve(base, cells["reference"])
            if not reference.exists():
                raise fail("reference", f"{reference} does not exist")
        labels = None
        if cells.get("reference_labels"):
            labels = _parse_labels(cells["reference_labels"], fail)
            if reference is None:
                raise fail("reference_labels", "label values given without a reference")
        thickness = _parse_mm(
            cells.get("slice_thickness_mm", ""), "slice_thickness_mm", fail, allow_zero=False
        )
        gap = _parse_mm(cells.get("slice_gap_mm", ""), "slice_gap_mm", fail, allow_zero=True)
        rows.append(
            ManifestRow(
                patient_id=pid,
                image=image,
                modality=modality,
                reference=reference,
                reference_labels=labels,
                slice_thickness_mm=thickness,
                slice_gap_mm=gap,
            )
        )
    return rows


def write_manifest(rows: Iterable[ManifestRow], path: str | os.PathLike[str]) -> Path:
    """Write a cohort manifest CSV that :func:`read_manifest` reads back.

    Paths are written relative to the manifest's folder (POSIX separators)
    where possible; all columns of :data:`MANIFEST_COLUMNS` are written,
    empty where a value is not given. The file is written to a temporary
    name and renamed.

    Parameters
    ----------
    rows : iterable of ManifestRow
        Rows to write; patient ids must be unique.
    path : str or path-like
        Destination CSV; its folder must exist.

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    InputError
        If two rows share a patient id or the folder does not exist.
    """
    p = Path(path)
    base = p.parent.resolve() if p.parent.exists() else None
    if base is None:
        raise InputError("the manifest's folder does not exist", str(p))
    rows = list(rows)
    ids = [r.patient_id for r in rows]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise InputError(f"duplicate patient_id {', '.join(dup)}", str(p))

    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=base)
    try:
        with os.fdopen(fd, "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(MANIFEST_COLUMNS)
            for r in rows:
                writer.writerow(
                    [
                        r.patient_id,
                        _relative(base, r.image),
                        r.modality,
                        "" if r.reference is None else _relative(base, r.reference),
                        ""
                        if r.reference_labels is None
                        else ",".join(str(v) for v in r.reference_labels),
                        "" if r.slice_thickness_mm is None else repr(float(r.slice_thickness_mm)),
                        "" if r.slice_gap_mm is None else repr(float(r.slice_gap_mm)),
                    ]
                )
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p


def _check_header(header: list[str], where: str) -> None:
    if not header or header == [""]:
        raise InputError(
            f"empty manifest: the first line must name the columns {', '.join(REQUIRED_COLUMNS)}",
            where,
        )
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise InputError(
            f"missing required column(s) {', '.join(missing)} in the header "
            f"(found: {', '.join(header)})",
            where,
        )
    unknown = [c for c in header if c not in MANIFEST_COLUMNS]
    if unknown:
        raise InputError(
            f"unknown column(s) {', '.join(repr(c) for c in unknown)}; allowed: "
            f"{', '.join(MANIFEST_COLUMNS)}",
            where,
        )
    dup = sorted({c for c in header if header.count(c) > 1})
    if dup:
        raise InputError(f"column(s) {', '.join(dup)} appear more than once", where)


def _resolve(base: Path, value: str) -> Path:
    q = Path(os.path.expanduser(value))
    return (q if q.is_absolute() else base / q).resolve()


def _relative(base: Path, target: Path) -> str:
    t = Path(target).resolve()
    try:
        return Path(os.path.relpath(t, base)).as_posix()
    except ValueError:  # e.g. another drive on Windows
        return t.as_posix()


def _parse_labels(text: str, fail: _Fail) -> tuple[int, ...]:
    parts = [s.strip() for s in text.split(",")]
    labels = []
    for s in parts:
        try:
            value = int(s)
        except ValueError:
            raise fail(
                "reference_labels",
                f"bad label list {text!r}: expected comma-separated positive integers",
            ) from None
        if value <= 0:
            raise fail("reference_labels", f"bad label list {text!r}: label {value} is not > 0")
        labels.append(value)
    if len(set(labels)) != len(labels):
        raise fail("reference_labels", f"bad label list {text!r}: a label is repeated")
    return tuple(labels)


def _parse_mm(text: str, column: str, fail: _Fail, *, allow_zero: bool) -> float | None:
    if not text:
        return None
    bound = "non-negative" if allow_zero else "positive"
    try:
        value = float(text)
    except ValueError:
        raise fail(column, f"{text!r} is not a number (mm)") from None
    if not math.isfinite(value):
        raise fail(column, f"{text!r} is not a finite number (mm)")
    if value < 0 or (value == 0 and not allow_zero):
        raise fail(column, f"{text!r} must be a {bound} number of mm")
    return value

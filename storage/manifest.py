"""Cohort manifest: a CSV listing one input scan per patient.

Columns (header names exact, any order):

==================  ========  ==============================================
column              required  meaning
==================  ========  ==============================================
patient_id          yes       folder-safe id, unique in the manifest
image               yes       NIfTI file or DICOM / image-stack folder
modality            yes       ``t2``, ``flair`` or ``t1c`` (case-insensitive)
brain_mask          no        a brain mask on the image's voxel grid (same
                              shape and affine; brain = values > 0.5: a 0/1
                              or 0/255 mask or a probability map), used
                              instead of skull removal
                              (:mod:`tumor3d.storage.brain_mask`); with emulation it
                              is emulated like the image
segmentation        no        your own tumour mask on the image's voxel grid
                              (the brain mask's grid rule; tumour = values >
                              0.5), used instead of the segment-tumor stage's
                              (:mod:`tumor3d.storage.given_segmentation`); not with
                              ``emulate_step_mm``
reference           no        reference tumour label volume (NIfTI, any grid
                              in the same world space)
reference_labels    no        label values forming the tumour, e.g. ``"1,2,4"``
                              (default: every value > 0); needs ``reference``
slice_thickness_mm  no        overrides the input's slice thickness (> 0)
slice_gap_mm        no        overrides the input's inter-slice gap (>= 0)
emulate_step_mm     no        evaluation only: resample the (thin-slice NIfTI)
                              image to one slice every this many mm before the
                              pipeline (:mod:`tumor3d.evaluation.emulate`)
emulate_thickness_mm no       evaluation only: thickness of each emulated
                              slice in mm (<= the step; needs
                              ``emulate_step_mm``; default: the image's own
                              slice step, i.e. keep every k-th slice)
reference_kind      no        what the reference is: ``expert``,
                              ``semiautomatic`` (drawn with a program's help
                              under a person's control), ``algorithmic``
                              (made by a program), ``truth`` (a phantom's),
                              or ``tumor_free`` (no tumour: no ``reference``
                              file needed)
==================  ========  ==============================================

Relative paths are relative to the manifest's folder; ``$VAR`` / ``${VAR}``
in a path is replaced from the environment, and ``${TUMOR3D_DATA_DIR}``
defaults to ``../shared/data`` beside the repository (:data:`DATA_DIR_DEFAULT`).
An empty optional cell means "not given". Errors name the manifest, the data
row (1-based, the header excluded; the file line is given too) and the column.

:func:`read_manifest` stops at the first bad row (a cohort with a bad
manifest does not start); :func:`read_manifest_rows` reports every bad row
as a :class:`RowProblem` and returns the good ones, so that one bad row does
not stop the other patients (the evaluation flow uses it).
"""

from __future__ import annotations

import csv
import math
import os
import re
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from tumor3d.errors import InputError
from tumor3d.evaluation.registry import REFERENCE_KINDS as CASE_REFERENCE_KINDS
from tumor3d.imaging.identity import MODALITIES, validate_patient_id
from tumor3d.package_layout import PROJECT_ROOT

__all__ = [
    "DATA_DIR_DEFAULT",
    "MANIFEST_COLUMNS",
    "REFERENCE_KINDS",
    "REQUIRED_COLUMNS",
    "ManifestRow",
    "RowProblem",
    "read_manifest",
    "read_manifest_rows",
    "write_manifest",
]

REQUIRED_COLUMNS = ("patient_id", "image", "modality")
MANIFEST_COLUMNS = (
    *REQUIRED_COLUMNS,
    "reference",
    "reference_labels",
    "slice_thickness_mm",
    "slice_gap_mm",
    "emulate_step_mm",
    "emulate_thickness_mm",
    "reference_kind",
    "brain_mask",
    "segmentation",
)
#: Values of the ``reference_kind`` column: the evaluation's kinds less its
#: "unspecified" (an empty cell).
REFERENCE_KINDS = tuple(k for k in CASE_REFERENCE_KINDS if k != "unspecified")
#: ``${TUMOR3D_DATA_DIR}`` when the environment does not set it.
DATA_DIR_DEFAULT = (PROJECT_ROOT / ".." / "shared" / "data").resolve()
_Fail = Callable[[str, str], InputError]


@dataclass(frozen=True)
class ManifestRow:
    """One patient of a cohort manifest.

    Parameters
    ----------
    patient_id : str
        Folder-safe id (:func:`tumor3d.imaging.scan.validate_patient_id`).
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
    emulate_step_mm, emulate_thickness_mm : float or None
        Thick-slice emulation for evaluation (see the module docstring).
    reference_kind : str or None
        One of :data:`REFERENCE_KINDS`, or ``None`` (not stated).
    brain_mask : Path or None
        Absolute path of a given brain mask on the image's grid, if any.
    segmentation : Path or None
        Absolute path of a given tumour segmentation on the image's grid, if any.
    """

    patient_id: str
    image: Path
    modality: str
    reference: Path | None = None
    reference_labels: tuple[int, ...] | None = None
    slice_thickness_mm: float | None = None
    slice_gap_mm: float | None = None
    emulate_step_mm: float | None = None
    emulate_thickness_mm: float | None = None
    reference_kind: str | None = None
    brain_mask: Path | None = None
    segmentation: Path | None = None

    def __post_init__(self) -> None:
        validate_patient_id(self.patient_id)
        object.__setattr__(self, "image", Path(self.image))
        if self.brain_mask is not None:
            object.__setattr__(self, "brain_mask", Path(self.brain_mask))
        if self.segmentation is not None:
            object.__setattr__(self, "segmentation", Path(self.segmentation))
            if self.emulate_step_mm is not None:
                raise InputError(
                    "segmentation given with emulate_step_mm (a mask on the thin image "
                    "cannot replace the emulated image's segmentation)"
                )
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
        if self.emulate_thickness_mm is not None and self.emulate_step_mm is None:
            raise InputError("emulate_thickness_mm given without emulate_step_mm")
        for name in ("emulate_step_mm", "emulate_thickness_mm"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(float(v)) and float(v) > 0):
                raise InputError(f"{name} must be a positive number of mm, got {v!r}")
        if (
            self.emulate_step_mm is not None
            and self.emulate_thickness_mm is not None
            and self.emulate_thickness_mm > self.emulate_step_mm
        ):
            raise InputError(
                f"emulate_thickness_mm = {self.emulate_thickness_mm:g} exceeds "
                f"emulate_step_mm = {self.emulate_step_mm:g}"
            )
        if self.reference_kind is not None:
            kind = str(self.reference_kind).strip().lower().replace("-", "_")
            if kind not in REFERENCE_KINDS:
                raise InputError(
                    f"unknown reference_kind {self.reference_kind!r}: expected one of "
                    f"{', '.join(REFERENCE_KINDS)}"
                )
            if kind == "tumor_free" and self.reference is not None:
                raise InputError("reference_kind tumor_free with a reference file")
            object.__setattr__(self, "reference_kind", kind)


@dataclass(frozen=True)
class RowProblem:
    """A manifest row that cannot be used.

    Parameters
    ----------
    row : int
        Data row, 1-based (the header excluded).
    patient_id : str or None
        The row's patient id, if it has one.
    column : str
        The offending column.
    message : str
        The full error message (names the manifest, row and column).
    missing_file : bool
        Whether the problem is only that a file named by the row is absent.
    """

    row: int
    patient_id: str | None
    column: str
    message: str
    missing_file: bool = False


def read_manifest(path: str | os.PathLike[str], *, require_files: bool = True) -> list[ManifestRow]:
    """Read and validate a cohort manifest CSV; the first bad row is an error.

    Parameters
    ----------
    path : str or path-like
        The CSV file (UTF-8, optional BOM).
    require_files : bool
        Whether an image, brain mask, segmentation or reference path that
        does not exist is an error of the manifest. ``tumor3d cohort`` passes
        False: such a row is kept (every other column still validated) and
        fails alone when its patient runs, so the other patients still run.

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
        label list, bad emulation values or reference kind, or (with
        ``require_files``) an image, brain mask, segmentation or reference path
        that does not exist.
    """
    rows, problems = read_manifest_rows(path, require_files=require_files)
    if problems:
        raise InputError(problems[0].message)
    return rows


def read_manifest_rows(
    path: str | os.PathLike[str], *, require_files: bool = True
) -> tuple[list[ManifestRow], list[RowProblem]]:
    """Read a cohort manifest, keeping the good rows and listing the bad ones.

    Parameters
    ----------
    path : str or path-like
        The CSV file (UTF-8, optional BOM).
    require_files : bool
        Whether a row naming an absent image, brain mask, segmentation or
        reference is a problem
        (default); see :func:`read_manifest`.

    Returns
    -------
    rows : list of ManifestRow
        The valid rows, in file order (of two rows with one ``patient_id``,
        the first).
    problems : list of RowProblem
        One per invalid row, in file order.

    Raises
    ------
    InputError
        For problems of the whole file: missing or unreadable file, bad
        header, no data rows.
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
    problems: list[RowProblem] = []
    seen: dict[str, int] = {}
    for index, (line, rec) in enumerate(records, start=1):
        pid = ((rec.get("patient_id") or "") if isinstance(rec, dict) else "").strip() or None
        try:
            rows.append(_parse_row(index, line, rec, header, base, seen, where, require_files))
        except _RowError as exc:
            problems.append(
                RowProblem(index, pid, exc.column, str(exc), missing_file=exc.missing_file)
            )
    return rows, problems


class _RowError(InputError):
    def __init__(self, message: str, path: str, column: str, missing_file: bool) -> None:
        super().__init__(message, path)
        self.column = column
        self.missing_file = missing_file


def _parse_row(
    index: int,
    line: int,
    rec: dict,
    header: list[str],
    base: Path,
    seen: dict[str, int],
    where: str,
    require_files: bool = True,
) -> ManifestRow:
    def fail(column: str, problem: str, missing: bool = False) -> _RowError:
        return _RowError(
            f"data row {index} (line {line}), column {column!r}: {problem}", where, column, missing
        )

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
    modality = cells["modality"].lower()
    if modality not in MODALITIES:
        raise fail(
            "modality",
            f"unknown modality {cells['modality']!r}: expected one of {', '.join(MODALITIES)}",
        )
    image = _resolve(base, cells["image"], fail, "image")
    if require_files and not image.exists():
        raise fail("image", f"{image} does not exist", missing=True)
    brain_mask = None
    if cells.get("brain_mask"):
        brain_mask = _resolve(base, cells["brain_mask"], fail, "brain_mask")
        if require_files and not brain_mask.exists():
            raise fail("brain_mask", f"{brain_mask} does not exist", missing=True)
    segmentation = None
    if cells.get("segmentation"):
        segmentation = _resolve(base, cells["segmentation"], fail, "segmentation")
        if require_files and not segmentation.exists():
            raise fail("segmentation", f"{segmentation} does not exist", missing=True)
    reference = None
    if cells.get("reference"):
        reference = _resolve(base, cells["reference"], fail, "reference")
        if require_files and not reference.exists():
            raise fail("reference", f"{reference} does not exist", missing=True)
    labels = None
    if cells.get("reference_labels"):
        labels = _parse_labels(cells["reference_labels"], fail)
        if reference is None:
            raise fail("reference_labels", "label values given without a reference")
    thickness = _parse_mm(
        cells.get("slice_thickness_mm", ""), "slice_thickness_mm", fail, allow_zero=False
    )
    gap = _parse_mm(cells.get("slice_gap_mm", ""), "slice_gap_mm", fail, allow_zero=True)
    e_step = _parse_mm(cells.get("emulate_step_mm", ""), "emulate_step_mm", fail, allow_zero=False)
    e_thick = _parse_mm(
        cells.get("emulate_thickness_mm", ""), "emulate_thickness_mm", fail, allow_zero=False
    )
    if e_thick is not None and e_step is None:
        raise fail("emulate_thickness_mm", "given without emulate_step_mm")
    if e_thick is not None and e_step is not None and e_thick > e_step:
        raise fail(
            "emulate_thickness_mm",
            f"{e_thick:g} mm exceeds emulate_step_mm = {e_step:g} mm (slices would overlap)",
        )
    kind = cells.get("reference_kind", "").lower().replace("-", "_") or None
    if kind is not None and kind not in REFERENCE_KINDS:
        raise fail(
            "reference_kind",
            f"unknown kind {cells['reference_kind']!r}: "
            f"expected one of {', '.join(REFERENCE_KINDS)}",
        )
    if kind == "tumor_free" and reference is not None:
        raise fail("reference_kind", "tumor_free, but a reference file is given")
    if segmentation is not None and e_step is not None:
        raise fail(
            "segmentation",
            "given with emulate_step_mm (a mask on the thin image cannot replace the "
            "emulated image's segmentation)",
        )
    seen[pid] = index
    return ManifestRow(
        patient_id=pid,
        image=image,
        modality=modality,
        reference=reference,
        reference_labels=labels,
        slice_thickness_mm=thickness,
        slice_gap_mm=gap,
        emulate_step_mm=e_step,
        emulate_thickness_mm=e_thick,
        reference_kind=kind,
        brain_mask=brain_mask,
        segmentation=segmentation,
    )


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
                        "" if r.emulate_step_mm is None else repr(float(r.emulate_step_mm)),
                        ""
                        if r.emulate_thickness_mm is None
                        else repr(float(r.emulate_thickness_mm)),
                        r.reference_kind or "",
                        "" if r.brain_mask is None else _relative(base, r.brain_mask),
                        "" if r.segmentation is None else _relative(base, r.segmentation),
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
        # one cell holding them all: another delimiter (a spreadsheet's ';' or a tab)
        other = len(header) == 1 and any(d in header[0] for d in ";\t|")
        hint = " (the manifest must be comma-separated)" if other else ""
        raise InputError(
            f"missing required column(s) {', '.join(missing)} in the header "
            f"(found: {', '.join(header)}){hint}",
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


def data_dir() -> Path:
    """The real-data folder: ``$TUMOR3D_DATA_DIR``, else :data:`DATA_DIR_DEFAULT`.

    A relative ``TUMOR3D_DATA_DIR`` is relative to the working directory, as
    any path from the environment. The manifests' ``${TUMOR3D_DATA_DIR}`` and
    the benchmarks read the folder through this one function.
    """
    env = os.environ.get("TUMOR3D_DATA_DIR")
    return Path(env).resolve() if env else DATA_DIR_DEFAULT


#: ``$NAME`` or ``${NAME}`` in a path.
_VARIABLE = re.compile(r"\$(?:\{(\w+)\}|(\w+))")


def _resolve(base: Path, value: str, fail: _Fail | None = None, column: str = "") -> Path:
    """``value`` with its variables and ``~`` expanded, relative to ``base``.

    A variable the environment does not set (``${TUMOR3D_DATA_DIR}`` has a
    default) is an error of the row's ``column``: left as text, it made a path
    that "does not exist" without saying why.
    """
    unset = sorted(
        {a or b for a, b in _VARIABLE.findall(value)} - set(os.environ) - {"TUMOR3D_DATA_DIR"}
    )
    if unset and fail is not None:
        names = ", ".join(f"${n}" for n in unset)
        raise fail(column, f"environment variable {names} is not set (in {value!r})")
    if "TUMOR3D_DATA_DIR" in value:
        folder = str(data_dir())
        value = value.replace("${TUMOR3D_DATA_DIR}", folder)
        value = value.replace("$TUMOR3D_DATA_DIR", folder)
    q = Path(os.path.expanduser(os.path.expandvars(value)))
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

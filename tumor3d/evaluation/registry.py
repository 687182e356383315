"""The registry of evaluations that ``tumor3d evaluate`` runs.

An *evaluation* is a pure function ``fn(case: EvaluationCase) ->
EvaluationRows``: arrays in (one patient's published results and its
reference, already loaded and put on comparable grids by the storage layer), rows
out. It never reads files. Optionally it also has ``summarize(rows) -> str``,
which turns every patient's row of one configuration into a Markdown section
of the report.

Adding an evaluation = one module and one line:

1. a module, e.g. ``tumor3d/evaluation/interpolation.py``, with::

       from tumor3d.evaluation.registry import register_evaluation

       @register_evaluation("interpolation", description="Table 4: ...")
       def evaluate_interpolation(case):
           ...
           return EvaluationRows(patient={...}, slices=[...])

2. its name in :data:`EVALUATION_MODULES` below.

Column names of the rows are prefixed with nothing: keep them unique across
evaluations (``patient_id`` and ``config`` are added by
:func:`tumor3d.storage.evaluation_tables.evaluation_rows`).

What an evaluation shows of its columns is declared with them
(``register_evaluation(..., columns=ReportColumns(...))``): the report's table
per case and its summary per group (:mod:`tumor3d.storage.evaluation_report`)
and the console's table of ``tumor3d evaluate`` read the declaration, each
column with its label and format.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tumor3d.errors import InputError

__all__ = [
    "EVALUATION_MODULES",
    "Evaluation",
    "EvaluationCase",
    "EvaluationRows",
    "ReportColumn",
    "ReportColumns",
    "register_evaluation",
    "registered_evaluations",
    "selected_evaluations",
]

#: Modules whose import registers evaluations; add one line per new module.
EVALUATION_MODULES: tuple[str, ...] = (
    "tumor3d.evaluation.segmentation",
    "tumor3d.evaluation.geometry",
)

#: Kinds of reference a case may have.
REFERENCE_KINDS = (
    "expert",
    "semiautomatic",
    "algorithmic",
    "truth",
    "tumor_free",
    "unspecified",
)


@dataclass(frozen=True, eq=False)
class EvaluationCase:
    """One patient's results and reference, ready to compare.

    All masks are boolean arrays in their file's own voxel order; every
    affine maps the voxel index ``(i0, i1, i2, 1)`` in array order to RAS mm.

    Parameters
    ----------
    patient_id : str
    reference_kind : str
        One of :data:`REFERENCE_KINDS`.
    slice_axis : int
        The acquisition (slice) axis of the acquired grid.
    acquired_affine : (4, 4) ndarray
        Grid of the image the pipeline ran on (emulated or native).
    pred_slices : bool ndarray
        The pipeline's tumour on the acquired slices (``tumor_mask_slices``).
    ref_slices : bool ndarray or None
        The reference on the acquired grid (emulated the same way as the
        image, or sampled at its voxel centres); ``None`` without reference.
    detector_abnormal : (n_slices,) bool ndarray or None
        The abnormal-slice detector's flags (before segmentation).
    pred_fine, pred_fine_affine : bool ndarray, (4, 4) ndarray
        The interpolated 3-D tumour (``tumor_mask``) and its grid.
    reference, reference_affine : bool ndarray or None, (4, 4) ndarray or None
        The reference at full resolution on its own grid.
    pred_on_reference : bool ndarray or None
        ``pred_fine`` sampled at the reference's voxel centres (nearest).
    metrics : dict
        The patient's ``metrics.parquet`` row (volumes in mm^3 etc.).
    extras : dict
        Anything else a later evaluation needs (e.g. meshes), by name.
    """

    patient_id: str
    reference_kind: str
    slice_axis: int
    acquired_affine: np.ndarray
    pred_slices: np.ndarray
    ref_slices: np.ndarray | None
    detector_abnormal: np.ndarray | None
    pred_fine: np.ndarray
    pred_fine_affine: np.ndarray
    reference: np.ndarray | None
    reference_affine: np.ndarray | None
    pred_on_reference: np.ndarray | None
    metrics: dict[str, Any]
    extras: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.reference_kind not in REFERENCE_KINDS:
            raise InputError(
                f"reference_kind must be one of {', '.join(REFERENCE_KINDS)}, "
                f"got {self.reference_kind!r}"
            )
        if self.ref_slices is not None and self.ref_slices.shape != self.pred_slices.shape:
            raise InputError(
                f"ref_slices {self.ref_slices.shape} and pred_slices "
                f"{self.pred_slices.shape} must share the acquired grid"
            )
        if (self.reference is None) != (self.reference_affine is None):
            raise InputError("reference and reference_affine go together")


@dataclass
class EvaluationRows:
    """What an evaluation returns for one patient.

    ``patient``: one row of ``evaluation.parquet`` (column -> scalar);
    ``slices``: rows of ``evaluation_slices.parquet`` (each with
    ``slice_index``).
    """

    patient: dict[str, Any] = field(default_factory=dict)
    slices: list[dict[str, Any]] = field(default_factory=list)


@dataclass(frozen=True)
class ReportColumn:
    """A column an evaluation shows: the values of ``keys``, each by ``fmt``, joined by " / ".

    Parameters
    ----------
    label : str
        Its header (in the report's table per case, after ``<configuration>: ``).
    keys : tuple of str
        The ``evaluation.parquet`` columns of one cell (one for a summary or the console).
    fmt : str
        :meth:`str.format` pattern of one value, e.g. ``"{:.3f}"``.
    """

    label: str
    keys: tuple[str, ...]
    fmt: str


@dataclass(frozen=True)
class ReportColumns:
    """Where an evaluation's columns are shown, each with its label and format.

    Parameters
    ----------
    title, intro : str
        Heading and text of the report's table per case (``table``).
    table : tuple of ReportColumn
        The report's table per case: one cell per configuration and column.
    summary : tuple of ReportColumn
        The report's summary per group: the mean of each (one key each).
    console : tuple of ReportColumn
        The console's table of ``tumor3d evaluate`` (one key each; a column only when
        some case has a value).
    """

    title: str = ""
    intro: str = ""
    table: tuple[ReportColumn, ...] = ()
    summary: tuple[ReportColumn, ...] = ()
    console: tuple[ReportColumn, ...] = ()


@dataclass(frozen=True)
class Evaluation:
    """A registered evaluation."""

    name: str
    description: str
    fn: Callable[[EvaluationCase], EvaluationRows]
    summarize: Callable[[list[dict[str, Any]]], str] | None = None
    #: Run when the user names no evaluation (the costly ones are asked for by name).
    default: bool = True
    #: What the report and the console show of its columns.
    columns: ReportColumns = field(default_factory=ReportColumns)


_REGISTRY: dict[str, Evaluation] = {}


def register_evaluation(
    name: str,
    *,
    description: str,
    summarize: Callable[[list[dict[str, Any]]], str] | None = None,
    default: bool = True,
    columns: ReportColumns | None = None,
) -> Callable[[Callable[[EvaluationCase], EvaluationRows]], Callable]:
    """Decorator registering ``fn(case) -> EvaluationRows`` under ``name``.

    Parameters
    ----------
    name : str
        Unique name (re-registering the same function is a no-op).
    description : str
        One line for the report.
    summarize : callable, optional
        ``summarize(patient_rows) -> markdown`` for one configuration.
    default : bool
        Run when no evaluation is named (``tumor3d evaluate`` without
        ``--evaluation``); False for the ones asked for by name.
    columns : ReportColumns, optional
        Its columns as the report and the console show them; default none.
    """
    if not isinstance(name, str) or not name:
        raise InputError(f"evaluation name must be a non-empty string, got {name!r}")

    def deco(fn: Callable[[EvaluationCase], EvaluationRows]) -> Callable:
        old = _REGISTRY.get(name)
        if old is not None and old.fn.__qualname__ != fn.__qualname__:
            raise InputError(f"an evaluation named {name!r} is already registered")
        shown = columns
        _REGISTRY[name] = Evaluation(
            name, description, fn, summarize, bool(default), shown or ReportColumns()
        )
        return fn

    return deco


def registered_evaluations() -> dict[str, Evaluation]:
    """All evaluations, after importing :data:`EVALUATION_MODULES` (name -> Evaluation)."""
    for module in EVALUATION_MODULES:
        importlib.import_module(module)
    return dict(_REGISTRY)


def selected_evaluations(names: list[str] | tuple[str, ...] | None = None) -> dict[str, Evaluation]:
    """The evaluations to run: the named ones (in that order), or the default ones.

    Raises
    ------
    InputError
        For a name that is not registered (the message lists the registered ones).

    Examples
    --------
    >>> list(selected_evaluations())
    ['segmentation']
    >>> list(selected_evaluations(["segmentation", "interpolation"]))
    ['segmentation', 'interpolation']
    >>> try:
    ...     selected_evaluations(["volumes"])
    ... except InputError as exc:
    ...     print(exc.problem)
    no evaluation named 'volumes' (registered: interpolation, segmentation, simplification)
    """
    every = registered_evaluations()
    if not names:
        return {k: ev for k, ev in every.items() if ev.default}
    unknown = [n for n in names if n not in every]
    if unknown:
        raise InputError(
            f"no evaluation named {unknown[0]!r} (registered: {', '.join(sorted(every))})"
        )
    return {n: every[n] for n in dict.fromkeys(names)}

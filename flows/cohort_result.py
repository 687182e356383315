"""What a cohort run returns, and how a patient's failure is told apart.

:class:`PatientOutcome` (how one manifest row went), :class:`CohortResult` (what
:func:`tumor3d.flows.cohort.cohort_flow` and :func:`tumor3d.flows.cohort.run_cohort`
return) and :class:`PatientsFailed` (the data of a cohort flow run's Failed state);
:func:`one_line_error` and :func:`environment_failure` (a failure in one line, and
whether it was the machine's or the input's), :func:`exit_code_of` (a command's exit
code from its patients' statuses) and :func:`with_recompute_reason` (why stages ran
for a patient an earlier run had published). No Prefect: the flow module wires these.
"""

from __future__ import annotations

import errno
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from tumor3d.errors import Tumor3DError, exception_line
from tumor3d.flows.exit_codes import EXIT_CHECK, EXIT_ENVIRONMENT
from tumor3d.segmentation.review import STATUS_CHECK, STATUS_FAILED
from tumor3d.storage import bids
from tumor3d.storage.provenance import changed_since, patients_by_reason
from tumor3d.storage.store import StoreError
from tumor3d.tasks.runner import StageRun

__all__ = [
    "CohortResult",
    "PatientOutcome",
    "PatientsFailed",
    "environment_failure",
    "exit_code_of",
    "one_line_error",
    "with_recompute_reason",
]

#: Longest error message kept per patient (characters).
_MAX_ERROR = 300


class PatientOutcome(BaseModel):
    """How one manifest row went.

    Parameters
    ----------
    patient_id : str
    status : {"ok", "check", "failed"}
        ``check``: completed, but the tool's own checks doubt the result
        (:mod:`tumor3d.segmentation.review`; the metrics' ``review_reasons`` say why).
    failed_stage : str or None
        The stage that raised (``prepare-input`` before the first stage,
        ``publish`` after the last).
    error : str or None
        One line: exception type and message (an OS error: the file it names and
        what happened, ``OSError: DIR/p1/...: no space left on device (ENOSPC)``).
    environment : bool
        Failed for the machine, not the input: an artifact store, or a full,
        read-only or forbidden disk while writing (:func:`environment_failure`).
    output_dir : str or None
        ``DIR/<patient_id>`` when ok.
    metrics : dict
        That patient's ``metrics.parquet`` row when ok, else empty.
    stages : list of StageRun
        The stages that completed.
    row : dict
        The manifest row as given (extra columns passed through).
    lane_seconds : float
        Time the patient's lane spent on it: preparing, every stage, publishing.
    publish_seconds : float
        Of which publishing (:attr:`tumor3d.flows.patient.PatientResult.publish_seconds`).
    recomputed : str or None
        Why stages ran for a patient that an earlier run had published in ``DIR``
        (:func:`tumor3d.storage.provenance.recompute_reason`: its input or a given
        file, the code or the numerical packages' versions, or the configuration
        changed, or the results were not in this store); None when every stage was a
        cache hit or nothing was published.
    """

    model_config = ConfigDict(frozen=True)

    patient_id: str
    status: str
    failed_stage: str | None = None
    error: str | None = None
    environment: bool = False
    output_dir: str | None = None
    metrics: dict[str, Any] = Field(default_factory=dict)
    stages: list[StageRun] = Field(default_factory=list)
    row: dict[str, Any] = Field(default_factory=dict)
    lane_seconds: float = 0.0
    publish_seconds: float = 0.0
    recomputed: str | None = None


class CohortResult(BaseModel):
    """What the cohort flow (and :func:`~tumor3d.flows.cohort.run_cohort`) returns.

    Attributes
    ----------
    patients : list of PatientOutcome
        One per manifest row, in its order: ``patient_id``, ``status`` (ok, check,
        failed), ``metrics`` (the ``metrics.parquet`` row), ``output_dir``, the failing
        stage and its one-line error.
    removed : list of str
        Patients published in ``out_dir`` by an earlier run but no longer in the
        manifest (reported, their folders kept).
    earlier : list of str
        Failed patients whose folder still holds an earlier run's result (a new
        input that failed leaves the old result in place: reported, so that its
        ``metrics.parquet`` is not read as this run's).
    out_dir : str
        ``DIR``.
    workers : int
        Stages run at a time.
    wall_seconds : float
        The cohort's wall time.
    failed, to_check : list of PatientOutcome
        The patients that failed, and those that completed with status ``check``.
    exit_code : int
        3 when some patient failed for the machine (``PatientOutcome.environment``:
        a full disk, a store), else 1 when some failed, else 4 when some needs a
        check, else 0.
    """

    model_config = ConfigDict(frozen=True)

    patients: list[PatientOutcome]
    removed: list[str] = Field(default_factory=list)
    """Patients published in ``out_dir`` by an earlier run but no longer in the manifest
    (reported, their folders kept)."""
    earlier: list[str] = Field(default_factory=list)
    """Failed patients whose folder in ``out_dir`` still holds an earlier run's result,
    not this run's input's (reported: nothing in that folder is this run's)."""
    out_dir: str = ""
    workers: int = 1
    wall_seconds: float = 0.0

    @property
    def failed(self) -> list[PatientOutcome]:
        """The patients that failed."""
        return [p for p in self.patients if p.status == STATUS_FAILED]

    @property
    def to_check(self) -> list[PatientOutcome]:
        """The patients that completed with status ``check``."""
        return [p for p in self.patients if p.status == STATUS_CHECK]

    @property
    def since_earlier(self) -> dict[str, list[str]]:
        """Patient ids under the reason their result is not the earlier published one."""
        return patients_by_reason((p.patient_id, p.recomputed) for p in self.patients)

    @property
    def exit_code(self) -> int:
        """3 when some failed for the machine, 1 when some failed, 4 when some needs a check."""
        if any(p.environment for p in self.failed):
            return EXIT_ENVIRONMENT
        return exit_code_of([p.status for p in self.patients])


#: OS errors that say the machine could not write, wherever they happen.
_ENVIRONMENT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS})
#: OS errors that say so once the input was read (before, a forbidden input file).
_WRITE_ERRNOS = frozenset({errno.EACCES, errno.EPERM})


def exit_code_of(statuses: list[str]) -> int:
    """A command's exit code from its patients' statuses (:mod:`tumor3d.segmentation.review`).

    1 when some failed, else :data:`EXIT_CHECK` (4) when some has status
    ``check``, else 0.

    >>> exit_code_of(["ok", "ok"]), exit_code_of(["ok", "check"]), exit_code_of(["check", "failed"])
    (0, 4, 1)
    """
    if STATUS_FAILED in statuses:
        return 1
    return EXIT_CHECK if STATUS_CHECK in statuses else 0


def one_line_error(exc: BaseException) -> str:
    """``Type: first line of the message``, at most 300 characters.

    An OS error: the file and what happened in words (:func:`tumor3d.errors.os_error_line`).
    """
    return exception_line(exc, limit=_MAX_ERROR)


def environment_failure(exc: BaseException, *, input_read: bool) -> bool:
    """Whether a patient's failure is the machine's (exit code 3), not its input's.

    An artifact store that fails, a full or read-only disk anywhere, and a
    forbidden write once the input was read (``input_read``).

    >>> environment_failure(OSError(28, "No space left on device"), input_read=False)
    True
    >>> environment_failure(OSError(13, "Permission denied"), input_read=False)
    False
    >>> environment_failure(ValueError("bad"), input_read=True)
    False
    """
    if isinstance(exc, StoreError):
        return True
    if not isinstance(exc, OSError) or exc.errno is None:
        return False
    return exc.errno in _ENVIRONMENT_ERRNOS or (input_read and exc.errno in _WRITE_ERRNOS)


def with_recompute_reason(
    outcome: PatientOutcome, before: dict[str, dict[str, Any] | None], layout: str
) -> PatientOutcome:
    """``outcome`` with :attr:`PatientOutcome.recomputed` when stages ran that were published."""
    earlier = before.get(bids.folder_name(outcome.patient_id, layout))
    if earlier is None or outcome.status == STATUS_FAILED or outcome.output_dir is None:
        return outcome
    reason = changed_since(earlier, outcome.output_dir, all(s.cached for s in outcome.stages))
    return outcome if reason is None else outcome.model_copy(update={"recomputed": reason})


class PatientsFailed(Tumor3DError):
    """Some patients of a cohort failed; ``result`` is the whole :class:`CohortResult`.

    The data of the cohort flow run's Failed state: a direct call of
    :func:`~tumor3d.flows.cohort.cohort_flow` raises it (as Prefect raises a failed flow's
    error); :func:`~tumor3d.flows.cohort.run_cohort` returns its ``result``.
    """

    def __init__(self, result: CohortResult) -> None:
        n, total = len(result.failed), len(result.patients)
        names = ", ".join(o.patient_id for o in result.failed[:3])
        more = f" and {n - 3} more" if n > 3 else ""
        super().__init__(f"{n} of {total} patient{'s' if total != 1 else ''} failed: {names}{more}")
        self.result = result

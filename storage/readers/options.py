"""How to read an input: the reading options, validated once where the user's input enters.

:class:`ReadOptions` is the one spelling of the options every reader takes
(modality, patient id, DICOM series, slice thickness and gap overrides,
skipping unreadable DICOM files, the voxel limit). The command line, a
cohort manifest's row and the Python API build one from what the user gave;
:func:`tumor3d.storage.readers.read_scan`, the ingest stage and the flows
pass that object on unchanged.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from tumor3d.errors import InputError
from tumor3d.imaging.identity import validate_patient_id
from tumor3d.storage.readers.common import (
    MAX_VOXELS_DEFAULT,
    _check_override,
    check_max_voxels,
    check_modality,
)

__all__ = ["ReadOptions"]


class ReadOptions(BaseModel):
    """The options of one read, checked once (an :class:`InputError` names the bad one).

    Parameters
    ----------
    modality : {"t2", "flair", "t1c"}, optional
        MR sequence (case-insensitive, stored in lower case). ``None``: ``"t2"``,
        except for an image stack whose sidecar names a modality.
    patient_id : str, optional
        Folder-safe id; ``None``: derived from the input's name.
    series_uid : str, optional
        SeriesInstanceUID to pick when a DICOM folder holds several series.
    slice_thickness_mm, slice_gap_mm : float, optional
        Override the nominal slice thickness (> 0) and gap (>= 0) the input
        states (see :mod:`tumor3d.storage.readers`).
    skip_unreadable : bool
        DICOM: skip files that cannot be read instead of stopping.
    max_voxels : int
        Refuse a volume whose header declares more voxels, before reading it.

    Raises
    ------
    InputError
        An unknown modality, an unsafe patient id, a thickness <= 0, a gap < 0,
        a voxel limit < 1 (one line naming the option).
    TypeError
        A voxel limit that is not an integer.

    Examples
    --------
    >>> ReadOptions(modality="FLAIR", slice_gap_mm=0).modality
    'flair'
    >>> try:
    ...     ReadOptions(slice_thickness_mm=-1)
    ... except InputError as exc:
    ...     print(exc)
    slice_thickness_mm must be a positive number of mm, got -1
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    modality: str | None = None
    patient_id: str | None = None
    series_uid: str | None = None
    slice_thickness_mm: float | None = None
    slice_gap_mm: float | None = None
    skip_unreadable: bool = False
    max_voxels: int = MAX_VOXELS_DEFAULT

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise _input_error(exc) from None

    @field_validator("modality", mode="before")
    @classmethod
    def _modality(cls, value: Any) -> Any:
        return None if value is None else check_modality(value)

    @field_validator("patient_id", mode="before")
    @classmethod
    def _patient_id(cls, value: Any) -> Any:
        return None if value is None else validate_patient_id(value)

    @field_validator("slice_thickness_mm", mode="before")
    @classmethod
    def _thickness(cls, value: Any) -> Any:
        return _check_override("slice_thickness_mm", value, allow_zero=False)

    @field_validator("slice_gap_mm", mode="before")
    @classmethod
    def _gap(cls, value: Any) -> Any:
        return _check_override("slice_gap_mm", value, allow_zero=True)

    @field_validator("max_voxels", mode="before")
    @classmethod
    def _max_voxels(cls, value: Any) -> Any:
        return check_max_voxels(value)

    @classmethod
    def of(cls, source: Any) -> ReadOptions:
        """The options held by ``source``, any object with these attributes (an ``InputSource``).

        Only these options, also of a subclass (an ``InputSource`` is one).

        >>> from types import SimpleNamespace
        >>> ReadOptions.of(SimpleNamespace(modality="t1c", max_voxels=10, path="x")).max_voxels
        10
        """
        if type(source) is cls:
            return source
        return cls(**{k: getattr(source, k) for k in cls.model_fields if hasattr(source, k)})

    def common(self) -> dict[str, Any]:
        """The keywords every reader function takes: patient id, thickness, gap, voxel limit."""
        return {
            "patient_id": self.patient_id,
            "slice_thickness_mm": self.slice_thickness_mm,
            "slice_gap_mm": self.slice_gap_mm,
            "max_voxels": self.max_voxels,
        }

    def content_key(self) -> tuple[Any, ...]:
        """What decides the scan read (all but the patient id, which names it only)."""
        return tuple(getattr(self, k) for k in type(self).model_fields if k != "patient_id")


def _input_error(exc: ValidationError) -> InputError:
    """The first problem of ``exc`` as one line: a check's own InputError when it raised one."""
    first = exc.errors()[0]
    raised = (first.get("ctx") or {}).get("error")
    if isinstance(raised, InputError):
        return raised
    key = ".".join(str(p) for p in first["loc"]) or "options"
    if first["type"] == "extra_forbidden":
        return InputError(f"unknown reading option {key!r}")
    return InputError(f"reading option {key}: {first['msg']}")

"""What names a scan: its patient id and its MR sequence.

:data:`MODALITIES` (the sequences the pipeline knows) and
:func:`validate_patient_id` (an id that is one safe folder name). A
:class:`~tumor3d.imaging.scan.Scan` checks both; the readers and the manifest check
an id before any file is read.
"""

from __future__ import annotations

import re

from tumor3d.errors import InputError

__all__ = ["MODALITIES", "validate_patient_id"]

#: The MR sequences the pipeline knows (they decide which cluster is tumour).
MODALITIES = ("t2", "flair", "t1c")

_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def validate_patient_id(patient_id: str) -> str:
    """Check that a patient id is a safe, single folder name.

    Parameters
    ----------
    patient_id : str
        Candidate id: 1-128 characters from ``[A-Za-z0-9._-]``, starting
        with a letter or digit (so never ``.``, ``..`` or a hidden name),
        with no path separator.

    Returns
    -------
    str
        The id, unchanged.

    Raises
    ------
    InputError
        If the id is empty, too long, or contains any other character.

    Examples
    --------
    >>> validate_patient_id("pat-0003")
    'pat-0003'
    """
    if not isinstance(patient_id, str) or not _SAFE_ID.match(patient_id):
        raise InputError(
            f"unsafe patient id {patient_id!r}: use 1-128 characters from "
            "letters, digits, '.', '_' and '-', starting with a letter or digit "
            "(no path separators, no '..')"
        )
    return patient_id

"""Provenance of a published result: versions, input, configuration, stages.

Modelled on pyradiomics' ``generalinfo.py``: one function gathers the
general information (package versions, platform: :func:`tumor3d.storage.versions.versions`,
the one the stages' cache keys read too), one assembles the record written
as ``provenance.json``.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from typing import Any

from tumor3d.storage.store import canonical_dumps
from tumor3d.storage.versions import PACKAGES, versions

__all__ = ["PACKAGES", "METHOD", "build_provenance", "versions"]

#: The method, as cited in every record.
METHOD = "Arakeri & Reddy (2013), IJSIP 6(3); see ALGORITHMS.md choices [A1]-[A29]"


def build_provenance(
    *,
    input_info: dict[str, Any],
    config: dict[str, Any],
    stages: list[dict[str, Any]],
    volume_methods: dict[str, str],
    eq7_slice_rule: dict[str, str],
    config_digest: str,
    notes: list[str] | None = None,
) -> dict[str, Any]:
    """The provenance record of one patient.

    Parameters
    ----------
    input_info : dict
        Name, content digest, modality and patient id of the input (never its
        DICOM identity).
    config : dict
        The full pipeline configuration (JSON mode).
    stages : list of dict
        Per stage: name, cache status, times, artifact digests, code digest.
    volume_methods : dict
        Volume column -> definition.
    eq7_slice_rule : dict
        ``{"name": ..., "definition": ...}``: which slices Eq. 7 summed.
    config_digest : str
        SHA-256 of the canonical configuration JSON.
    notes : list of str, optional
        Plain statements (e.g. "no tumour found").
    """
    return {
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "method": METHOD,
        "versions": versions(),
        "input": input_info,
        "config": json.loads(canonical_dumps(config)),
        "config_sha256": config_digest,
        "volume_methods": volume_methods,
        "eq7_slices": eq7_slice_rule,
        "stages": stages,
        "notes": list(notes or []),
    }

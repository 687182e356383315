"""Provenance of a published result: versions, input, configuration, stages.

Modelled on pyradiomics' ``generalinfo.py``: one function gathers the
general information (package versions, platform), one assembles the record
written as ``provenance.json``.
"""

from __future__ import annotations

import json
import platform
from datetime import UTC, datetime
from importlib import metadata as importlib_metadata
from typing import Any

import tumor3d
from storage.store import canonical_dumps

__all__ = ["PACKAGES", "METHOD", "build_provenance", "versions"]

#: Distributions whose versions are recorded.
PACKAGES = (
    "prefect", "numpy", "scipy", "scikit-image", "nibabel", "pydicom", "open3d-cpu",
    "pandas", "pyarrow", "PyWavelets", "numba", "pydantic", "fast-simplification",
)  # fmt: skip

#: The method, as cited in every record.
METHOD = "Arakeri & Reddy (2013), IJSIP 6(3); see ALGORITHMS.md choices [A1]-[A29]"


def versions() -> dict[str, str]:
    """tumor3d, Python and every package of :data:`PACKAGES` (``not installed`` if absent)."""
    out = {
        "tumor3d": tumor3d.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(terse=True),
    }
    for name in PACKAGES:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


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

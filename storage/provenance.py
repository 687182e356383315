"""Provenance of a published result: versions, input, configuration, stages.

Modelled on pyradiomics' ``generalinfo.py``: one function gathers the
general information (package versions, platform: :func:`tumor3d.storage.versions.versions`,
the one the stages' cache keys read too), one assembles the record written
as ``provenance.json``.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from tumor3d.storage.refs import canonical_dumps
from tumor3d.storage.versions import NUMERICAL_DISTRIBUTIONS, PACKAGES, versions

__all__ = [
    "METHOD",
    "PACKAGES",
    "build_provenance",
    "cache_identity",
    "changed_since",
    "patients_by_reason",
    "recompute_reason",
    "same_identity",
    "versions",
]

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


def cache_identity(folder: str | Path) -> dict[str, Any] | None:
    """What decided a published patient's cache keys, from its ``provenance.json``.

    ``input`` (the input's content digest), ``modality`` (the sequence it was
    segmented as), ``config`` (the configuration's digest), ``given`` (the SHA-256
    of a given brain mask and segmentation, and of the models ``segment.learned_models``
    named, where the learned method ran with them),
    ``code`` (stage -> code digest) and ``versions``; None when the folder
    holds no readable record (never published, or by another tool).
    """
    try:
        doc = json.loads((Path(folder) / "provenance.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict):
        return None
    stages = [s for s in doc.get("stages") or [] if isinstance(s, dict)]
    given = {
        key: doc[key].get("sha256") for key in ("brain_mask", "segmentation")
        if isinstance(doc.get(key), dict) and doc[key].get("given")
    }  # fmt: skip
    seg, config = doc.get("segmentation"), doc.get("config")
    own = isinstance(config, dict) and (config.get("segment") or {}).get("learned_models")
    if own and isinstance(seg, dict) and seg.get("model_sha256"):  # a user's trained models
        given["models"] = [seg["model_sha256"], *(seg.get("cnn_sha256") or [])]
    return {
        "input": (doc.get("input") or {}).get("digest_sha256"),
        "modality": (doc.get("input") or {}).get("modality"),
        "config": doc.get("config_sha256"),
        "given": given,
        "code": {str(s.get("stage")): s.get("code_sha256") for s in stages},
        "versions": dict(doc.get("versions") or {}),
    }


def _modality_change(before: dict[str, Any], after: dict[str, Any]) -> tuple[str, str] | None:
    """The earlier and the new modality when both records name one and they differ."""
    old, new = before.get("modality"), after.get("modality")  # None: a record before it was kept
    return (old, new) if old is not None and new is not None and old != new else None


def same_identity(before: dict[str, Any], after: dict[str, Any]) -> bool:
    """Whether two :func:`cache_identity` records agree on all that decides the result.

    The versions of the numerical packages only (not of python or the platform); the
    modality where both records name one.

    >>> old = {"input": "a", "modality": "flair", "config": "c", "given": {}, "code": {}}
    >>> same_identity(old, {**old, "modality": "t2"}), same_identity(old, {**old, "modality": None})
    (False, True)
    """
    keys = ("input", "config", "given", "code")
    old_v, new_v = before.get("versions") or {}, after.get("versions") or {}
    return (
        all(before.get(k) == after.get(k) for k in keys)
        and _modality_change(before, after) is None
        and all(old_v.get(name) == new_v.get(name) for name in NUMERICAL_DISTRIBUTIONS)
    )


def recompute_reason(before: dict[str, Any], after: dict[str, Any]) -> str:
    """Why a patient published before was computed again, in words.

    ``before`` and ``after`` are :func:`cache_identity` of the earlier and the
    new record. In this order: its input, the modality it was segmented as or a
    given file changed (a record written before the modality was kept names none:
    not a change); the code of
    some stages or the versions of the numerical packages the keys hold moved
    (a new release, whose configuration defaults may have moved with it); the
    configuration changed; else nothing the records hold changed, and the
    results were not found in this artifact store (another ``--store``, one
    cleared, or code edited while the earlier run was under way: the records
    hold the code as the run began).

    >>> old = {"input": "a", "config": "c", "given": {}, "code": {"segment": "1", "render": "2"},
    ...        "versions": {"tumor3d": "0.1.0", "numpy": "2.4.6"}}
    >>> recompute_reason(old, {**old, "config": "d"})
    'configuration changed'
    >>> recompute_reason({**old, "modality": "flair"}, {**old, "modality": "t2"})
    'modality changed: flair -> t2'
    >>> recompute_reason(old, {**old, "given": {"brain_mask": "e3b0"}})
    'given brain mask changed'
    >>> recompute_reason(old, {**old, "given": {"models": ["9f86"]}})  # segment.learned_models
    'given models changed'
    >>> recompute_reason(old, {**old, "config": "d", "code": {"segment": "9", "render": "2"}})
    'code of 1 of 2 stages changed'
    >>> recompute_reason(old, {**old, "versions": {"tumor3d": "0.1.0", "numpy": "2.4.7"}})
    'package versions changed: numpy 2.4.6 -> 2.4.7'
    >>> recompute_reason(old, old)[:70]
    'nothing recorded changed, but the results were not in this artifact st'
    """
    if before.get("input") != after.get("input"):
        return "input changed"
    modality = _modality_change(before, after)
    if modality is not None:
        return f"modality changed: {modality[0]} -> {modality[1]}"
    old_given, new_given = before.get("given") or {}, after.get("given") or {}
    keys = ("brain_mask", "segmentation", "models")
    files = [k for k in keys if old_given.get(k) != new_given.get(k)]
    if files:
        words = {"brain_mask": "brain mask", "segmentation": "segmentation", "models": "models"}
        return f"given {' and '.join(words[k] for k in files)} changed"
    code_after = after.get("code") or {}
    moved = [s for s, digest in code_after.items() if (before.get("code") or {}).get(s) != digest]
    old_v, new_v = before.get("versions") or {}, after.get("versions") or {}
    packages = [
        f"{name} {old_v.get(name, '?')} -> {new_v[name]}"
        for name in NUMERICAL_DISTRIBUTIONS
        if name in new_v and old_v.get(name) != new_v[name]
    ]
    said = []
    if moved:
        said.append(f"code of {len(moved)} of {len(code_after)} stages changed")
    if packages:
        said.append(f"package versions changed: {', '.join(packages)}")
    if said:
        return "; ".join(said)
    if before.get("config") != after.get("config"):
        return "configuration changed"
    return (
        "nothing recorded changed, but the results were not in this artifact store (another "
        "--store, one cleared, or the code changed during the earlier run)"
    )


def changed_since(earlier: dict[str, Any], folder: str | Path, all_cached: bool) -> str | None:
    """Why ``folder``'s new result is not the one published before (``earlier``), or None.

    A recorded change (input, given file, code, versions, configuration) is said even
    when every stage was a cache hit (another patient of the same content computed it);
    with nothing recorded changed, only stages that ran need a reason.
    """
    now = cache_identity(folder)
    if now is None or (all_cached and same_identity(earlier, now)):
        return None
    return recompute_reason(earlier, now)


def patients_by_reason(pairs: Iterable[tuple[str, Any]]) -> dict[str, list[str]]:
    """Patient ids under the reason their result is not the earlier one, in order.

    ``pairs`` are ``(patient_id, reason)``; a reason that is not a non-empty string
    (None, NaN) leaves its patient out.

    >>> patients_by_reason([("p1", "input changed"), ("p2", None), ("p3", "input changed")])
    {'input changed': ['p1', 'p3']}
    """
    grouped: dict[str, list[str]] = {}
    for pid, reason in pairs:
        if isinstance(reason, str) and reason:
            grouped.setdefault(reason, []).append(str(pid))
    return grouped

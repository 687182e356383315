"""Why a re-run's result is not the folder's earlier one (tumor3d.storage.provenance).

A user audit: re-running a patient with only --modality changed republished a result
twice or half the earlier volume, and the run said either nothing (every stage a cache
hit) or that "nothing recorded changed"; the modality was not part of what the records
compare.
"""

from __future__ import annotations

import json

from tumor3d.storage.provenance import cache_identity, changed_since


def _record(folder, modality, config="c1"):
    folder.mkdir(parents=True, exist_ok=True)
    doc = {
        "input": {"digest_sha256": "d1", "modality": modality},
        "config_sha256": config,
        "stages": [{"stage": "segment-tumor", "code_sha256": "s1"}],
        "versions": {"numpy": "2.4.6"},
    }
    if modality is None:
        del doc["input"]["modality"]  # a record written before the modality was kept
    (folder / "provenance.json").write_text(json.dumps(doc))
    return folder


def test_a_changed_modality_is_the_reason_even_when_every_stage_was_a_cache_hit(tmp_path):
    flair = cache_identity(_record(tmp_path / "a", "flair"))
    assert flair["modality"] == "flair"
    now = _record(tmp_path / "b", "t2")
    for all_cached in (True, False):
        assert changed_since(flair, now, all_cached) == "modality changed: flair -> t2"
    # the same modality and nothing else: no reason when every stage was a cache hit
    assert changed_since(flair, _record(tmp_path / "c", "flair"), True) is None
    # another configuration as well: the modality is named first
    both = _record(tmp_path / "d", "t1c", config="c2")
    assert changed_since(flair, both, True) == "modality changed: flair -> t1c"


def test_a_record_without_the_modality_is_no_change_of_it(tmp_path):
    old = cache_identity(_record(tmp_path / "a", None))
    assert old["modality"] is None
    assert changed_since(old, _record(tmp_path / "b", "t2"), True) is None
    assert changed_since(old, _record(tmp_path / "c", "t2", config="c2"), True) == (
        "configuration changed"
    )

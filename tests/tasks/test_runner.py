"""The Prefect runner distrusts cache hits whose artifacts are gone or corrupted (issue 12)."""

from __future__ import annotations

import pytest

from tumor3d.storage.store import ArtifactStore
from tumor3d.tasks.runner import PrefectRunner
from tumor3d.tasks.spec import StageOutput


def _cached_output(store: ArtifactStore) -> StageOutput:
    ref = store.put_json({"eq7_mm3": 9901.0, "slices": list(range(20))})
    return StageOutput(stage="measure-volume", artifacts={"record": ref}).sealed()


def _flip_same_size(path) -> None:
    data = bytearray(path.read_bytes())
    data[5] ^= 0xFF
    path.write_bytes(bytes(data))


def test_an_intact_cache_hit_is_trusted(tmp_path):
    store = ArtifactStore(tmp_path / "store")
    runner = PrefectRunner(store, "p1", total=1)
    assert runner._distrust(_cached_output(store)) is None


def test_a_cache_hit_whose_artifact_is_corrupted_is_recomputed_and_quarantined(tmp_path):
    store = ArtifactStore(tmp_path / "store")
    out = _cached_output(store)
    path = store.path(out.artifacts["record"])
    size = path.stat().st_size
    _flip_same_size(path)  # same size: a presence (or size) check cannot see it
    assert path.stat().st_size == size
    reason = PrefectRunner(store, "p1", total=1)._distrust(out)
    assert reason is not None and "corrupted" in reason and "record" in reason
    # the bad object was moved aside, so recomputing the stage writes it afresh
    assert not path.exists()
    assert len(list((store.root / "quarantine").iterdir())) == 1


def test_a_cache_hit_whose_artifact_is_missing_is_recomputed(tmp_path):
    store = ArtifactStore(tmp_path / "store")
    out = _cached_output(store)
    store.path(out.artifacts["record"]).unlink()
    reason = PrefectRunner(store, "p1", total=1)._distrust(out)
    assert reason is not None and "record" in reason


def test_why_refused_names_an_unreadable_record():
    from tumor3d.tasks.records import why_refused

    assert "not JSON" in why_refused(b'{"metadata": {"storage_key": ', "0" * 32)


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_record_prefect_cannot_read_is_a_named_miss_not_a_silent_one(tmp_path):
    """Issue 6: Prefect's ResultStore.exists() swallows read errors and reports a plain miss.

    A torn record (a truncated file) of one stage makes Prefect recompute it;
    the stage run now says why, and the next run is all hits again.
    """
    from tumor3d.flows.patient import run_patient
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_patient

    row = write_phantom_patient(make_phantom_patient(5, patient_id="rec5", n_slices=12), tmp_path)
    out = tmp_path / "out"
    first = run_patient(row.image, out, patient_id="rec5")
    records = tmp_path / "out" / ".tumor3d-store" / "prefect-results"
    needle = '\\"stage\\": \\"segment-tumor\\"'  # the output, as escaped JSON in the record
    victim = next(f for f in records.iterdir() if needle in f.read_text())
    victim.write_bytes(victim.read_bytes()[:100])  # a torn write
    again = run_patient(row.image, out, patient_id="rec5")
    by_stage = {s.stage: s for s in again.stages}
    seg = by_stage["segment-tumor"]
    assert not seg.cached
    assert seg.repaired is not None and "refused: not JSON" in seg.repaired
    assert all(s.cached for s in again.stages if s.stage != "segment-tumor")
    assert again.metrics["volume_eq7_mm3"] == first.metrics["volume_eq7_mm3"]
    assert all(run_patient(row.image, out, patient_id="rec5").cache_hits)

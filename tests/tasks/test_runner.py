"""The Prefect runner distrusts cache hits whose artifacts are gone or corrupted (issue 12)."""

from __future__ import annotations

from storage.store import ArtifactStore
from tasks.runner import PrefectRunner
from tasks.spec import StageOutput


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

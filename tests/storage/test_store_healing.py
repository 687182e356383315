"""A store that heals: corrupted objects are quarantined and rewritten (issue 12)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tumor3d.storage.store import ArtifactStore, CorruptArtifactError, StoreError


@pytest.fixture
def store(tmp_path):
    return ArtifactStore(tmp_path / "store")


def flip_bytes(path, offset=40, n=8):
    """Corrupt a file in place, keeping its size (the case put_bytes used to miss)."""
    data = bytearray(path.read_bytes())
    for i in range(offset, offset + n):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def test_put_bytes_rewrites_a_same_size_corrupted_object(store):
    payload = bytes(range(256)) * 4
    ref = store.put_bytes(payload, kind="json", suffix=".bin")
    flip_bytes(store.path(ref))
    assert store.path(ref).stat().st_size == len(payload)
    again = store.put_bytes(payload, kind="json", suffix=".bin")
    assert again == ref
    assert store.path(ref).read_bytes() == payload
    assert [r.action for r in store.repairs] == ["rewritten"]
    assert store.get_bytes(ref) == payload


def test_put_bytes_leaves_an_intact_object_alone(store):
    ref = store.put_bytes(b"same", kind="json", suffix=".json")
    before = store.path(ref).stat().st_mtime_ns
    store.put_bytes(b"same", kind="json", suffix=".json")
    assert store.path(ref).stat().st_mtime_ns == before
    assert store.repairs == []


def test_a_digest_mismatch_quarantines_the_object(store):
    ref = store.put_bytes(b"original content", kind="json", suffix=".json")
    flip_bytes(store.path(ref), offset=2, n=4)
    bad = store.path(ref).read_bytes()
    with pytest.raises(CorruptArtifactError, match="digest mismatch.*moved to quarantine/") as info:
        store.get_bytes(ref)
    assert isinstance(info.value, StoreError)
    assert info.value.ref == ref
    assert not store.path(ref).exists()  # so the stage's rewrite is not skipped
    moved = store.root / info.value.repair.quarantined_to
    assert moved.read_bytes() == bad  # kept for inspection, never deleted
    log = [json.loads(line) for line in (store.root / "repairs.jsonl").read_text().splitlines()]
    assert log[-1]["action"] == "quarantined" and log[-1]["relpath"] == ref.relpath


def test_verify_reports_intact_missing_and_corrupted(store):
    good = store.put_bytes(b"good", kind="json", suffix=".json")
    gone = store.put_bytes(b"gone", kind="json", suffix=".json")
    bad = store.put_bytes(b"bad!", kind="json", suffix=".json")
    store.path(gone).unlink()
    flip_bytes(store.path(bad), offset=0, n=2)
    assert store.verify(good)
    assert not store.verify(gone)
    assert not store.verify(bad)
    assert not store.path(bad).exists()
    assert [r.action for r in store.repairs] == ["quarantined"]


def test_recomputing_after_a_mismatch_heals_the_store(store):
    """The stage's recompute (the same put) makes the artifact readable again."""
    volume = np.arange(4 * 5 * 6, dtype=np.float32).reshape(4, 5, 6)
    affine = np.diag([-1.0, -1.0, 5.0, 1.0])
    ref = store.put_volume(volume, affine)
    flip_bytes(store.path(ref), offset=60)
    with pytest.raises(CorruptArtifactError):
        store.get_volume(ref)
    assert store.put_volume(volume, affine) == ref  # what the recomputed stage does
    back, _ = store.get_volume(ref)
    np.testing.assert_array_equal(back, volume)
    assert ArtifactStore(store.root).verify(ref)  # and later runs see a healthy store


def test_repairs_are_readable_by_another_store_instance(store):
    ref = store.put_bytes(b"payload!", kind="json", suffix=".json")
    flip_bytes(store.path(ref), offset=0, n=3)
    other = ArtifactStore(store.root)  # what a task opens
    assert other.read_repairs() == []
    assert not other.verify(ref)
    other.put_bytes(b"payload!", kind="json", suffix=".json")  # the recomputed stage
    log = ArtifactStore(store.root).read_repairs()
    assert [r.action for r in log] == ["quarantined"]
    assert log[0].relpath == ref.relpath and log[0].quarantined_to.startswith("quarantine/")
    (store.root / "repairs.jsonl").open("a").write("{torn\n")
    assert len(store.read_repairs()) == 1

"""A store that heals: corrupted objects are quarantined and rewritten (issue 12)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tumor3d.storage.refs import CorruptArtifactError, StoreError
from tumor3d.storage.store import ArtifactStore


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


def _dead_pid() -> int:
    """The pid of a child process that has exited (reaped, so it no longer exists)."""
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_temporary_files_of_killed_writers_are_removed_and_live_ones_kept(store):
    """A SIGKILLed writer cannot remove its temporary file: the store sweeps it.

    Only temporary files whose writer is gone: a dead pid on this machine, or
    an hour untouched when written on another machine. A live writer's file,
    a final object and a file of another naming are left alone.
    """
    import os
    import time

    from tumor3d.storage.atomic import HOST_TAG, STALE_TMP_S

    ref = store.put_json({"kept": True})
    folder = store.path(ref).parent
    name = store.path(ref).name
    other = "0" * 8 if HOST_TAG != "0" * 8 else "1" * 8

    def tmp(host: str, pid: int, rand: str = "abcdef01", age_s: float = 0.0) -> os.PathLike:
        path = folder / f".{name}.tmp-{host}-{pid}-{rand}"
        path.write_bytes(b"half")
        if age_s:
            then = time.time() - age_s
            os.utime(path, (then, then))
        return path

    killed = tmp(HOST_TAG, _dead_pid())
    live = tmp(HOST_TAG, os.getpid())
    parent = tmp(HOST_TAG, os.getppid())
    remote_recent = tmp(other, _dead_pid())
    remote_old = tmp(other, 12345, age_s=STALE_TMP_S + 60)
    reused = tmp(HOST_TAG, os.getppid(), "abcdef02", age_s=STALE_TMP_S + 60)  # pid reused
    locked = tmp(HOST_TAG, _dead_pid(), "abcdef03")  # cannot be removed: left, no error
    unrelated = folder / ".notes.txt"
    unrelated.write_text("not ours")
    real_unlink = type(locked).unlink

    def unlink(self, *args, **kwargs):
        if self == locked:
            raise PermissionError(13, "Permission denied", str(self))
        return real_unlink(self, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(type(locked), "unlink", unlink)
        removed = store.clean_stale_tmp()
    assert sorted(removed) == sorted([str(killed), str(remote_old), str(reused)])
    for kept in (live, parent, remote_recent, locked, unrelated, store.path(ref)):
        assert kept.exists(), kept
    locked.unlink()
    assert store.get_json(ref) == {"kept": True}
    assert store.clean_stale_tmp() == []  # nothing left to remove


def test_atomic_writes_name_their_temporary_file_by_host_and_process(store, monkeypatch):
    """The name the sweep reads is the one the writer gives (a crash mid-write kept it)."""
    import os

    from tumor3d.storage import atomic

    seen: list[str] = []

    def crash(src, dst):
        seen.append(os.path.basename(src))
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic.os, "replace", crash)
    with pytest.raises(StoreError):
        store.put_json({"x": 1})
    m = atomic.TMP_NAME.match(seen[0])
    assert m is not None and m["host"] == atomic.HOST_TAG
    assert int(m["pid"]) == os.getpid()


@pytest.mark.parametrize(
    "relpath",
    ["../../in/scan.nii.gz", "/home/u/scan.nii.gz", "objects/{d2}/{d}/../../../../x.json",
     "objects/00/{other}.json", "objects/{d2}/{d}", "objects/{d2}/{d}.json/../x"],
)  # fmt: skip
def test_a_reference_names_only_its_own_object(store, relpath):
    """A reference (read from a shared store's record, say) whose path is not where the
    store keeps its digest's object is refused when it is read: it cannot steer a read, a
    quarantine or a rewrite to a file outside the store."""
    from pydantic import ValidationError

    from tumor3d.storage.refs import ArtifactRef

    ref = store.put_json({"x": 1})
    d = ref.digest
    bad = relpath.format(d2=d[:2], d=d, other="1" * 64)
    with pytest.raises(ValidationError, match="not where the store keeps object"):
        ArtifactRef(**{**ref.model_dump(), "relpath": bad})
    assert ArtifactRef(**ref.model_dump()) == ref  # the store's own path is accepted


def test_a_quarantine_moves_nothing_outside_the_objects(store, tmp_path):
    """A reference made without validation (``model_construct``) that names a file outside
    the store, with other bytes than its digest's: the read refuses to move it (one line),
    and the file stays where it is, unchanged."""
    from tumor3d.storage.refs import ArtifactRef

    victim = tmp_path / "in" / "scan.nii.gz"
    victim.parent.mkdir()
    victim.write_bytes(b"the patient's scan")
    ref = store.put_json({"x": 1})
    for relpath in ("../in/scan.nii.gz", str(victim)):
        forged = ArtifactRef.model_construct(**{**ref.model_dump(), "relpath": relpath})
        with pytest.raises(StoreError, match="is not an object of the store") as info:
            store.get_bytes(forged)
        assert "\n" not in str(info.value)
        assert victim.read_bytes() == b"the patient's scan"
    assert not (store.root / "quarantine").exists() and store.repairs == []
    for relpath in ("objects", "objects/ab"):  # the folders themselves are no objects
        forged = ArtifactRef.model_construct(**{**ref.model_dump(), "relpath": relpath})
        with pytest.raises(StoreError, match="is not an object of the store"):
            store._quarantine(forged.relpath, "test")


def test_a_suffix_no_reference_takes_is_refused_before_anything_is_written(store):
    for suffix in (".PLY", "", ".a.b.c", ".ply\n"):
        with pytest.raises(ValueError, match="not where the store keeps object"):
            store.put_bytes(b"x", kind="json", suffix=suffix)
    assert not (store.root / "objects").exists() or not any((store.root / "objects").rglob("*"))

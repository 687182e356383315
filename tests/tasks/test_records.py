"""Cached result records: nothing in a store is unpickled or imported or served for another key.

A store may be shared (issue 29): whoever can write it must not be able to
make the tool run code, import a module, or publish another patient's (or
another stage's) result. Every refused record is a cache miss: the stage is
recomputed and its record rewritten, so the store heals.
"""

from __future__ import annotations

import base64
import json
import os
import pickle
import sys
from pathlib import Path

import pytest

from tumor3d.storage.store import ArtifactStore
from tumor3d.tasks.records import (
    SERIALIZER_TYPE,
    ScreenedResultFolder,
    StageOutputSerializer,
    UntrustedRecord,
    screen_record,
)
from tumor3d.tasks.spec import StageOutput

KEY = "a" * 64
OTHER = "b" * 64


def _record(out: StageOutput, serializer: dict | None = None, result: str | None = None) -> bytes:
    """A record as Prefect writes it with this project's serializer."""
    body = result if result is not None else StageOutputSerializer().dumps(out).decode()
    meta = {"storage_key": KEY, "expiration": None, "prefect_version": "3",
            "serializer": serializer or {"type": SERIALIZER_TYPE}}  # fmt: skip
    return json.dumps({"metadata": meta, "result": body}).encode()


def _output(tmp_path: Path, key: str = KEY, stage: str = "segment-tumor") -> StageOutput:
    ref = ArtifactStore(tmp_path / "store").put_json({"eq7_mm3": 21779.3})
    return StageOutput(stage=stage, artifacts={"record": ref}, key=key).sealed()


class _Payload:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_a_record_of_this_project_under_its_own_key_is_trusted(tmp_path):
    out = _output(tmp_path)
    assert screen_record(_record(out), KEY) == out


def test_a_pickle_record_is_refused_without_unpickling(tmp_path):
    marker = tmp_path / "pwned"
    blob = base64.encodebytes(pickle.dumps(_Payload(marker))).decode()
    rec = _record(_output(tmp_path), {"type": "pickle", "picklelib": "cloudpickle"}, blob)
    with pytest.raises(UntrustedRecord, match="'pickle'"):
        screen_record(rec, KEY)
    assert not marker.exists()


def test_a_prefect_json_record_naming_a_class_is_refused_without_importing_it(tmp_path):
    sys.modules.pop("this", None)
    rec = _record(
        _output(tmp_path), {"type": "json"}, json.dumps({"__class__": "this.s", "data": "x"})
    )
    with pytest.raises(UntrustedRecord, match="'json'"):
        screen_record(rec, KEY)
    # the same object under this project's serializer: plain JSON, not a stage output
    rec = _record(_output(tmp_path), None, json.dumps({"__class__": "this.s", "data": "x"}))
    with pytest.raises(UntrustedRecord, match="not a stage output"):
        screen_record(rec, KEY)
    with pytest.raises(UntrustedRecord):
        StageOutputSerializer().loads(json.dumps({"__class__": "this.s", "data": "x"}).encode())
    assert "this" not in sys.modules


def test_a_record_stored_under_another_key_is_refused(tmp_path):
    """Another patient's (or another stage's) record copied over this key's."""
    moved = _record(_output(tmp_path, key=OTHER))
    with pytest.raises(UntrustedRecord, match="another key"):
        screen_record(moved, KEY)
    # re-sealing it under the new key needs the digest rule; a plain edit fails it
    edited = moved.replace(OTHER.encode(), KEY.encode())
    with pytest.raises(UntrustedRecord, match="digest"):
        screen_record(edited, KEY)


def test_the_result_folder_never_reads_or_writes_through_a_symlink(tmp_path):
    outside = tmp_path / "outside.txt"
    outside.write_text("not a record")
    folder = ScreenedResultFolder(basepath=str(tmp_path / "results"))
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / KEY).symlink_to(outside)
    with pytest.raises(UntrustedRecord, match="symlink"):
        folder.read_path(KEY)
    record = _record(_output(tmp_path))
    folder.write_path(KEY, record)
    assert outside.read_text() == "not a record"  # the link was replaced, not followed
    assert not (tmp_path / "results" / KEY).is_symlink()
    assert folder.read_path(KEY) == record
    with pytest.raises(UntrustedRecord, match="not a cache key"):
        folder.read_path("../outside.txt")


def test_a_fifo_or_an_oversized_record_is_refused_without_blocking(tmp_path):
    from tumor3d.tasks.records import MAX_RECORD_BYTES

    (tmp_path / "results").mkdir()
    folder = ScreenedResultFolder(basepath=str(tmp_path / "results"))
    os.mkfifo(tmp_path / "results" / KEY)  # opening it for reading would wait for a writer
    with pytest.raises(UntrustedRecord, match="not a regular file"):
        folder.read_path(KEY)
    (tmp_path / "results" / OTHER).write_bytes(b" " * (MAX_RECORD_BYTES + 1))
    with pytest.raises(UntrustedRecord, match="larger than"):
        folder.read_path(OTHER)


# -- end to end: the attacks of issue 29 against a real run ---------------------------


@pytest.fixture(scope="module")
def two_patients(tmp_path_factory):
    from tumor3d.flows.patient import run_patient
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_patient

    base = tmp_path_factory.mktemp("records")
    images = {}
    for seed, pid in ((5, "p1"), (9, "p2")):
        # small phantoms (128 x 128 pixels of 1.875 mm): what is tested is the records
        row = write_phantom_patient(
            make_phantom_patient(seed, patient_id=pid, n_slices=12, matrix_size=(128, 128)),
            base / pid,
        )
        images[pid] = row.image
    out = base / "out"
    first = {pid: run_patient(images[pid], out, patient_id=pid) for pid in images}
    eq7 = {pid: r.metrics["volume_eq7_mm3"] for pid, r in first.items()}
    assert eq7["p1"] != eq7["p2"]
    # per patient, each stage's artifact digests (every test leaves the store healed:
    # its last re-run is all cache hits, so these stay the stages' current results)
    digests = {pid: {s.stage: set(s.artifacts.values()) for s in r.stages}
               for pid, r in first.items()}  # fmt: skip
    return images, out, eq7, digests


def _rerun(images, out, pid="p1"):
    from tumor3d.flows.patient import run_patient

    return run_patient(images[pid], out, patient_id=pid)


def _record_of(out: Path, key: str) -> Path:
    return out / ".tumor3d-store" / "prefect-results" / key


def _key_of(out: Path, stage: str, pid: str, digests) -> str:
    """The key of ``stage`` for patient ``pid``: the one record of that stage whose artifacts
    are those of the patient's run (``digests``: stage -> artifact digests, per patient)."""
    digests = digests[pid]
    for f in (out / ".tumor3d-store" / "prefect-results").iterdir():
        if f.is_file() and not f.is_symlink():
            res = json.loads(json.loads(f.read_text())["result"])
            arts = {a["digest"] for a in res["artifacts"].values()}
            if res["stage"] == stage and arts and arts == digests[stage]:
                return f.name
    raise AssertionError(f"no record of {stage} for {pid}")


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_pickle_record_in_the_store_never_runs_and_the_store_heals(two_patients, tmp_path):
    images, out, eq7, digests = two_patients
    key = _key_of(out, "segment-tumor", "p1", digests)
    victim = _record_of(out, key)
    marker = tmp_path / "pwned"
    rec = json.loads(victim.read_text())
    rec["metadata"]["serializer"] = {"type": "pickle", "picklelib": "cloudpickle"}
    rec["result"] = base64.encodebytes(pickle.dumps(_Payload(marker))).decode()
    victim.write_text(json.dumps(rec))
    again = _rerun(images, out)
    assert not marker.exists()
    seg = {s.stage: s for s in again.stages}["segment-tumor"]
    assert not seg.cached and "'pickle'" in (seg.repaired or "")
    assert again.metrics["volume_eq7_mm3"] == eq7["p1"]
    assert all(_rerun(images, out).cache_hits)  # the record was rewritten


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_json_record_naming_a_module_imports_nothing(two_patients):
    images, out, eq7, digests = two_patients
    key = _key_of(out, "measure-volume", "p1", digests)
    victim = _record_of(out, key)
    rec = json.loads(victim.read_text())
    rec["metadata"]["serializer"] = {"type": "json"}
    rec["result"] = json.dumps({"__class__": "this.s", "data": "x"})
    victim.write_text(json.dumps(rec))
    sys.modules.pop("this", None)
    again = _rerun(images, out)
    assert "this" not in sys.modules
    assert again.metrics["volume_eq7_mm3"] == eq7["p1"]
    assert all(_rerun(images, out).cache_hits)


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_another_patients_record_copied_over_is_recomputed_not_published(two_patients):
    images, out, eq7, digests = two_patients
    k1 = _key_of(out, "segment-tumor", "p1", digests)
    k2 = _key_of(out, "segment-tumor", "p2", digests)
    assert k1 != k2
    rec = json.loads(_record_of(out, k2).read_text())
    rec["metadata"]["storage_key"] = k1  # the storage key adjusted
    _record_of(out, k1).write_text(json.dumps(rec))
    again = _rerun(images, out)
    seg = {s.stage: s for s in again.stages}["segment-tumor"]
    assert not seg.cached and "another key" in (seg.repaired or "")
    assert again.metrics["volume_eq7_mm3"] == eq7["p1"]
    assert all(_rerun(images, out).cache_hits)


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_another_stages_record_copied_over_is_recomputed_and_the_store_heals(two_patients):
    images, out, eq7, digests = two_patients
    seg = _key_of(out, "segment-tumor", "p1", digests)
    pre = _key_of(out, "preprocess", "p1", digests)
    _record_of(out, seg).write_bytes(_record_of(out, pre).read_bytes())
    again = _rerun(images, out)
    assert again.metrics["volume_eq7_mm3"] == eq7["p1"]
    assert not {s.stage: s for s in again.stages}["segment-tumor"].cached
    assert all(_rerun(images, out).cache_hits)


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_record_symlinked_outside_the_store_is_replaced_not_followed(two_patients, tmp_path):
    images, out, eq7, digests = two_patients
    key = _key_of(out, "measure-volume", "p1", digests)
    victim = _record_of(out, key)
    outside = tmp_path / "elsewhere.json"
    outside.write_bytes(victim.read_bytes())
    before = outside.read_bytes()
    victim.unlink()
    victim.symlink_to(outside)
    again = _rerun(images, out)
    measure = {s.stage: s for s in again.stages}["measure-volume"]
    assert not measure.cached and "symlink" in (measure.repaired or "")
    assert outside.read_bytes() == before  # never written through the link
    assert not victim.is_symlink()
    assert again.metrics["volume_eq7_mm3"] == eq7["p1"]
    assert all(_rerun(images, out).cache_hits)


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_sealed_record_naming_a_file_outside_the_store_touches_nothing(two_patients):
    """A store's writer reseals a record (its digest is plain SHA-256) whose artifact names
    the run's own input, absolute or relative: the record is refused (the stage recomputed),
    the input stays where it was, byte for byte, and nothing is quarantined."""
    import hashlib

    from tumor3d.storage.refs import canonical_dumps

    images, out, eq7, digests = two_patients
    image = Path(images["p1"])
    before = image.read_bytes()
    store = out / ".tumor3d-store"
    relative = os.path.relpath(image, store)
    for relpath in (str(image.resolve()), relative):
        key = _key_of(out, "measure-volume", "p1", digests)
        victim = _record_of(out, key)
        rec = json.loads(victim.read_text())
        res = json.loads(rec["result"])
        name = next(iter(res["artifacts"]))
        res["artifacts"][name]["relpath"] = relpath
        del res["digest"]  # resealed as StageOutput.content_digest seals: no secret
        text = canonical_dumps(res).encode()
        res["digest"] = hashlib.sha256(b"tumor3d-stage-output-v1\0" + text).hexdigest()
        rec["result"] = json.dumps(res, sort_keys=True)
        victim.write_text(json.dumps(rec))
        again = _rerun(images, out)
        measure = {s.stage: s for s in again.stages}["measure-volume"]
        assert not measure.cached and "schema" in (measure.repaired or "")
        assert image.read_bytes() == before
        assert again.metrics["volume_eq7_mm3"] == eq7["p1"]
    assert not (store / "quarantine").exists()
    assert all(_rerun(images, out).cache_hits)

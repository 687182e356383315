"""The process's memo of decoded volumes (:mod:`tumor3d.storage.product_memo`).

What a stage stores is handed to the next stage and to publishing from memory:
the value must be the one a fresh read of the store gives (the naive reference
here), read-only, keyed by content so another content is never served, and the
memo bounded by bytes.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from tumor3d.flows.patient import run_stages_direct
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage import product_memo
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.storage.product_memo import ProductMemo
from tumor3d.storage.store import ArtifactStore, CorruptArtifactError, StoreError
from tumor3d.tasks.kinds import load

MIB = 1024 * 1024


@pytest.fixture
def memo(monkeypatch):
    """A fresh process memo of 64 MiB for the test."""
    fresh = ProductMemo(64 * MIB)
    monkeypatch.setattr(product_memo, "_PROCESS_MEMO", [fresh])
    return fresh


def _affine(rng):
    """Spacings and origin that float32 cannot hold exactly (the sform is float32)."""
    aff = np.diag([0.9375001, 0.9375003, 5.1000001, 1.0])
    aff[:3, 3] = rng.uniform(-120, 120, 3)
    return aff


def _cases(rng):
    """(kind, array as given, dtype to store) covering casts, masks and memory layouts."""
    f64 = rng.normal(100.0, 30.0, (6, 9, 7))  # not float32-exact
    labels = rng.integers(0, 3, (6, 9, 7)).astype(np.uint8)  # a mask of 0/1/2
    return [
        ("image", f64, "float32"),
        ("scan", f64.astype(np.float32), "float32"),
        ("image", np.asfortranarray(f64).astype(np.float32), None),  # Fortran order
        ("image", rng.integers(-300, 300, (9, 6, 7)).astype(np.int16).transpose(1, 0, 2), None),
        ("mask", labels > 0, None),  # bool -> uint8
        ("mask", labels, None),  # labels read back as bool
        ("mask", labels.astype(np.float64)[::-1], "uint8"),  # whole floats, a reversed view
    ]


def test_a_stored_volume_is_kept_as_a_fresh_read_of_the_store_returns_it(tmp_path, memo):
    store = ArtifactStore(tmp_path)
    rng = np.random.default_rng(0)
    for kind, array, dtype in _cases(rng):
        ref = store.put_volume(array, _affine(rng), kind=kind, dtype=dtype)
        kept = memo.get(ref.digest)
        assert kept is not None, (kind, array.dtype)
        fresh_array, fresh_affine = store.get_volume(ref)  # the naive reference: decode
        assert kept[0].dtype == fresh_array.dtype, (kind, array.dtype)
        assert kept[0].flags.c_contiguous and fresh_array.flags.c_contiguous
        np.testing.assert_array_equal(kept[0], fresh_array)
        np.testing.assert_array_equal(kept[1], fresh_affine)  # exactly: float32 sform
        assert kept[1].dtype == fresh_affine.dtype == np.float64


def test_load_volume_serves_the_kept_value_read_only_without_reading(tmp_path, memo):
    store = ArtifactStore(tmp_path)
    mask = np.zeros((4, 5, 6), dtype=bool)
    mask[1:3, 2:4, 1:5] = True
    ref = store.put_volume(mask, np.eye(4), kind="mask")
    store.path(ref).unlink()  # from now on only the memo has it
    array, affine = store.load_volume(ref)
    np.testing.assert_array_equal(array, mask)
    assert not array.flags.writeable and not affine.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        array[0, 0, 0] = True
    with pytest.raises(StoreError, match="missing"):
        store.get_volume(ref)  # get_volume always reads the store
    vol = load(store, ref)  # a stage input: the same arrays
    assert vol.array is array and not vol.array.flags.writeable
    assert memo.hits >= 2


def test_a_miss_reads_the_store_once_then_serves_from_memory(tmp_path, memo):
    store = ArtifactStore(tmp_path)
    image = np.arange(60, dtype=np.float32).reshape(3, 4, 5)
    ref = store.put_volume(image, np.eye(4))
    memo.clear()  # as in another process, or after eviction
    first, _ = store.load_volume(ref)
    assert memo.misses == 1 and not first.flags.writeable
    store.path(ref).unlink()
    again, _ = store.load_volume(ref)
    assert again is first and memo.hits == 1
    np.testing.assert_array_equal(again, image)


def test_the_producer_changing_its_array_after_storing_changes_nothing_kept(tmp_path, memo):
    store = ArtifactStore(tmp_path)
    image = np.ones((3, 4, 5), dtype=np.float32)
    ref = store.put_volume(image, np.eye(4))
    image[:] = 7.0  # the caller's own array
    np.testing.assert_array_equal(store.load_volume(ref)[0], 1.0)
    assert image.flags.writeable  # the caller's array is not made read-only


def test_another_content_is_another_key_and_a_corrupted_file_is_still_found(tmp_path, memo):
    store = ArtifactStore(tmp_path)
    a = np.zeros((3, 4, 5), dtype=np.float32)
    b = a + 1.0
    ref_a = store.put_volume(a, np.eye(4))
    ref_b = store.put_volume(b, np.eye(4))
    assert ref_a.digest != ref_b.digest
    np.testing.assert_array_equal(store.load_volume(ref_b)[0], b)
    np.testing.assert_array_equal(store.load_volume(ref_a)[0], a)
    # a file edited in the store: the memo serves the content its digest names, and the
    # store's own check (the runner's distrust of a cached hit) still finds the file bad
    path = store.path(ref_a)
    path.write_bytes(store.path(ref_b).read_bytes())
    np.testing.assert_array_equal(store.load_volume(ref_a)[0], a)
    assert not store.verify(ref_a)  # quarantined, so the stage that made it runs again
    memo.clear()
    store.put_volume(a, np.eye(4))  # rewritten
    path.write_bytes(store.path(ref_b).read_bytes())
    memo.clear()
    with pytest.raises(CorruptArtifactError):
        store.load_volume(ref_a)  # a miss reads and checks the digest


def test_the_bound_evicts_the_least_recently_used_and_refuses_what_cannot_fit():
    memo = ProductMemo(max_bytes=300)
    arrays = {k: (np.full(100, i, dtype=np.uint8),) for i, k in enumerate("abcd")}
    for key in "abc":
        memo.put(key, arrays[key])
    assert memo.nbytes == 300 and len(memo) == 3
    assert memo.get("a") is arrays["a"]  # now the most recent
    memo.put("d", arrays["d"])
    assert memo.get("b") is None  # the least recently used went
    assert [memo.get(k) is not None for k in "acd"] == [True, True, True]
    assert memo.nbytes == 300
    memo.put("e", (np.zeros(301, dtype=np.uint8),))  # larger than the bound: not kept
    assert memo.get("e") is None and memo.nbytes == 300
    memo.put("a", (np.zeros(50, dtype=np.uint8),))  # replacing counts the new size
    assert memo.nbytes == 250
    memo.discard(["a", "zz"])
    assert memo.nbytes == 200 and memo.get("a") is None


def test_no_memo_keeps_nothing_and_still_returns_read_only_arrays(tmp_path, monkeypatch):
    monkeypatch.setattr(product_memo, "_PROCESS_MEMO", [ProductMemo(0)])
    store = ArtifactStore(tmp_path)
    ref = store.put_volume(np.ones((2, 3, 4), dtype=np.float32), np.eye(4))
    array, _ = store.load_volume(ref)
    assert not array.flags.writeable and len(product_memo.products()) == 0


def test_the_bound_holds_and_the_count_agrees_under_concurrent_lanes():
    memo = ProductMemo(max_bytes=40_000)
    errors: list[BaseException] = []

    def lane(seed: int) -> None:
        rng = np.random.default_rng(seed)
        try:
            for _ in range(400):
                key = f"{rng.integers(0, 50):064x}"
                if rng.random() < 0.5:
                    memo.put(key, (np.zeros(int(rng.integers(1, 4000)), dtype=np.uint8),))
                else:
                    memo.get(key)
                if rng.random() < 0.05:
                    memo.discard([key])
        except BaseException as exc:  # noqa: BLE001 - reported by the main thread
            errors.append(exc)

    threads = [threading.Thread(target=lane, args=(s,)) for s in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    held = sum(v[0].nbytes for v in memo._entries.values())
    assert memo.nbytes == held <= memo.max_bytes


def test_a_patient_run_from_memory_stores_the_same_artifacts_as_one_from_the_store(
    tmp_path, monkeypatch
):
    patient = make_phantom_patient(3, patient_id="memo3", n_slices=16, matrix_size=(128, 128))
    image = write_phantom_patient(patient, tmp_path / "in").image
    digests = {}
    for mib in (64, 0):
        monkeypatch.setattr(product_memo, "_PROCESS_MEMO", [ProductMemo(mib * MIB)])
        run = run_stages_direct(image, tmp_path / f"store{mib}", patient_id="memo3")
        digests[mib] = {
            (stage, name): ref.digest
            for stage, out in run.outputs.items()
            for name, ref in out.artifacts.items()
        }
        if mib:
            assert product_memo.products().hits >= 10  # the stages' volume inputs
            assert product_memo.products().misses == 0
    assert digests[64] == digests[0]


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_a_published_patient_leaves_nothing_in_the_memo(tmp_path, memo):
    """A warm runner serves many commands: each patient's volumes go once it is published."""
    from tumor3d.flows.patient import run_patient

    patient = make_phantom_patient(4, patient_id="memo4", n_slices=16, matrix_size=(128, 128))
    image = write_phantom_patient(patient, tmp_path / "in").image
    result = run_patient(image, tmp_path / "out", patient_id="memo4")
    assert memo.misses + memo.hits > 0  # the stages did go through the memo
    kept = {d for run in result.stages for d in run.artifacts.values()} & set(memo._entries)
    assert not kept and memo.nbytes == 0


def test_a_local_clusters_worker_processes_keep_a_small_memo(monkeypatch):
    """Worker processes never publish, so nothing forgets their volumes: a smaller bound,
    unless the user set one (which the workers inherit)."""
    pytest.importorskip("prefect_dask", reason="prefect-dask not installed")
    from tumor3d.flows.dask_runner import WORKER_PRODUCT_MEMO_MIB, DaskSpec, cohort_task_runner

    monkeypatch.delenv(product_memo.MEMO_ENV, raising=False)
    kwargs = cohort_task_runner(2, DaskSpec(n_workers=2)).cluster_kwargs
    assert kwargs["env"] == {product_memo.MEMO_ENV: str(WORKER_PRODUCT_MEMO_MIB)}
    assert WORKER_PRODUCT_MEMO_MIB < product_memo.DEFAULT_MAX_MIB
    threads = DaskSpec(n_workers=2, processes=False)  # they share the flow's process and memo
    assert "env" not in cohort_task_runner(2, threads).cluster_kwargs
    monkeypatch.setenv(product_memo.MEMO_ENV, "8")
    assert "env" not in cohort_task_runner(2, DaskSpec(n_workers=2)).cluster_kwargs

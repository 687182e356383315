"""The S3 artifact store against a local S3 server (moto in server mode on 127.0.0.1).

Independent expectations: the local ``ArtifactStore`` on the same data (same
digests, same object names, same bytes), boto3's own view of the bucket
(no temporary or partial keys), and the cohort run on a local store (same
volumes). Skipped, with the reason, when moto or s3fs is not installed.
"""

from __future__ import annotations

import socket
import time
import uuid

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("s3fs", reason="s3fs not installed (pip install 'tumor3d[s3]')")
moto_server = pytest.importorskip(
    "moto.server", reason="moto[server] not installed (pip install 'moto[server]')"
)

from phantom_rows import small_phantom_rows  # noqa: E402

from tumor3d.flows.cli import app  # noqa: E402
from tumor3d.flows.cohort import run_cohort  # noqa: E402
from tumor3d.geometry.mesh import Mesh  # noqa: E402
from tumor3d.storage import objectstore  # noqa: E402
from tumor3d.storage.manifest import write_manifest  # noqa: E402
from tumor3d.storage.objectstore import ObjectStore, open_store  # noqa: E402
from tumor3d.storage.refs import CorruptArtifactError, StoreError  # noqa: E402
from tumor3d.storage.remote_publish import (  # noqa: E402
    MARKER,
    RemoteFolder,
    publish_folder,
    published_names,
    read_marker,
    verify_folder,
)
from tumor3d.storage.store import ArtifactStore  # noqa: E402
from tumor3d.tasks.caching import stage_cache_policy  # noqa: E402

BUCKET = "tumor3d-test"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def s3_endpoint():
    """A moto S3 server on 127.0.0.1 for this module, with one bucket."""
    port = _free_port()
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    endpoint = f"http://127.0.0.1:{port}"
    mp = pytest.MonkeyPatch()
    for k, v in {
        "AWS_ENDPOINT_URL": endpoint,
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_REGION": "us-east-1",
    }.items():
        mp.setenv(k, v)
    import boto3

    client = boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1")
    client.create_bucket(Bucket=BUCKET)
    yield client
    mp.undo()
    server.stop()


def _keys(client, prefix: str) -> list[str]:
    pages = client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix)
    return sorted(o["Key"] for page in pages for o in page.get("Contents", []))


def _stamps(client, prefix: str) -> dict[str, tuple[str, object]]:
    pages = client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix)
    return {o["Key"]: (o["ETag"], o["LastModified"]) for p in pages for o in p.get("Contents", [])}


def _mesh() -> Mesh:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)
    return Mesh(vertices=v, faces=f)


def test_same_digests_names_and_bytes_as_the_local_store(s3_endpoint, tmp_path):
    s3 = open_store(f"s3://{BUCKET}/same")
    local = ArtifactStore(tmp_path / "local")
    assert isinstance(s3, ObjectStore) and type(local) is ArtifactStore
    vol = np.random.default_rng(0).random((3, 4, 5)).astype(np.float32)
    affine = np.diag([0.9, 0.9, 5.0, 1.0])
    mask = vol > 0.5
    pairs = [
        (s3.put_volume(vol, affine), local.put_volume(vol, affine)),
        (s3.put_volume(mask, affine, kind="mask"), local.put_volume(mask, affine, kind="mask")),
        (s3.put_mesh(_mesh()), local.put_mesh(_mesh())),
        (s3.put_table([{"a": 1, "b": 2.5}]), local.put_table([{"a": 1, "b": 2.5}])),
        (s3.put_json({"x": [1, 2]}), local.put_json({"x": [1, 2]})),
    ]  # fmt: skip
    for r_s3, r_local in pairs:
        assert r_s3 == r_local  # digest, relpath, metadata
        body = s3_endpoint.get_object(Bucket=BUCKET, Key=f"same/{r_s3.relpath}")["Body"].read()
        assert body == local.path(r_local).read_bytes()
    back, back_affine = s3.get_volume(pairs[0][0])
    assert np.array_equal(back, vol) and np.allclose(back_affine, affine)
    assert s3.get_mesh(pairs[2][0]).n_faces == 4
    assert s3.get_json(pairs[4][0]) == {"x": [1, 2]}
    # every key is a final object: no temporary key left behind
    assert all(k.startswith("same/objects/") for k in _keys(s3_endpoint, "same/"))


def test_cache_keys_do_not_depend_on_the_store_location():
    policy = stage_cache_policy("preprocess", ("tumor3d.tasks.preprocess",))
    ref = {"kind": "scan", "digest": "a" * 64, "relpath": f"objects/aa/{'a' * 64}.nii.gz"}
    from tumor3d.storage.refs import ArtifactRef

    inputs = {"scan": ArtifactRef(**ref), "store_root": "/srv/store"}
    local_key = policy.compute_key(None, inputs, {})
    s3_key = policy.compute_key(None, {**inputs, "store_root": f"s3://{BUCKET}/p"}, {})
    assert local_key == s3_key


@pytest.mark.parametrize("backend", ["s3", "memory"])
def test_a_write_that_fails_is_one_line_and_leaves_no_object(backend, request, monkeypatch):
    """On S3 one PUT writes an object, all-or-nothing: a PUT that fails leaves none. A
    back-end without that promise (fsspec's memory file system here) writes under
    ``tmp/`` and copies: a writer stopped between the two leaves no final object, and its
    temporary key goes."""
    if backend == "s3":
        request.getfixturevalue("s3_endpoint")
        store, step = ObjectStore(f"s3://{BUCKET}/crash"), "pipe_file"
    else:
        store, step = ObjectStore(f"memory://crash-{uuid.uuid4().hex[:8]}"), "cp_file"

    def killed(*args, **kwargs):
        raise ConnectionError("worker killed mid-write")

    monkeypatch.setattr(store.fs, step, killed)
    with pytest.raises(StoreError, match="cannot write the artifact.*worker killed") as exc:
        store.put_json({"half": True})
    assert "\n" not in str(exc.value) and str(exc.value).startswith(f"{store.url}/objects/")
    assert store.fs.find(store._base) == []  # no object, no temporary key
    monkeypatch.undo()
    ref = store.put_json({"half": True})
    assert store.get_json(ref) == {"half": True}
    assert store.fs.find(store._base) == [f"{store._base}/{ref.relpath}"]
    store.fs.rm(store._base, recursive=True)


def _s3_calls(monkeypatch, fs) -> list[str]:
    """The S3 API operations s3fs sends through ``fs`` from now on, in order."""
    calls: list[str] = []
    real = fs._call_s3

    async def counted(method, *args, **kwargs):
        calls.append(method)
        return await real(method, *args, **kwargs)

    monkeypatch.setattr(fs, "_call_s3", counted)
    return calls


def test_on_s3_an_artifact_or_record_is_one_request_to_write_and_one_to_read(
    s3_endpoint, monkeypatch
):
    """A round trip costs latency and money on S3: a new artifact is one GET (is it
    there?) and one PUT (an S3 PUT is all-or-nothing: no temporary key to copy), a
    present one one GET, a read one GET, a cache record one PUT and one GET; no HEAD
    to size an object, no listing to tell a key from a folder, no server-side copy."""
    from tumor3d.tasks.records import ScreenedRemoteFolder

    store = ObjectStore(f"s3://{BUCKET}/calls")
    calls = _s3_calls(monkeypatch, store.fs)
    ref = store.put_json({"n": 1})
    assert calls == ["get_object", "put_object"]
    del calls[:]
    assert store.put_json({"n": 1}) == ref and calls == ["get_object"]  # present: no write
    del calls[:]
    assert store.get_json(ref) == {"n": 1} and calls == ["get_object"]
    assert _keys(s3_endpoint, "calls/") == [f"calls/{ref.relpath}"]  # no temporary key
    records = ScreenedRemoteFolder(
        basepath=f"s3://{BUCKET}/calls/prefect-results",
        settings=objectstore._storage_options("s3"),
    )
    calls = _s3_calls(monkeypatch, records.filesystem)
    records.write_path("a" * 32, b"{}")
    assert calls == ["put_object"]  # no folder to make on S3
    del calls[:]
    assert records.read_raw("a" * 32) == b"{}" and calls == ["get_object"]
    del calls[:]
    with pytest.raises(FileNotFoundError):  # a cache miss: one request
        records.read_raw("b" * 32)
    assert calls == ["get_object"]


def test_a_corrupted_object_is_quarantined_and_rewritten(s3_endpoint):
    store = ObjectStore(f"s3://{BUCKET}/heal")
    ref = store.put_json({"v": 1})
    key = f"heal/{ref.relpath}"
    good = s3_endpoint.get_object(Bucket=BUCKET, Key=key)["Body"].read()
    s3_endpoint.put_object(Bucket=BUCKET, Key=key, Body=good.replace(b"1", b"2"))
    assert not store.verify(ref)  # digest checked on read: quarantined
    assert key not in _keys(s3_endpoint, "heal/")
    assert [k for k in _keys(s3_endpoint, "heal/quarantine/")]
    with pytest.raises(StoreError, match="is missing"):
        store.get_bytes(ref)
    assert store.put_json({"v": 1}) == ref and store.get_json(ref) == {"v": 1}
    s3_endpoint.put_object(Bucket=BUCKET, Key=key, Body=good.replace(b"1", b"3"))
    with pytest.raises(CorruptArtifactError):
        store.get_bytes(ref)
    actions = [r.action for r in ObjectStore(f"s3://{BUCKET}/heal").read_repairs()]
    assert actions == ["quarantined", "quarantined"]


def _rows(folder, seeds):
    return small_phantom_rows(folder, seeds, "s3p")


@pytest.fixture(scope="module")
def local_pair(tmp_path_factory, prefect_harness):
    """Phantoms s3p0 and s3p1 and their cohort with a local store and a local ``--out``:
    the reference that the S3 runs of several tests must equal (only read by them)."""
    folder = tmp_path_factory.mktemp("s3-local")
    rows = _rows(folder / "in", [0, 1])
    local = run_cohort(rows, folder / "local", workers=2)
    assert local.exit_code == 0, [p.error for p in local.patients]
    return rows, local, folder / "local"


def test_an_unreachable_endpoint_fails_in_one_line_before_any_patient(
    s3_endpoint, tmp_path, monkeypatch
):
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{_free_port()}")
    # a refused connection is the same at any count: one botocore attempt, not 3
    monkeypatch.setattr(objectstore, "S3_MAX_ATTEMPTS", 1)
    rows = _rows(tmp_path / "in", [0])
    out = tmp_path / "out"
    t0 = time.perf_counter()
    with pytest.raises(StoreError, match="cannot reach the artifact store") as exc:
        run_cohort(rows, out, workers=1, store_dir=f"s3://{BUCKET}/down")
    assert "\n" not in str(exc.value) and f"s3://{BUCKET}/down" in str(exc.value)
    assert time.perf_counter() - t0 < 60
    assert not out.exists()
    manifest = write_manifest(rows, tmp_path / "m.csv")
    res = CliRunner().invoke(
        app, ["cohort", str(manifest), "--out", str(out), "--store", f"s3://{BUCKET}/down"]
    )
    assert res.exit_code == 3 and "cannot reach the artifact store" in res.output
    assert not out.exists()


def test_a_missing_bucket_is_refused_for_the_store_and_for_the_outputs(
    s3_endpoint, tmp_path, monkeypatch
):
    rows = _rows(tmp_path / "in", [0])
    with pytest.raises(StoreError, match="bucket 'no-such-bucket' does not exist"):
        run_cohort(rows, tmp_path / "o", workers=1, store_dir="s3://no-such-bucket/p")
    with pytest.raises(StoreError, match="bucket 'no-such-bucket' does not exist") as exc:
        run_cohort(rows, "s3://no-such-bucket/out", workers=1, store_dir=tmp_path / "st")
    assert "s3://no-such-bucket/out" in str(exc.value)
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{_free_port()}")
    monkeypatch.setattr(objectstore, "S3_MAX_ATTEMPTS", 1)  # refused at any count (above)
    manifest = write_manifest(rows, tmp_path / "m.csv")
    res = CliRunner().invoke(
        app, ["cohort", str(manifest), "--out", f"s3://{BUCKET}/down-out", "--store",
              str(tmp_path / "st")],
    )  # fmt: skip
    assert res.exit_code == 3 and "cannot reach the output location" in res.output
    assert not (tmp_path / "st").exists()  # nothing started


# -- publishing outputs to the object store (tumor3d.storage.remote_publish) -------------------


def _folder(root, files: dict[str, bytes]):
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root


def _body(client, key: str) -> bytes:
    return client.get_object(Bucket=BUCKET, Key=key)["Body"].read()


V1 = {
    "metrics.parquet": b"PAR1" * 100,
    "report.html": b"<html>1</html>",
    "views/a.png": b"\x89PNG1",
}


def test_a_published_folder_holds_the_staged_bytes_and_a_marker_written_last(s3_endpoint, tmp_path):
    import hashlib
    import json

    staged = _folder(tmp_path / "v1", V1)
    url = f"s3://{BUCKET}/pub/p1"
    assert publish_folder(staged, url) == url
    keys = _keys(s3_endpoint, "pub/")
    assert keys == sorted([f"pub/p1/{r}" for r in V1] + [f"pub/p1/{MARKER}"])  # no tmp key
    for rel, data in V1.items():
        assert _body(s3_endpoint, f"pub/p1/{rel}") == data
    marker = json.loads(_body(s3_endpoint, f"pub/p1/{MARKER}"))
    assert marker["files"] == {
        r: {"sha256": hashlib.sha256(d).hexdigest(), "size": len(d)} for r, d in V1.items()
    }
    out = RemoteFolder(f"s3://{BUCKET}/pub")
    assert published_names(out) == ["p1"] and verify_folder(out, "p1") == []
    # a new version replaces the folder as a whole: a file it lacks is gone
    v2 = {"metrics.parquet": b"PAR1" * 50, "report.html": b"<html>2</html>"}
    publish_folder(_folder(tmp_path / "v2", v2), url)
    assert _keys(s3_endpoint, "pub/") == sorted([f"pub/p1/{r}" for r in v2] + [f"pub/p1/{MARKER}"])
    assert _body(s3_endpoint, "pub/p1/report.html") == b"<html>2</html>"
    assert verify_folder(out, "p1") == []


def test_an_interrupted_publish_leaves_no_marker_and_a_rerun_completes_it(
    s3_endpoint, tmp_path, monkeypatch
):
    url = f"s3://{BUCKET}/cut/p1"
    out = RemoteFolder(f"s3://{BUCKET}/cut")
    publish_folder(_folder(tmp_path / "v1", V1), url)
    v2 = {**V1, "report.html": b"<html>v2</html>"}
    real_copy, copies = out.fs.cp_file, []

    def copy_then_die(src, dst, **kw):
        if len(copies) == 1:  # the worker dies after the first file reached its final key
            raise ConnectionError("worker killed mid-publish")
        copies.append(dst)
        return real_copy(src, dst, **kw)

    monkeypatch.setattr(out.fs, "cp_file", copy_then_die)
    with pytest.raises(StoreError, match="left unpublished") as exc:
        publish_folder(_folder(tmp_path / "v2", v2), url)
    assert "\n" not in str(exc.value) and copies
    monkeypatch.undo()
    keys = _keys(s3_endpoint, "cut/")
    assert f"cut/p1/{MARKER}" not in keys  # the old marker went before the first copy
    assert read_marker(out, "p1") is None and published_names(out) == []
    assert verify_folder(out, "p1") == [f"{out.url}/p1: not published (no valid {MARKER})"]
    assert not [k for k in keys if "/.tumor3d-tmp/" in k]
    publish_folder(tmp_path / "v2", url)  # the re-run completes it
    assert published_names(out) == ["p1"] and verify_folder(out, "p1") == []
    assert _body(s3_endpoint, "cut/p1/report.html") == b"<html>v2</html>"
    assert not [k for k in _keys(s3_endpoint, "cut/") if "/.tumor3d-tmp/" in k]


def test_a_corrupted_object_is_detected_after_the_copy_and_after_publication(
    s3_endpoint, tmp_path, monkeypatch
):
    url = f"s3://{BUCKET}/bad/p1"
    out = RemoteFolder(f"s3://{BUCKET}/bad")
    staged = _folder(tmp_path / "v1", V1)
    real_copy = out.fs.cp_file

    def corrupting_copy(src, dst, **kw):
        real_copy(src, dst, **kw)
        if dst.endswith("report.html"):
            out.fs.pipe_file(dst, b"<html>X</html>")  # same size, other bytes

    monkeypatch.setattr(out.fs, "cp_file", corrupting_copy)
    with pytest.raises(StoreError, match="does not match the staged file's sha256"):
        publish_folder(staged, url)
    monkeypatch.undo()
    assert read_marker(out, "p1") is None and published_names(out) == []
    publish_folder(staged, url)
    assert verify_folder(out, "p1") == []
    s3_endpoint.put_object(Bucket=BUCKET, Key="bad/p1/views/a.png", Body=b"\x89PNG2")
    assert verify_folder(out, "p1") == [
        f"{out.url}/p1/views/a.png: content does not match its sha256 in {MARKER}"
    ]
    publish_folder(staged, url)  # same staged bytes: the corrupted object is re-published
    assert (
        verify_folder(out, "p1") == []
        and _body(s3_endpoint, "bad/p1/views/a.png") == V1["views/a.png"]
    )
    s3_endpoint.delete_object(Bucket=BUCKET, Key="bad/p1/report.html")
    assert read_marker(out, "p1") is None  # a listed file missing: not published
    publish_folder(staged, url)  # a re-publish repairs it (marker no longer valid)
    assert verify_folder(out, "p1") == []


@pytest.mark.parametrize("marker_etags", [True, False])
def test_a_rerun_from_the_cache_republishes_an_object_edited_since(
    s3_endpoint, marker_etags, monkeypatch
):
    """A re-run whose stages were all cache hits (``reuse``, the same publish key) uploads
    nothing to an intact folder, but an object written since, with other bytes of the
    same size (a forged volume in metrics.parquet), is published again: told by its ETag
    against the marker's, or, for a marker without ETags (written before them), by the
    bytes read back, after which the marker has them (the next re-run reads nothing back)."""
    import json

    import tumor3d.storage.remote_publish as rp
    from tumor3d.storage.remote_publish import publish_files

    out = RemoteFolder(f"s3://{BUCKET}/reuse{int(marker_etags)}")
    prefix = f"reuse{int(marker_etags)}/p1"
    publish_files(out, "p1", V1, exclusive=True, key="k1")
    marker = json.loads(_body(s3_endpoint, f"{prefix}/{MARKER}"))
    assert set(marker["etags"]) == set(V1)  # moto gives ETags, as S3 does
    if not marker_etags:
        del marker["etags"]
        s3_endpoint.put_object(Bucket=BUCKET, Key=f"{prefix}/{MARKER}", Body=json.dumps(marker))
    before = _stamps(s3_endpoint, f"{prefix}/")
    publish_files(out, "p1", V1, exclusive=True, key="k1", reuse=True)
    after = _stamps(s3_endpoint, f"{prefix}/")
    rewritten = {k for k in set(before) | set(after) if before.get(k) != after.get(k)}
    # intact: nothing uploaded (a marker without ETags gets them)
    assert rewritten == (set() if marker_etags else {f"{prefix}/{MARKER}"})
    upgraded = json.loads(_body(s3_endpoint, f"{prefix}/{MARKER}"))
    assert set(upgraded["etags"]) == set(V1) and all(upgraded["etags"].values())
    assert {k: v for k, v in upgraded.items() if k != "etags"} == {
        k: v for k, v in marker.items() if k != "etags"
    }
    with monkeypatch.context() as m:  # now told by the ETags: nothing read back
        m.setattr(rp, "verify_folder", lambda *a: pytest.fail("read back"))
        publish_files(out, "p1", V1, exclusive=True, key="k1", reuse=True)
    if not marker_etags:  # another writer's marker, written during the read-back, stays
        theirs = {**marker, "published_utc": "another writer"}
        s3_endpoint.put_object(Bucket=BUCKET, Key=f"{prefix}/{MARKER}", Body=json.dumps(marker))

        def meanwhile(*args):
            s3_endpoint.put_object(Bucket=BUCKET, Key=f"{prefix}/{MARKER}", Body=json.dumps(theirs))
            return []

        with monkeypatch.context() as m:
            m.setattr(rp, "verify_folder", meanwhile)
            publish_files(out, "p1", V1, exclusive=True, key="k1", reuse=True)
        # not written over (theirs lists these same files: nothing to publish again)
        assert json.loads(_body(s3_endpoint, f"{prefix}/{MARKER}")) == theirs
    forged = b"PAR2" + V1["metrics.parquet"][4:]  # same size, other bytes
    s3_endpoint.put_object(Bucket=BUCKET, Key=f"{prefix}/metrics.parquet", Body=forged)
    assert read_marker(out, "p1") is not None  # the sizes alone see nothing
    publish_files(out, "p1", V1, exclusive=True, key="k1", reuse=True)
    assert _body(s3_endpoint, f"{prefix}/metrics.parquet") == V1["metrics.parquet"]
    assert verify_folder(out, "p1") == []


@pytest.fixture(scope="module")
def s3_cohort(s3_endpoint, local_pair):
    """The S3 cohorts' one computation, read by the three tests below: the phantoms of
    ``local_pair`` published to ``s3://{BUCKET}/outs`` with the default store beside them
    on S3 (``outs/.tumor3d-store``), computed on two Dask worker *processes*
    (``--dask-workers 2``) when the Dask extra is installed, else by the local runner.

    The folders handed to the uploader are captured as they were staged. One run serves
    the store, the publishing and the worker processes: three separate S3 cohorts of two
    patients each cost about 20 s of a test worker more (reports/test_suite.md).
    """
    import tumor3d.tasks.publish as publish_mod  # where the uploads are made

    try:
        import prefect_dask  # noqa: F401

        from tumor3d.flows.dask_runner import DaskSpec

        dask = DaskSpec(n_workers=2)
    except ImportError:
        dask = None
    staged: dict[str, dict[str, bytes]] = {}
    real = publish_mod.publish_folder

    def spy(folder, url, **kwargs):
        staged[url] = {
            p.relative_to(folder).as_posix(): p.read_bytes()
            for p in folder.rglob("*")
            if p.is_file()
        }
        return real(folder, url, **kwargs)

    rows = local_pair[0]
    url = f"s3://{BUCKET}/outs"
    mp = pytest.MonkeyPatch()
    mp.setattr(publish_mod, "publish_folder", spy)
    try:
        first = run_cohort(rows, url, workers=2, dask=dask)
    finally:
        mp.undo()
    assert first.exit_code == 0, [p.error for p in first.patients]
    return url, first, staged, dask is not None


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_cohort_with_an_s3_store_matches_a_local_store_and_reruns_from_cache(
    s3_endpoint, local_pair, s3_cohort, tmp_path
):
    """The S3 store holds every artifact of the cohort (the same digests as a local store)
    and the cache records; a local ``--out`` with that store keeps nothing locally and is
    all hits, in this process, not the workers that wrote (a new worker process would load
    numpy, numba's kernels and Prefect afresh for the same check)."""
    rows, local, _ = local_pair
    _, first, _, _ = s3_cohort
    for a, b in zip(local.patients, first.patients, strict=True):
        assert b.metrics["volume_eq7_mm3"] == a.metrics["volume_eq7_mm3"]
        assert b.metrics["volume_mesh_mm3"] == a.metrics["volume_mesh_mm3"]
        assert [s.artifacts for s in b.stages] == [s.artifacts for s in a.stages]
        assert not any(s.cached for s in b.stages)  # its own store: computed afresh
    keys = _keys(s3_endpoint, "outs/.tumor3d-store/")
    digests = {d for p in first.patients for s in p.stages for d in s.artifacts.values()}
    stored = {k.rsplit("/", 1)[-1].split(".")[0] for k in keys if "/objects/" in k}
    assert digests <= stored  # every artifact is on S3 ...
    assert any(k.startswith("outs/.tumor3d-store/prefect-results/") for k in keys)  # ... the cache
    assert not [k for k in keys if k.startswith("outs/.tumor3d-store/tmp/")]
    store = f"s3://{BUCKET}/outs/.tumor3d-store"
    again = run_cohort(rows, tmp_path / "out", workers=2, store_dir=store)
    assert again.workers == 2 and all(s.cached for p in again.patients for s in p.stages)
    assert [p.metrics["volume_eq7_mm3"] for p in again.patients] == [
        p.metrics["volume_eq7_mm3"] for p in first.patients
    ]
    assert (tmp_path / "out" / "s3p0" / "metrics.parquet").is_file()
    assert not (tmp_path / "out" / ".tumor3d-store").exists()  # nothing kept locally


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_dask_worker_processes_share_the_s3_store_and_its_cache(s3_endpoint, s3_cohort):
    """Two Dask worker *processes* (--dask-workers 2) computed ``s3_cohort``: the store, the
    Prefect result block and the endpoint from the environment reached them (the test
    above finds their artifacts and cache records in the bucket and re-runs all hits)."""
    pytest.importorskip("prefect_dask", reason="prefect-dask not installed")
    _, first, _, on_dask = s3_cohort
    assert on_dask and first.workers == 2
    assert [p.status for p in first.patients] == ["ok", "ok"], [p.error for p in first.patients]
    assert any(k.startswith("outs/.tumor3d-store/objects/") for k in _keys(s3_endpoint, "outs/"))


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_cohort_published_to_s3_is_the_local_publish_and_reports_removed_patients(
    s3_endpoint, local_pair, s3_cohort
):
    """``--out s3://``: every patient's objects are the bytes of its local staging folder
    (captured as handed to the uploader), the same files and deterministic bytes as a
    local ``--out``, a marker per patient and for the cohort files; a re-run without a
    patient reports it removed (a prefix without a marker is no patient), and, every stage
    of the patient it keeps cached, rewrites no object of that patient's folder."""
    rows, local, local_out = local_pair
    url, first, staged, _ = s3_cohort
    assert [p.output_dir for p in first.patients] == [f"{url}/s3p0", f"{url}/s3p1"]
    out = RemoteFolder(url)
    assert published_names(out) == ["s3p0", "s3p1"]
    for p_local, p_s3 in zip(local.patients, first.patients, strict=True):
        pid = p_s3.patient_id
        files = staged[f"{url}/{pid}"]
        keys = _keys(s3_endpoint, f"outs/{pid}/")
        assert keys == sorted([f"outs/{pid}/{r}" for r in files] + [f"outs/{pid}/{MARKER}"])
        for rel, data in files.items():
            assert _body(s3_endpoint, f"outs/{pid}/{rel}") == data, rel
        assert verify_folder(out, pid) == []
        local_dir = local_out / pid
        local_files = {
            p.relative_to(local_dir).as_posix() for p in local_dir.rglob("*") if p.is_file()
        }
        assert set(files) == local_files
        for rel in ("tumor_mask.nii.gz", "tumor_mask_slices.nii.gz", "tumor.ply", "slices.parquet"):
            assert files[rel] == (local_dir / rel).read_bytes(), rel
        assert p_s3.metrics["volume_eq7_mm3"] == p_local.metrics["volume_eq7_mm3"]
    root = _keys(s3_endpoint, "outs/")
    for name in ("cohort.parquet", "cohort.md", "cohort.html", MARKER):
        assert f"outs/{name}" in root
    assert verify_folder(out, "") == []
    assert b"s3p0/report.html" in _body(s3_endpoint, "outs/cohort.html")  # link to a published file
    assert any(k.startswith("outs/.tumor3d-store/objects/") for k in root)  # default store on S3
    assert not [k for k in root if k.startswith("outs/.tumor3d-tmp/")]
    # a prefix without a marker (an interrupted publish) is not a published patient
    s3_endpoint.put_object(Bucket=BUCKET, Key="outs/ghost/metrics.parquet", Body=b"half")
    before = _stamps(s3_endpoint, "outs/s3p0/")
    assert len(before) > 5
    time.sleep(1.1)  # LastModified has a resolution of a second
    again = run_cohort(rows[:1], url, workers=1)
    assert again.removed == ["s3p1"] and all(s.cached for s in again.patients[0].stages)
    assert _stamps(s3_endpoint, "outs/s3p0/") == before  # a cached patient uploads nothing
    assert verify_folder(out, "s3p0") == []
    md = _body(s3_endpoint, "outs/cohort.md").decode()
    assert "Removed from the manifest" in md and "s3p1" in md
    page = _body(s3_endpoint, "outs/cohort.html").decode()
    assert "kept (not deleted): s3p1." in page.split("<h2>Removed from the manifest</h2>")[1]
    assert f"outs/s3p1/{MARKER}" in _keys(s3_endpoint, "outs/s3p1/")  # reported, not deleted


# -- issue 29: `run` to s3 is s3; a cached re-run uploads nothing -----------------------


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_harness")
def test_run_with_an_s3_output_or_store_writes_the_bucket_not_a_local_folder(
    s3_endpoint, tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    row = _rows(tmp_path / "in", [3])[0]
    args = ["run", str(row.image), "--patient-id", "s3p3"]
    res = CliRunner().invoke(app, [*args, "--out", f"s3://{BUCKET}/single"])
    assert res.exit_code in (0, 4), res.output
    assert not (tmp_path / "s3:").exists()
    keys = _keys(s3_endpoint, "single/")
    assert f"single/s3p3/{MARKER}" in keys and "single/s3p3/provenance.json" in keys
    assert any(k.startswith("single/.tumor3d-store/objects/") for k in keys)  # the store too
    assert verify_folder(RemoteFolder(f"s3://{BUCKET}/single"), "s3p3") == []
    out = tmp_path / "o"
    res = CliRunner().invoke(app, [*args, "--out", str(out), "--store", f"s3://{BUCKET}/store1"])
    assert res.exit_code in (0, 4), res.output
    assert not (tmp_path / "s3:").exists() and not (out / ".tumor3d-store").exists()
    assert (out / "s3p3" / "provenance.json").is_file()
    assert any(k.startswith("store1/objects/") for k in _keys(s3_endpoint, "store1/"))
    # an unreachable bucket: one line, before any work
    res = CliRunner().invoke(app, [*args, "--out", "s3://no-such-bucket/x"])
    assert res.exit_code == 3 and "no-such-bucket" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "s3:").exists()


def test_temporary_keys_of_killed_writers_are_removed_by_age(s3_endpoint, monkeypatch):
    """A writer killed between its temporary PUT and the copy (a back-end or version that
    wrote through ``tmp/``) leaves a ``tmp/`` key: swept by age."""
    store = ObjectStore(f"s3://{BUCKET}/sweep")
    ref = store.put_json({"kept": True})
    s3_endpoint.put_object(Bucket=BUCKET, Key="sweep/tmp/x.json.4242-abcdef01", Body=b"half")
    assert store.clean_stale_tmp() == []  # written just now: perhaps a live writer's
    assert "sweep/tmp/x.json.4242-abcdef01" in _keys(s3_endpoint, "sweep/")
    removed = store.clean_stale_tmp(max_age_s=-1.0)  # as if an hour had passed
    assert removed == [f"s3://{BUCKET}/sweep/tmp/x.json.4242-abcdef01"]
    assert _keys(s3_endpoint, "sweep/") == [f"sweep/{ref.relpath}"]
    assert store.get_json(ref) == {"kept": True}


def test_an_unfinished_upload_of_a_killed_writer_is_aborted_by_age(s3_endpoint):
    """On S3 a killed writer of a large object (s3fs uploads from 100 MiB in parts) leaves
    an unfinished multipart upload: invisible, billed. The sweep aborts the store's own
    by age, nothing outside its prefix. (moto dates every upload 2010-11-10: an age
    limit of 10^12 s stands for a live writer's.)"""
    store = ObjectStore(f"s3://{BUCKET}/mpu")
    big = "mpu/objects/ab/" + "ab" * 32 + ".nii.gz"
    for key in (big, "elsewhere/objects/big.nii.gz"):
        s3_endpoint.create_multipart_upload(Bucket=BUCKET, Key=key)

    def uploads(prefix):
        listed = s3_endpoint.list_multipart_uploads(Bucket=BUCKET, Prefix=prefix)
        return [u["Key"] for u in listed.get("Uploads", [])]

    assert store.clean_stale_tmp(max_age_s=1e12) == [] and uploads("mpu/") == [big]
    assert store.clean_stale_tmp(max_age_s=-1.0) == [f"s3://{BUCKET}/{big}"]
    assert uploads("mpu/") == [] and uploads("elsewhere/") == ["elsewhere/objects/big.nii.gz"]


def test_the_sweep_reads_every_page_of_unfinished_uploads(s3_endpoint, monkeypatch):
    """S3 lists unfinished uploads 1,000 a page (moto: all in one); the sweep follows the
    pages' markers. Here S3's paging with one upload a page, in front of moto's list."""
    store = ObjectStore(f"s3://{BUCKET}/paged")
    keys = [f"paged/objects/{c}{c}/" + c * 64 + ".nii.gz" for c in "abc"]
    for key in keys:
        s3_endpoint.create_multipart_upload(Bucket=BUCKET, Key=key)
    real, calls = store.fs.call_s3, []

    def paged(method, **kwargs):
        if method != "list_multipart_uploads":
            return real(method, **kwargs)
        calls.append(dict(kwargs))
        key_after = kwargs.pop("KeyMarker", "")
        id_after = kwargs.pop("UploadIdMarker", "")
        listed = real(method, **kwargs)
        ups = sorted(listed.get("Uploads", []), key=lambda u: (u["Key"], u["UploadId"]))
        ups = [u for u in ups if (u["Key"], u["UploadId"]) > (key_after, id_after)]
        page = dict(listed, Uploads=ups[:1], IsTruncated=len(ups) > 1)
        if len(ups) > 1:
            page.update(NextKeyMarker=ups[0]["Key"], NextUploadIdMarker=ups[0]["UploadId"])
        return page

    monkeypatch.setattr(store.fs, "call_s3", paged)
    assert store.clean_stale_tmp(max_age_s=-1.0) == [f"s3://{BUCKET}/{k}" for k in keys]
    assert len(calls) == 3 and calls[1]["KeyMarker"] == keys[0]
    listed = s3_endpoint.list_multipart_uploads(Bucket=BUCKET, Prefix="paged/")
    assert listed.get("Uploads", []) == []


@pytest.mark.parametrize("sizes_first", [True, False])
def test_a_read_is_one_get_with_any_s3fs_version(sizes_first):
    """s3fs 2026.3 and later size an object before reading it unless told
    ``max_concurrency=1``; earlier ones read in one GET and refuse the keyword."""
    asked = []

    class S3(type(ObjectStore(f"s3://{BUCKET}/x").fs)):
        if sizes_first:

            async def _cat_file(self, path, version_id=None, start=None, end=None,
                                chunksize=None, max_concurrency=None):  # fmt: skip
                raise AssertionError("not called")
        else:

            async def _cat_file(self, path, version_id=None, start=None, end=None):
                raise AssertionError("not called")

        def cat_file(self, path, **kwargs):
            asked.append(kwargs)
            return b"bytes"

    fs = S3.__new__(S3)  # no session: only the reader's signature and call are looked at
    assert objectstore.read_object(fs, "b/k") == b"bytes"
    assert asked == [{"max_concurrency": 1} if sizes_first else {}]

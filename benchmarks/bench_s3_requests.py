"""S3 requests of a cohort on an object store: one request per object against generic fsspec.

Every S3 request is a round trip (tens of milliseconds in a region, more across
one) and is billed. ``tumor3d.storage.objectstore`` writes an artifact with one
PUT (an S3 PUT is all-or-nothing) and reads one with one GET
(:func:`~tumor3d.storage.objectstore.read_object`), the Prefect cache records
too (:class:`~tumor3d.tasks.records.ScreenedRemoteFolder`), and publishing copies
with ``cp_file`` (:func:`~tumor3d.storage.objectstore.copy_object`). The peer,
run in the same process on the same phantoms, is the generic fsspec path those
replaced: ``cat_file`` (a HEAD to size the object, a listing when it is missing,
then the GET), a temporary key copied with ``fs.copy`` (globs and folders
expanded by listings) and deleted, Prefect's own ``RemoteFileSystem.write_path``
(``makedirs``: a HEAD of the bucket).

The cohort: two phantom patients, ``--out s3://bench/<mode>`` (the store beside
it on S3), the local runner, one lane; then the same command again (every stage
a cache hit). The S3 endpoint is a moto server in this process (no network
latency: the wall times are the client's and the server's CPU). Run::

    nice -n 10 .venv/bin/python benchmarks/bench_s3_requests.py
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import logging
import os
import re
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from moto import server as moto_server

BUCKET = "bench"
_REQUEST = re.compile(r'"(?:\x1b\[[\d;]*m)*(GET|PUT|HEAD|DELETE|POST) (\S*)')


class _Counter(logging.Handler):
    """Counts the S3 server's requests by method (werkzeug's access log)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.by_method: collections.Counter[str] = collections.Counter()

    def emit(self, record: logging.LogRecord) -> None:
        m = _REQUEST.search(record.getMessage())
        if m:
            method = "LIST" if "list-type=" in m[2] else m[1]
            self.by_method[method] += 1


@contextlib.contextmanager
def _generic_fsspec() -> Iterator[None]:
    """The peer: fsspec's generic calls where the project makes one request."""
    from prefect.filesystems import RemoteFileSystem

    from tumor3d.storage import objectstore, remote_publish
    from tumor3d.tasks import records

    saved = [
        (objectstore, "put_is_atomic", objectstore.put_is_atomic),
        (objectstore, "read_object", objectstore.read_object),
        (objectstore, "copy_object", objectstore.copy_object),
        (records, "read_object", records.read_object),
        (records, "put_is_atomic", records.put_is_atomic),
        (remote_publish, "read_object", remote_publish.read_object),
        (remote_publish, "copy_object", remote_publish.copy_object),
    ]
    generic = {
        "put_is_atomic": lambda fs: False,
        "read_object": lambda fs, key: fs.cat_file(key),
        "copy_object": lambda fs, src, dst: fs.copy(src, dst),
    }
    for module, name, _ in saved:
        setattr(module, name, generic[name])
    write_path = records.ScreenedRemoteFolder.write_path
    records.ScreenedRemoteFolder.write_path = lambda self, path, content, _sync=None: (  # type: ignore[method-assign]
        RemoteFileSystem.write_path(self, path, content, _sync=True)  # type: ignore[call-arg]
    )
    try:
        yield
    finally:
        for module, name, value in saved:
            setattr(module, name, value)
        records.ScreenedRemoteFolder.write_path = write_path  # type: ignore[method-assign]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    with contextlib.ExitStack() as stack:
        _bench(stack)


def _bench(stack: contextlib.ExitStack) -> None:
    port = _free_port()
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    stack.callback(server.stop)
    endpoint = f"http://127.0.0.1:{port}"
    os.environ.update(
        AWS_ENDPOINT_URL=endpoint, AWS_ACCESS_KEY_ID="bench", AWS_SECRET_ACCESS_KEY="bench",
        AWS_DEFAULT_REGION="us-east-1", AWS_REGION="us-east-1",
    )  # fmt: skip
    import boto3

    boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1").create_bucket(Bucket=BUCKET)
    counter = _Counter()
    werkzeug = logging.getLogger("werkzeug")
    werkzeug.addHandler(counter)
    werkzeug.setLevel(logging.INFO)
    werkzeug.propagate = False

    from tumor3d.flows.cohort import run_cohort
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_patient

    folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-s3-")))
    rows = [
        write_phantom_patient(make_phantom_patient(s, patient_id=f"b{s}"), folder / f"b{s}")
        for s in (0, 1)
    ]

    def run(mode: str) -> list[tuple[str, int, dict[str, int], float]]:
        out = []
        for label in ("first run", "re-run (cached)"):
            counter.by_method.clear()
            t0 = time.perf_counter()
            result = run_cohort(rows, f"s3://{BUCKET}/{mode}", workers=1)
            wall = time.perf_counter() - t0
            assert result.exit_code in (0, 4), [p.error for p in result.patients]
            out.append((label, sum(counter.by_method.values()), dict(counter.by_method), wall))
        return out

    run("warm-up")  # imports, the temporary Prefect server, numba's cache
    with _generic_fsspec():
        generic = run("generic")
    ours = run("one-request")
    print(
        "| run | fsspec's generic calls: requests (wall) "
        "| one request per object: requests (wall) | requests ratio |"
    )
    print("|---|---|---|---|")
    for (label, n_g, _, w_g), (_, n_o, _, w_o) in zip(generic, ours, strict=True):
        print(f"| {label} | {n_g} ({w_g:.1f} s) | {n_o} ({w_o:.1f} s) | {n_g / n_o:.2f}x |")
    for (label, _, by_g, _), (_, _, by_o, _) in zip(generic, ours, strict=True):
        methods = sorted(set(by_g) | set(by_o))
        each = ", ".join(f"{m} {by_g.get(m, 0)} -> {by_o.get(m, 0)}" for m in methods)
        print(f"\n{label}: {each}")


if __name__ == "__main__":
    main()

"""Code digests are computed once per process, even when threads ask for them at once.

A cohort's lanes and task threads compute a stage's code digest concurrently the
first time it is needed. If a source file changes between two threads' reads (an
edit while a run is going on), a plain ``functools.cache`` lets both compute and
keeps the last: two lanes then key the same stage differently within one process,
and the record written under the key that lost is never found again (issue 32:
the cohort re-run's intermittent misses of one patient's stages).
"""

from __future__ import annotations

import threading

from tumor3d.tasks import caching


def _tiny_package(root) -> None:
    # laid out as the repository: tumor3d.tasks is the folder tasks/ (package-dir)
    (root / "tumor3d").mkdir()
    (root / "tasks").mkdir()
    (root / "tumor3d" / "__init__.py").write_text("")
    (root / "tasks" / "__init__.py").write_text("")
    (root / "tasks" / "probe.py").write_text("LIMIT = 1\n")


def test_a_file_edited_while_two_threads_digest_it_gives_one_digest(tmp_path, monkeypatch):
    _tiny_package(tmp_path)
    probe = tmp_path / "tasks" / "probe.py"
    roots, root = ("tumor3d.tasks.probe",), str(tmp_path)
    read_done, release = threading.Event(), threading.Event()
    first = threading.current_thread()  # replaced by the first worker below
    original = caching._syntax_digest_of

    def slow_first_reader(name, path, base):
        digest = original(name, path, base)  # the file is read here
        if name == "tumor3d.tasks.probe" and threading.current_thread() is first:
            read_done.set()
            assert release.wait(10)
        return digest

    monkeypatch.setattr(caching, "_syntax_digest_of", slow_first_reader)
    caching.module_closure.cache_clear()
    caching.code_digest.cache_clear()
    results: dict[str, str] = {}

    def digest(label: str) -> None:
        results[label] = caching.code_digest(roots, root)

    try:
        first = threading.Thread(target=digest, args=("first",))
        first.start()
        assert read_done.wait(10)
        probe.write_text("LIMIT = 2\n")  # edited after the first read, before the second
        second = threading.Thread(target=digest, args=("second",))
        second.start()
        second.join(2.0)  # with a plain cache it computes (from the edited file) meanwhile
        release.set()
        first.join(10)
        second.join(10)
        assert set(results) == {"first", "second"}
        assert results["second"] == results["first"]
        # the process keeps that first value: the edit takes effect in a new process
        assert caching.code_digest(roots, root) == results["first"]
    finally:
        release.set()
        caching.module_closure.cache_clear()
        caching.code_digest.cache_clear()

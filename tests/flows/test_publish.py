"""Publishing as one unit: no input ever replaced, leftovers of killed runs cleaned."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from storage.publish import check_output_not_input, clean_stale_staging, staged_folder
from tumor3d.errors import InputError


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_folder_that_is_or_contains_an_input_is_refused(tmp_path):
    d = tmp_path / "series"
    d.mkdir()
    (d / "a.dcm").write_bytes(b"x")
    with pytest.raises(InputError, match="would delete the input"):
        check_output_not_input(d, [d])  # the DICOM folder itself
    with pytest.raises(InputError, match="would delete the input"):
        check_output_not_input(tmp_path, [d / "a.dcm"])  # a parent of the input
    check_output_not_input(tmp_path / "other", [d / "a.dcm"])  # a sibling is fine


def test_killed_run_leftovers_are_cleaned_by_the_next_publish(tmp_path):
    dead = _dead_pid()
    stale = tmp_path / f".p1.partial-{dead}-0123abcd"
    stale_old = tmp_path / f".p1.old-{dead}-89abcdef"
    live = tmp_path / f".p1.partial-{os.getpid()}-deadbeef"  # a concurrent run of ours
    other = tmp_path / f".p2.partial-{dead}-0123abcd"  # another patient's: not ours to clean
    for folder in (stale, stale_old, live, other):
        folder.mkdir()
        (folder / "tumor.ply").write_bytes(b"half")
    with staged_folder(tmp_path, "p1") as staging:
        (staging / "metrics.parquet").write_bytes(b"new")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(["p1", live.name, other.name])
    assert (tmp_path / "p1" / "metrics.parquet").read_bytes() == b"new"
    assert clean_stale_staging(tmp_path, "p2") == [other]


def test_failure_while_staging_leaves_the_old_folder(tmp_path):
    (tmp_path / "p1").mkdir()
    (tmp_path / "p1" / "old.txt").write_text("old")
    with pytest.raises(RuntimeError), staged_folder(tmp_path, "p1") as staging:
        (staging / "new.txt").write_text("new")
        raise RuntimeError("killed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p1"]
    assert (tmp_path / "p1" / "old.txt").read_text() == "old"


def test_republish_replaces_the_folder_as_a_whole(tmp_path):
    for content in ("one", "two"):
        with staged_folder(tmp_path, "p1") as staging:
            (staging / f"{content}.txt").write_text(content)
    assert sorted(p.name for p in (tmp_path / "p1").iterdir()) == ["two.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p1"]

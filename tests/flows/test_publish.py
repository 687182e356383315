"""Publishing as one unit: no input ever replaced, leftovers of killed runs cleaned."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from tumor3d.errors import InputError
from tumor3d.storage.publish import (
    PUBLISH_MANIFEST,
    check_destination,
    check_output_not_input,
    check_replaceable,
    check_same_input,
    clean_stale_staging,
    staged_folder,
)

#: What tumor3d writes: the publish manifest, and provenance naming its version.
MANIFEST = json.dumps({"format": 1, "key": "k", "files": {}})
PROVENANCE = json.dumps({"versions": {"tumor3d": "0.1.0"}})


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
    """Any patient's leftovers of this machine's dead publishers go, another machine's
    only once untouched for an hour (its pids cannot be asked here); a live run's stay.
    Folders named before the host tag: their own name's only, as before."""
    from tumor3d.storage.store import HOST_TAG

    dead, me = _dead_pid(), os.getpid()
    other_host = "0123abcd" if HOST_TAG != "0123abcd" else "4567cdef"
    stale = tmp_path / f".p1.partial-{HOST_TAG}-{dead}-0123abcd"
    stale_old = tmp_path / f".p1.old-{HOST_TAG}-{dead}-89abcdef"
    live = tmp_path / f".p1.partial-{HOST_TAG}-{me}-deadbeef"  # a concurrent run of ours
    other = tmp_path / f".p2.partial-{HOST_TAG}-{dead}-0123abcd"  # another patient's, dead
    remote = tmp_path / f".p3.partial-{other_host}-{me}-0123abcd"  # another machine's
    remote_old = tmp_path / f".p4.partial-{other_host}-{me}-0123abcd"
    reused = tmp_path / f".p5.partial-{HOST_TAG}-{me}-0123abcd"  # ours by pid, hour-old: reused
    legacy = tmp_path / f".p1.partial-{dead}-0123abcd"  # no host tag: p1's
    legacy_other = tmp_path / f".p2.old-{dead}-0123abcd"  # no host tag: p2's, not p1's
    folders = (stale, stale_old, live, other, remote, remote_old, reused, legacy, legacy_other)
    for folder in folders:
        folder.mkdir()
        (folder / "tumor.ply").write_bytes(b"half")
    two_hours_ago = time.time() - 7200.0
    for old in (remote_old, reused):  # the store's rule for its temporary files
        os.utime(old, (two_hours_ago, two_hours_ago))
    with staged_folder(tmp_path, "p1") as staging:
        assert staging.name.startswith(f".p1.partial-{HOST_TAG}-{me}-")
        (staging / "metrics.parquet").write_bytes(b"new")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(["p1", live.name, remote.name, legacy_other.name])
    assert (tmp_path / "p1" / "metrics.parquet").read_bytes() == b"new"
    assert clean_stale_staging(tmp_path, "p2") == [legacy_other]


def test_failure_while_staging_leaves_the_old_folder(tmp_path):
    (tmp_path / "p1").mkdir()
    (tmp_path / "p1" / "old.txt").write_text("old")
    (tmp_path / "p1" / PUBLISH_MANIFEST).write_text(MANIFEST)  # a tumor3d result
    with pytest.raises(RuntimeError), staged_folder(tmp_path, "p1") as staging:
        (staging / "new.txt").write_text("new")
        raise RuntimeError("killed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p1"]
    assert (tmp_path / "p1" / "old.txt").read_text() == "old"


def test_republish_replaces_the_folder_as_a_whole(tmp_path):
    for content in ("one", "two"):
        with staged_folder(tmp_path, "p1") as staging:
            (staging / f"{content}.txt").write_text(content)
            (staging / "provenance.json").write_text(PROVENANCE)  # marks a tumor3d result
    assert sorted(p.name for p in (tmp_path / "p1").iterdir()) == ["provenance.json", "two.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p1"]


def _files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


@pytest.mark.parametrize(
    "marker, content",
    [
        (None, None),
        (PUBLISH_MANIFEST, MANIFEST),
        ("provenance.json", PROVENANCE),
        # another pipeline's provenance.json: the name alone does not make a tumor3d result
        ("provenance.json", json.dumps({"pipeline": "fmriprep", "versions": {"fsl": "6"}})),
        (PUBLISH_MANIFEST, "not json"),
    ],
)
def test_only_a_tumor3d_result_or_an_empty_folder_is_replaced(tmp_path, marker, content):
    """A folder of the user's own files under the patient's name is never deleted."""
    own = tmp_path / "data"
    (own / "sub").mkdir(parents=True)
    (own / "sub" / "notes.txt").write_text("mine")
    if marker is not None:
        (own / marker).write_text(content)
    before = _files(own)
    ours = content in (MANIFEST, PROVENANCE)
    if not ours:
        with pytest.raises(InputError, match="is not a tumor3d result") as err:
            check_replaceable(own)
        assert str(own) in str(err.value)
        with pytest.raises(InputError, match="is not a tumor3d result"):
            with staged_folder(tmp_path, "data") as staging:  # the mechanism refuses too
                (staging / "tumor.ply").write_text("new")
        assert _files(own) == before and (own / "sub" / "notes.txt").read_text() == "mine"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]  # no staging left
    else:
        check_replaceable(own)
        with staged_folder(tmp_path, "data") as staging:
            (staging / "tumor.ply").write_text("new")
        assert _files(own) == ["tumor.ply"]


def test_a_symbolic_link_is_not_replaced(tmp_path):
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "provenance.json").write_text(PROVENANCE)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "p1").symlink_to(target)
    with pytest.raises(InputError, match="is a symbolic link"):
        check_replaceable(tmp_path / "out" / "p1")
    assert (tmp_path / "out" / "p1").is_symlink() and (target / "provenance.json").is_file()


def test_a_folder_put_in_place_while_staging_is_checked_again_before_the_swap(tmp_path):
    """A concurrent run, or a user, may create the folder after the entry check."""
    with pytest.raises(InputError, match="is not a tumor3d result"):
        with staged_folder(tmp_path, "p1") as staging:
            (staging / "tumor.ply").write_text("new")
            (tmp_path / "p1").mkdir()
            (tmp_path / "p1" / "theirs.txt").write_text("theirs")
    assert _files(tmp_path / "p1") == ["theirs.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p1"]  # the staging was removed
    calls = []
    with staged_folder(tmp_path, "p2", check=calls.append) as staging:
        (staging / "a.txt").write_text("a")
    assert calls == [tmp_path / "p2", tmp_path / "p2"]  # at entry and before the swap


def test_an_absent_or_empty_folder_may_be_published_but_not_over_a_file(tmp_path):
    check_replaceable(tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    check_replaceable(tmp_path / "empty")
    (tmp_path / "p1").write_text("a file named like the patient")
    with pytest.raises(InputError, match="exists and is not a folder"):
        check_replaceable(tmp_path / "p1")
    with pytest.raises(InputError, match="exists and is not a folder"):
        with staged_folder(tmp_path, "p1"):
            pass
    assert (tmp_path / "p1").read_text() == "a file named like the patient"


def _result_of(folder, digest, name="flair.nii.gz", location="1" * 64):
    folder.mkdir(parents=True)
    record = {
        "versions": {"tumor3d": "0.1.0"},
        "input": {"name": name, "digest_sha256": digest, "location_sha256": location},
    }
    (folder / "provenance.json").write_text(json.dumps(record))


def test_a_derived_id_never_replaces_the_results_of_another_input(tmp_path):
    """pat3/flair.nii.gz then pat4/flair.nii.gz into one --out both derive the id 'flair'."""
    _result_of(tmp_path / "flair", "a" * 64)
    check_same_input(tmp_path / "flair", "a" * 64)  # the same content again: a re-run
    check_same_input(tmp_path / "flair", "c" * 64, location="1" * 64)  # the same file, edited
    with pytest.raises(InputError, match="holds the results of another input") as err:
        check_same_input(tmp_path / "flair", "b" * 64, location="2" * 64, suggestion="pat4_flair")
    msg = str(err.value)
    assert "flair.nii.gz, SHA-256 aaaaaaaaaaaa" in msg and "--patient-id pat4_flair" in msg
    # the content is hashed only when the location does not decide
    hashed = []
    check_same_input(tmp_path / "flair", lambda: hashed.append(1) or "x", location="1" * 64)
    assert hashed == []
    with pytest.raises(InputError, match="another input"):
        check_same_input(tmp_path / "flair", lambda: hashed.append(1) or "x", location="2" * 64)
    assert hashed == [1]
    check_same_input(tmp_path / "absent", "b" * 64)  # nothing published yet
    (tmp_path / "odd").mkdir()
    (tmp_path / "odd" / "provenance.json").write_text("not json")
    check_same_input(tmp_path / "odd", "b" * 64)  # no readable record: check_replaceable's job


def test_check_destination_applies_the_input_rule_only_for_a_derived_id(tmp_path):
    _result_of(tmp_path / "flair", "a" * 64)
    check_destination(tmp_path / "flair", [tmp_path / "x.nii.gz"])  # an id the user gave
    with pytest.raises(InputError, match="another input"):
        check_destination(tmp_path / "flair", [tmp_path / "x.nii.gz"], derived_from="b" * 64)
    with pytest.raises(InputError, match="would delete the input"):
        check_destination(tmp_path / "flair", [tmp_path / "flair" / "x.nii.gz"])


def test_prepare_source_applies_the_destination_rules_before_any_work(tmp_path):
    """The flow's own entry (also for the Python API), not only the CLI's preflight."""
    import nibabel as nib
    import numpy as np

    from tumor3d.flows.patient import prepare_source

    rng = np.random.default_rng(0)
    for folder in ("pat3", "pat4"):
        (tmp_path / folder).mkdir()
        img = nib.Nifti1Image((rng.random((8, 8, 3)) + 1).astype(np.float32), np.eye(4))
        nib.save(img, tmp_path / folder / "flair.nii.gz")
    out = tmp_path / "out"
    _result_of(out / "flair", "a" * 64)  # another input's results under the derived id
    with pytest.raises(InputError, match="holds the results of another input file"):
        prepare_source(tmp_path / "pat4" / "flair.nii.gz", out_dir=out)
    given = prepare_source(tmp_path / "pat4" / "flair.nii.gz", patient_id="flair", out_dir=out)
    assert given.id_derived is False
    assert prepare_source(tmp_path / "pat4" / "flair.nii.gz").id_derived is True
    (out / "mine").mkdir()
    (out / "mine" / "x.txt").write_text("x")
    with pytest.raises(InputError, match="is not a tumor3d result"):
        prepare_source(tmp_path / "pat3" / "flair.nii.gz", patient_id="mine", out_dir=out)


def test_a_cohort_row_whose_folder_is_not_a_result_is_refused_before_any_work(tmp_path):
    from tumor3d.storage.cohort_rows import validate_rows as _validate_rows

    (tmp_path / "pat1").mkdir()
    (tmp_path / "pat1" / "notes.txt").write_text("mine")
    rows = [{"patient_id": "pat1", "image": str(tmp_path / "a.nii.gz")}]
    with pytest.raises(InputError, match="is not a tumor3d result"):
        _validate_rows(rows, tmp_path)
    (tmp_path / "pat1" / "provenance.json").write_text(PROVENANCE)
    _validate_rows(rows, tmp_path)


def test_a_full_disk_while_publishing_names_the_folder(tmp_path):
    """Issue 29: ENOSPC from a write names no file; the error names the folder published."""
    import errno

    from tumor3d.flows.cli import EXIT_ENVIRONMENT, _error_line

    with pytest.raises(OSError) as exc:
        with staged_folder(tmp_path, "pat") as staging:
            (staging / "a.txt").write_text("x")
            raise OSError(errno.ENOSPC, "No space left on device")  # as a full disk's write()
    assert exc.value.errno == errno.ENOSPC and exc.value.filename == str(tmp_path / "pat")
    text, code = _error_line(exc.value)
    assert code == EXIT_ENVIRONMENT and text.startswith(f"{tmp_path / 'pat'}: ")
    assert "ENOSPC" in text and "\n" not in text
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing half-written

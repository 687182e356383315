"""One writer per output folder (tumor3d.storage.folder_lock): a second cohort command on the
same DIR stops at once, in one line naming the holder, and a killed holder blocks nothing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import pytest
from phantom_rows import small_phantom_rows

from tumor3d.flows.cli.errors import EXIT_ENVIRONMENT, _error_line
from tumor3d.flows.cohort import run_cohort
from tumor3d.storage.folder_lock import (
    LOCK_NAME,
    FolderBusyError,
    patient_lock_name,
    writing_folder,
)


def test_a_second_writer_is_refused_naming_the_first_and_may_write_after_it(tmp_path):
    out = tmp_path / "out"
    with writing_folder(out):
        with pytest.raises(FolderBusyError) as busy, writing_folder(out):
            pass
        text = str(busy.value)
        assert text.startswith(f"{out}: another tumor3d command is writing this folder")
        assert f"pid {os.getpid()} on " in text and "\n" not in text
        assert _error_line(busy.value) == (text, EXIT_ENVIRONMENT)  # exit code 3
    with writing_folder(out):  # released at the end of the first
        pass
    assert (out / LOCK_NAME).is_file()


def test_runs_share_the_folder_and_hold_their_patient_alone(tmp_path):
    """Runs hold the folder's lock shared and their patient's exclusively: two runs of
    other patients go together, a cohort command on the folder stops, and so does a
    second run of one patient (a user audit: both said ok for a folder holding one)."""
    out = tmp_path / "out"
    with writing_folder(out, shared=True), writing_folder(out, shared=True):
        with pytest.raises(FolderBusyError, match="writing this folder"), writing_folder(out):
            pass
        with writing_folder(out, name=patient_lock_name("p1")):
            with (
                pytest.raises(FolderBusyError, match=f"^{out}: another tumor3d command is "
                              "writing p1 here"),
                writing_folder(out, name=patient_lock_name("p1")),
            ):  # fmt: skip
                pass
            with writing_folder(out, name=patient_lock_name("p2")):
                pass
    with writing_folder(out):  # every lock released
        pass


@pytest.mark.usefixtures("prefect_harness")
def test_a_second_run_of_one_patient_into_one_folder_stops_before_any_work(tmp_path):
    from tumor3d.flows.patient import run_patient

    (row,) = small_phantom_rows(tmp_path / "in", [0], "lk")
    out = tmp_path / "out"
    with writing_folder(out, shared=True), writing_folder(out, name=patient_lock_name("lk0")):
        with pytest.raises(FolderBusyError, match="writing lk0 here"):
            run_patient(row.image, out, patient_id="lk0", modality="t2")
        named = tmp_path / "lk0.nii.gz"  # its id made from the file's name: the same
        named.write_bytes(row.image.read_bytes())
        with pytest.raises(FolderBusyError, match="writing lk0 here"):
            run_patient(named, out, modality="t2")
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME, patient_lock_name("lk0")]


def test_a_cohort_on_a_folder_another_command_writes_starts_nothing(tmp_path):
    rows = small_phantom_rows(tmp_path / "in", [0], "lk")
    out = tmp_path / "out"
    with writing_folder(out), pytest.raises(FolderBusyError, match="another tumor3d command"):
        run_cohort(rows, out, workers=1)
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # no patient, no store


def test_a_holder_killed_with_sigkill_leaves_the_folder_free(tmp_path):
    out = tmp_path / "out"
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys, time
            from tumor3d.storage.folder_lock import writing_folder
            with writing_folder({str(out)!r}):
                print("held", flush=True)
                time.sleep(120)
        """)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(FolderBusyError, match=f"pid {holder.pid} on "), writing_folder(out):
            pass
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
        with writing_folder(out):  # the operating system released it
            pass
    finally:
        if holder.poll() is None:
            holder.kill()
        holder.wait()


def test_a_symbolic_link_in_place_of_the_lock_is_refused_and_its_target_untouched(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    (out / LOCK_NAME).symlink_to(victim)
    with pytest.raises(OSError) as exc, writing_folder(out):
        pass
    assert exc.value.filename == str(out / LOCK_NAME)
    assert victim.read_text() == "keep me"


def test_another_users_lock_file_is_locked_read_only(tmp_path, monkeypatch):
    """A group-shared folder: the lock file of another user may not open read-write."""
    import tumor3d.storage.folder_lock as folder_lock

    out = tmp_path / "out"
    with writing_folder(out):  # the file exists, as another user left it
        pass
    real_open = os.open

    def no_write(path, flags, *args):
        if flags & os.O_RDWR:
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(folder_lock.os, "open", no_write)
    with writing_folder(out):
        with pytest.raises(FolderBusyError), writing_folder(out):
            pass


def test_a_file_system_that_cannot_lock_runs_unlocked(tmp_path, monkeypatch):
    import errno

    import tumor3d.storage.folder_lock as folder_lock

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(folder_lock.fcntl, "flock", no_locks)
    ran = []
    with writing_folder(tmp_path / "out"):
        ran.append(True)
    assert ran == [True]

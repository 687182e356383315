"""The cohort keeps one patient more in flight than it has workers (``EXTRA_LANES``).

A lane publishes its patient in the flow's own process after the last stage;
the next patient's stages must not wait for that. With one worker, a second
patient is under way before the first is published, and never more than
``workers + EXTRA_LANES`` patients are.
"""

from __future__ import annotations

import threading

import pytest

from tumor3d.flows import cohort
from tumor3d.flows.cohort import run_cohort
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.tasks.progress import ProgressEvent, use_reporter

SMALL = {"n_slices": 16, "matrix_size": (128, 128)}

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lanes-in")
    return [
        write_phantom_patient(
            make_phantom_patient(s, patient_id=f"lane{s}", **SMALL), folder / f"lane{s}"
        )
        for s in (0, 1, 2)
    ]


def _events(rows, out, monkeypatch, extra: int) -> list[ProgressEvent]:
    monkeypatch.setattr(cohort, "EXTRA_LANES", extra)
    events: list[ProgressEvent] = []
    lock = threading.Lock()

    def keep(event: ProgressEvent) -> None:
        with lock:
            events.append(event)

    with use_reporter(keep):
        result = run_cohort(rows, out, workers=1)
    assert result.exit_code in (0, 4) and all(p.output_dir for p in result.patients)
    return events


def _in_flight(events: list[ProgressEvent]) -> list[int]:
    """Patients started and not yet published, after each event."""
    live: set[str] = set()
    counts = []
    for e in events:
        if e.status == "published":
            live.discard(e.patient_id)
        else:
            live.add(e.patient_id)
        counts.append(len(live))
    return counts


def test_a_second_patient_is_under_way_while_the_first_publishes(rows, tmp_path, monkeypatch):
    events = _events(rows, tmp_path / "out", monkeypatch, extra=1)
    counts = _in_flight(events)
    assert max(counts) == 2  # workers (1) + EXTRA_LANES (1), never more
    first_published = next(i for i, e in enumerate(events) if e.status == "published")
    publisher = events[first_published].patient_id
    others = [i for i, e in enumerate(events) if e.patient_id != publisher]
    assert min(others) < first_published


def test_without_the_extra_lane_patients_run_one_after_another(rows, tmp_path, monkeypatch):
    events = _events(rows[:2], tmp_path / "out", monkeypatch, extra=0)
    assert max(_in_flight(events)) == 1

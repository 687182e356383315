"""Pieces shared by the cohort benchmarks (``bench_cohort.py``, ``bench_dask.py``)."""

from __future__ import annotations

import re
from pathlib import Path

from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.phantom_io import write_phantom_patient


def write_phantom_cohort(n: int, prefix: str, work: Path) -> list:
    """Phantom patients ``<prefix>000`` .. (seeds 0..n-1) written under ``work/inputs``.

    Returns their manifest rows, in seed order.
    """
    rows = []
    for seed in range(n):
        patient = make_phantom_patient(seed, patient_id=f"{prefix}{seed:03d}")
        rows.append(write_phantom_patient(patient, work / "inputs" / patient.scan.patient_id))
    print(f"{n} phantom patients written to {work / 'inputs'}")
    return rows


def replace_report_section(text: str, heading: str, section: str) -> str:
    """``text`` with its ``heading`` section (up to the next ``## ``) replaced by ``section``.

    Appended when the report has no such section.
    """
    pattern = re.compile(rf"^{re.escape(heading)}\n.*?(?=^## |\Z)", re.S | re.M)
    if pattern.search(text):
        return pattern.sub(lambda _: section, text)
    return text.rstrip("\n") + "\n\n" + section

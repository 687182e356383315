"""The same file under two patient ids: computed once, published under each id (issue 29).

Stage keys depend on content only (image, geometry, modality, reading
options, configuration, code), never on the patient id: the second id's run
is all cache hits from the ingest stage on. No cached record or artifact
holds an id, so the second patient's published metrics, provenance, report
and viewer name the second id only. Another file still computes.
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import pandas as pd
import pytest

from tumor3d.flows.patient import run_patient
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.tasks.stages import STAGES

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]

#: Distinctive ids: neither occurs by chance in a published or stored file.
FIRST, SECOND, OTHER = "idqalpha", "idqbravo", "idqcharlie"


def _texts(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (recursively), gzip members decompressed."""
    out = {}
    for f in sorted(p for p in folder.rglob("*") if p.is_file()):
        data = f.read_bytes()
        if data[:2] == b"\x1f\x8b":
            data = gzip.decompress(data)
        out[str(f.relative_to(folder))] = data
    return out


@pytest.fixture(scope="module")
def same_file_runs(tmp_path_factory):
    """One phantom file run as FIRST, then as SECOND, into one output folder and store."""
    patient = make_phantom_patient(6, patient_id="srcpat", n_slices=16)
    image = write_phantom_patient(patient, tmp_path_factory.mktemp("in")).image
    out = tmp_path_factory.mktemp("out")
    first = run_patient(image, out, patient_id=FIRST)
    second = run_patient(image, out, patient_id=SECOND)
    return out, first, second


def test_the_second_id_of_the_same_file_is_all_cache_hits(same_file_runs):
    _, first, second = same_file_runs
    assert not any(first.cache_hits)
    assert [s.stage for s in second.stages] == list(STAGES)
    assert all(second.cache_hits), [s.stage for s in second.stages if not s.cached]
    # the same stage outputs (artifact digests and values), served from the first run
    for a, b in zip(first.stages, second.stages, strict=True):
        assert a.artifacts == b.artifacts, a.stage
    assert second.metrics["volume_eq7_mm3"] == first.metrics["volume_eq7_mm3"]


def test_the_second_id_is_published_under_its_own_name_only(same_file_runs):
    out, _, second = same_file_runs
    folder = out / SECOND
    assert Path(second.output_dir) == folder
    metrics = pd.read_parquet(folder / "metrics.parquet")
    assert metrics["patient_id"].tolist() == [SECOND]
    provenance = json.loads((folder / "provenance.json").read_text())
    assert provenance["input"]["patient_id"] == SECOND
    report = (folder / "report.html").read_text(encoding="utf-8")
    assert SECOND in report
    assert second.report["patient_id"] == SECOND
    files = _texts(folder)
    leaked = [name for name, data in files.items() if FIRST.encode() in data]
    assert leaked == []  # not in metrics, provenance, report, viewer, meshes, masks
    # and the first id's folder still names the first id only
    first_files = _texts(out / FIRST)
    assert [n for n, d in first_files.items() if SECOND.encode() in d] == []
    assert pd.read_parquet(out / FIRST / "metrics.parquet")["patient_id"].tolist() == [FIRST]


def test_no_cached_record_or_artifact_holds_a_patient_id(same_file_runs):
    out, _, _ = same_file_runs
    store = out / ".tumor3d-store"
    stored = _texts(store)
    assert any(name.startswith("prefect-results") for name in stored)  # records are there
    for pid in (FIRST, SECOND):
        assert [n for n, d in stored.items() if pid.encode() in d] == [], pid


def test_another_file_still_computes(same_file_runs, tmp_path_factory):
    out, first, _ = same_file_runs
    other = make_phantom_patient(8, patient_id="srcother", n_slices=16)
    image = write_phantom_patient(other, tmp_path_factory.mktemp("in-other")).image
    result = run_patient(image, out, patient_id=OTHER)
    computed = {s.stage for s in result.stages if not s.cached}
    assert {"ingest-scan", "preprocess", "segment-tumor", "measure-volume"} <= computed
    assert result.metrics["volume_eq7_mm3"] != first.metrics["volume_eq7_mm3"]
    metrics = pd.read_parquet(out / OTHER / "metrics.parquet")
    assert metrics["patient_id"].tolist() == [OTHER]

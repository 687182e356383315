"""A re-run whose result is already published leaves the folder alone (issue 12).

Unchanged input, configuration and code: every stage is a cache hit and the
published folder is not rewritten (same inode, same mtimes). Any published
file edited, deleted or added, or a different configuration: published again,
and the folder then holds the result afresh.
"""

from __future__ import annotations

import json
import os

import pandas as pd
import pytest

from tumor3d.flows.patient import run_patient
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.storage.publish import PUBLISH_MANIFEST

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]


def _snapshot(folder):
    """File name -> (bytes, mtime_ns) of every file, and the folder's inode."""
    files = {f.name: (f.read_bytes(), f.stat().st_mtime_ns) for f in folder.iterdir()}
    return files, folder.stat().st_ino


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    # a small phantom (128 x 128 pixels of 1.875 mm): what is tested is the publishing
    patient = make_phantom_patient(3, patient_id="curpat", n_slices=16, matrix_size=(128, 128))
    image = write_phantom_patient(patient, tmp_path_factory.mktemp("in")).image
    out = tmp_path_factory.mktemp("out")
    first = run_patient(image, out, patient_id="curpat")
    assert not first.up_to_date
    return image, out


def test_unchanged_rerun_rewrites_nothing_and_says_up_to_date(published):
    image, out = published
    folder = out / "curpat"
    run_patient(image, out, patient_id="curpat")  # the folder holds this result
    before, inode = _snapshot(folder)
    again = run_patient(image, out, patient_id="curpat")
    assert all(again.cache_hits) and again.up_to_date
    after, inode_after = _snapshot(folder)
    assert inode_after == inode and after == before  # same folder, bytes and mtimes
    # the report handed to the Prefect artifacts still describes the folder
    assert again.report["provenance"] == json.loads((folder / "provenance.json").read_text())
    assert again.report.get("viewer") == "viewer.html"


@pytest.mark.parametrize("change", ["edit", "delete", "add", "manifest"])
def test_changed_published_folder_is_published_again(published, change):
    image, out = published
    folder = out / "curpat"
    run_patient(image, out, patient_id="curpat")
    good, _ = _snapshot(folder)
    target = folder / "metrics.parquet"
    if change == "edit":  # same size, one byte flipped
        data = bytearray(target.read_bytes())
        data[len(data) // 2] ^= 0xFF
        target.write_bytes(bytes(data))
    elif change == "delete":
        (folder / "render_anterior.png").unlink()
    elif change == "add":
        (folder / "stray.txt").write_text("not published by tumor3d")
    else:
        os.remove(folder / PUBLISH_MANIFEST)
    again = run_patient(image, out, patient_id="curpat")
    assert all(again.cache_hits) and not again.up_to_date
    fresh, _ = _snapshot(folder)
    assert set(fresh) == set(good)
    for name in ("render_anterior.png", "tumor.ply", "slices.parquet"):
        assert fresh[name][0] == good[name][0], name  # the same content, rewritten
    volumes = [pd.read_parquet(folder / "metrics.parquet")["volume_eq7_mm3"].iloc[0]]
    assert volumes == [again.metrics["volume_eq7_mm3"]]
    assert run_patient(image, out, patient_id="curpat").up_to_date


def test_other_configuration_is_published(published):
    image, out = published
    run_patient(image, out, patient_id="curpat")
    other = run_patient(
        image, out, patient_id="curpat", config={"simplify": {"reduction_percent": 40}}
    )
    assert not other.up_to_date
    assert json.loads((out / "curpat" / "provenance.json").read_text())["config"]["simplify"][
        "reduction_percent"
    ] == pytest.approx(40)
    back = run_patient(image, out, patient_id="curpat")  # default again: cached, republished
    assert all(back.cache_hits) and not back.up_to_date

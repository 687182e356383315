"""``tumor3d train``: models learned from a manifest's labelled patients (issue 28 item 2).

Two FLAIR phantoms with their truth as the reference and one tumour-free
phantom train a small model; the model, read back without pickle, segments
an unseen phantom close to its truth (the independent expectation); a
re-run with the same store takes every patient's stages from the cache and
writes the same model; a row without a reference is refused in one line.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from tumor3d import reconstruct as tumor3d_reconstruct
from tumor3d.errors import InputError
from tumor3d.evaluation.metrics import dice
from tumor3d.flows.cli import app
from tumor3d.flows.train import run_training
from tumor3d.learned.forest import ForestModel
from tumor3d.learned.rows import rows_from_bytes
from tumor3d.phantom import make_phantom_patient
from tumor3d.segmentation.segment import segment_tumor
from tumor3d.storage.manifest import write_manifest
from tumor3d.storage.phantom_io import write_phantom_patient

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]

ROUNDS = 30
#: tr12's field of view: 256 pixels of 1.1 mm (282 mm), wider than the U-Net's 240 mm window,
#: so its frame is not the whole slice (the other phantoms' 256 x 0.9375 mm is exactly 240 mm)
WIDE_FOV = {"matrix_size": (256, 256), "pixel_spacing_mm": 1.1}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    folder = tmp_path_factory.mktemp("train-in")
    rows = [
        write_phantom_patient(
            make_phantom_patient(s, modality="flair", patient_id=f"tr{s}", n_slices=14, **fov),
            folder / f"tr{s}",
        )
        for s, fov in ((11, {}), (12, WIDE_FOV))
    ]
    free = make_phantom_patient(13, modality="flair", patient_id="tr13n", n_slices=14,
                                tumor=False)  # fmt: skip
    rows.append(write_phantom_patient(free, folder / "tr13n"))
    manifest = write_manifest(rows, folder / "manifest.csv")
    out = tmp_path_factory.mktemp("train-out")
    result = run_training(manifest, out / "model", num_rounds=ROUNDS, command="test")
    return manifest, out, result


def test_the_model_is_written_with_its_card(trained):
    _, out, result = trained
    assert set(result.models) == {"hyper"}  # FLAIR only: the FLAIR/T2 family
    data = (out / "model" / "hyper.npz").read_bytes()
    model = ForestModel.from_bytes(data)
    assert model.meta["training_cases"] == ["tr11", "tr12", "tr13n"]
    assert model.meta["threshold"] == 0.5 and model.meta["prior"] == "robust"
    card = json.loads((out / "model" / "training.json").read_text())
    import hashlib

    assert card["models"]["hyper"]["sha256"] == hashlib.sha256(data).hexdigest()
    by_id = {c["patient_id"]: c for c in card["cases"]}
    assert by_id["tr13n"]["lesion_rows"] == 0 < by_id["tr11"]["lesion_rows"]
    assert by_id["tr11"]["reference_kind"] == "truth"


def test_the_trained_model_segments_an_unseen_phantom(trained):
    _, out, _ = trained
    model = ForestModel.from_bytes((out / "model" / "hyper.npz").read_bytes())
    patient = make_phantom_patient(5, modality="flair", n_slices=14)
    from tumor3d.imaging.preprocess import preprocess_volume
    from tumor3d.segmentation.detect import detect_abnormal_slices
    from tumor3d.segmentation.lesion import left_right_axis

    scan = patient.scan
    spacing = (scan.slice_step_mm, *scan.pixel_spacing_mm)
    pre = preprocess_volume(scan.image, spacing_mm=spacing)
    lr = left_right_axis(scan.affine)
    det = detect_abnormal_slices(
        pre.enhanced, pre.brain_mask, modality="flair", spacing_mm=spacing, lr_axis=lr
    )
    seg = segment_tumor(
        pre.enhanced, pre.brain_mask, det, modality="flair", method="learned",
        spacing_mm=spacing, lr_axis=lr, image=scan.image, model=model,
    )  # fmt: skip
    truth = np.asarray(patient.slice_masks) > 0.5
    assert dice(seg.tumor_mask, truth) > 0.8


def test_a_rerun_takes_every_patient_from_the_cache(trained):
    manifest, out, first = trained
    again = run_training(
        manifest, out / "model2", store_dir=str(out / "model" / ".tumor3d-store"),
        num_rounds=ROUNDS, command="test",
    )  # fmt: skip
    assert again.cached_patients == 3
    assert [c["rows_digest"] for c in again.cases] == [c["rows_digest"] for c in first.cases]
    a = ForestModel.from_bytes((out / "model" / "hyper.npz").read_bytes())
    b = ForestModel.from_bytes((out / "model2" / "hyper.npz").read_bytes())
    assert a.digest() == b.digest()  # deterministic training on the same rows


def test_stored_rows_are_never_unpickled(trained):
    _, out, _ = trained
    buf = io.BytesIO()
    np.savez(buf, x=np.array([object()], dtype=object), y=np.zeros(1, np.uint8),
             w=np.zeros(1, np.float32))  # fmt: skip
    with pytest.raises(InputError, match="not training rows"):
        rows_from_bytes(buf.getvalue(), source="planted")


def test_rows_of_one_class_name_each_patients_lesion_rows(trained, tmp_path):
    """Training on tumour-free patients alone (or on references that miss their images):
    one line naming each patient's lesion rows, before LightGBM (whose refusal named no
    patient; a user audit). Its rows come from the fixture's store (cached)."""
    import pandas as pd

    manifest, out, _ = trained
    free = pd.read_csv(manifest)
    free = free[free["patient_id"] == "tr13n"]
    free["image"] = [str((manifest.parent / p).resolve()) for p in free["image"]]
    free.to_csv(tmp_path / "free.csv", index=False)
    with pytest.raises(InputError) as exc:
        run_training(tmp_path / "free.csv", tmp_path / "model", num_rounds=ROUNDS,
                     store_dir=str(out / "model" / ".tumor3d-store"))  # fmt: skip
    text = str(exc.value)
    assert text.startswith("the hyper model's training rows hold one class only (lesion rows ")
    assert "patient: tr13n 0 of " in text and "\n" not in text
    assert not (tmp_path / "model").exists()


def test_a_row_without_reference_is_refused_in_one_line(tmp_path):
    patient = make_phantom_patient(3, modality="flair", patient_id="noref", n_slices=10)
    row = write_phantom_patient(patient, tmp_path / "noref")
    import dataclasses

    manifest = write_manifest(
        [dataclasses.replace(row, reference=None, reference_labels=None, reference_kind=None)],
        tmp_path / "m.csv",
    )
    res = CliRunner().invoke(app, ["train", str(manifest), "--out", str(tmp_path / "model")])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "noref" in lines[0] and "reference" in lines[0], res.output
    assert not (tmp_path / "model").exists()


def test_provenance_names_the_model_a_learned_run_used(tmp_path):
    """The learned method's model digest reaches provenance.json (issue 28 item 2)."""
    import hashlib
    from importlib import resources

    from tumor3d.flows.patient import run_patient
    from tumor3d.learned.shipped import shipped_model

    patient = make_phantom_patient(4, modality="flair", patient_id="prov", n_slices=12)
    row = write_phantom_patient(patient, tmp_path / "in")
    result = run_patient(row.image, tmp_path / "out", patient_id="prov", modality="flair")
    prov = json.loads((tmp_path / "out" / "prov" / "provenance.json").read_text())
    assert prov["segmentation"]["method"] == "learned"
    # the file's SHA-256, as training.json and sha256sum give it (it was the arrays' digest)
    shipped = resources.files("tumor3d.learned").joinpath("models", "hyper.npz").read_bytes()
    assert prov["segmentation"]["model_sha256"] == hashlib.sha256(shipped).hexdigest()
    assert prov["segmentation"]["model_sha256"] == shipped_model("flair").file_sha256
    assert prov["segmentation"]["model_file"] == "tumor3d/learned/models/hyper.npz"
    assert result.metrics["segment_method"] == "learned"


def test_a_trained_folder_replaces_the_shipped_models_and_its_bytes_key_the_segment_stage(
    trained, tmp_path
):
    """``segment.learned_models: DIR`` (audit 4 F7): the run uses the folder's forest (the
    API's volume to the mm3, the file named with its SHA-256 in provenance.json), a re-run
    takes every stage from the cache, and other bytes in the same file recompute the
    segment stage (and only the stages after it), the new digest recorded."""
    import hashlib
    import shutil

    from tumor3d.flows.patient import run_patient

    _, out, _ = trained
    folder = tmp_path / "mine"
    shutil.copytree(out / "model", folder, ignore=shutil.ignore_patterns(".tumor3d-store"))
    patient = make_phantom_patient(
        5, modality="flair", patient_id="own", n_slices=10, matrix_size=(128, 128)
    )
    row = write_phantom_patient(patient, tmp_path / "in")
    cfg = {"segment": {"learned_models": str(folder)}}
    kw = dict(patient_id="own", modality="flair", config=cfg)
    first = run_patient(row.image, tmp_path / "out", **kw)
    prov = json.loads((tmp_path / "out" / "own" / "provenance.json").read_text())["segmentation"]
    mine = (folder / "hyper.npz").read_bytes()
    assert prov["model_file"] == f"{folder}/hyper.npz"
    assert prov["model_sha256"] == hashlib.sha256(mine).hexdigest()
    assert "cnn_model" not in prov
    assert first.metrics["segment_model"] == f"forest, models of {folder}"
    api = tumor3d_reconstruct(row.image, modality="flair", config=cfg)
    assert first.metrics["volume_eq7_mm3"] == pytest.approx(api.volumes_mm3["eq7"], abs=1e-6)
    again = run_patient(row.image, tmp_path / "out", **kw)
    assert all(again.cache_hits)
    # other bytes, the same file name: the shipped forest copied over the user's
    from importlib import resources

    shipped = resources.files("tumor3d.learned").joinpath("models", "hyper.npz").read_bytes()
    (folder / "hyper.npz").write_bytes(shipped)
    changed = run_patient(row.image, tmp_path / "out", **kw)
    cached = {s.stage: s.cached for s in changed.stages}
    assert not cached["segment-tumor"] and cached["detect-abnormal"], cached
    prov = json.loads((tmp_path / "out" / "own" / "provenance.json").read_text())["segmentation"]
    assert prov["model_sha256"] == hashlib.sha256(shipped).hexdigest()
    assert changed.recomputed == "given models changed"
    # a file this FLAIR run does not use (the T1c forest) keys nothing (audit 5)
    (folder / "t1c.npz").write_bytes(resources.files("tumor3d.learned").joinpath(
        "models", "t1c.npz").read_bytes())  # fmt: skip
    unused = run_patient(row.image, tmp_path / "out", **kw)
    assert all(unused.cache_hits) and unused.recomputed is None
    # a given segmentation replaces the method: the folder is neither read nor keyed
    (folder / "hyper.npz").write_bytes(b"PK not a model any more")
    truth = row.image.parent / "own_truth_slices.nii.gz"  # on the scan's grid
    given = run_patient(row.image, tmp_path / "out", segmentation=str(truth), **kw)
    assert given.metrics["segment_method"] == "given"


@pytest.mark.parametrize(
    ("name", "command", "message"),
    [
        ("hyper.npz", "run", "m/hyper.npz: not a readable tumor3d forest model"),
        ("t1c.npz", "run", r"no hyper.npz (FLAIR and T2 model) for this FLAIR scan"),
        ("t1c.npz", "cohort", r"no hyper.npz (FLAIR and T2 model) for this FLAIR scan"),
        ("t1c.npz", "evaluate", r"no hyper.npz (FLAIR and T2 model) for this FLAIR scan"),
    ],
)
def test_a_models_folder_that_is_not_one_is_refused_before_any_flow(
    tmp_path, name, command, message
):
    """A damaged model, or no model for the scan's sequence (audit 5: that one was found
    after three stages, and a cohort exited 1 with its tables written)."""
    patient = make_phantom_patient(5, modality="flair", patient_id="own", n_slices=8)
    row = write_phantom_patient(patient, tmp_path / "in")
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / name).write_bytes(b"PK not a model")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"segment:\n  learned_models: {tmp_path / 'm'}\n")
    if name == "t1c.npz":
        from importlib import resources

        t1c = resources.files("tumor3d.learned").joinpath("models", "t1c.npz").read_bytes()
        (tmp_path / "m" / name).write_bytes(t1c)
    target = str(row.image)
    if command != "run":
        target = str(write_manifest([row], tmp_path / "manifest.csv"))
    named = f"mine={cfg}" if command == "evaluate" else str(cfg)
    args = [command, target, "--out", str(tmp_path / "out"), "--config", named]
    res = CliRunner().invoke(app, args + (["--modality", "flair"] if command == "run" else []))
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert message in lines[0]
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- --cnn: the U-Net (issue 28)

UNET_TINY = {"base": 2, "levels": 2, "epochs": 2}


def test_cnn_slices_are_the_inference_grid_of_each_flair_patient(trained, monkeypatch):
    """The unet-slices stage's slices, as the U-Net's training receives them, equal
    ``unet_slices`` of the phantom's own image and truth (no torch needed: the
    training itself is replaced by a recorder)."""
    import tumor3d.flows.train as train_mod
    from tumor3d.learned.cnn_data import frame_of
    from tumor3d.learned.cnn_train import UNetSettings, unet_slices

    manifest, out, _ = trained
    seen = {"seeds": []}

    def recorder(x, y, settings, **kw):
        seen.update(x=x, y=y, settings=settings, meta=kw["meta"])
        seen["seeds"].append(kw["seed"])
        return f"not a network {kw['seed']}".encode(), type("Fit", (), {"seconds": 0.0})()

    monkeypatch.setattr(train_mod, "require_torch", lambda: None)
    monkeypatch.setattr(train_mod, "train_unet", recorder)
    result = run_training(
        manifest, out / "cnn-rec", store_dir=str(out / "model" / ".tumor3d-store"),
        num_rounds=ROUNDS, command="test", cnn=True, cnn_settings=UNET_TINY,
    )  # fmt: skip
    assert seen["settings"] == UNetSettings(**UNET_TINY)
    assert seen["settings"].framing == "mm"  # the shipped nets' framing
    assert seen["seeds"] == [0, 1]  # the shipped ensemble: one net per seed
    assert seen["meta"]["training_cases"] == ["tr11", "tr12", "tr13n"]
    xs, ys = [], []
    for seed, tumour, fov in ((11, True, {}), (12, True, WIDE_FOV), (13, False, {})):
        p = make_phantom_patient(seed, modality="flair", n_slices=14, tumor=tumour, **fov)
        x, y = unet_slices(  # the shipped framing: 240 mm centred on the head
            p.scan.image, np.asarray(p.slice_masks) > 0.5, pixel_mm=p.scan.pixel_spacing_mm
        )
        if fov:  # a window of 240 / 1.1 = 218 pixels: not the whole slice
            assert frame_of(p.scan.image, "mm", p.scan.pixel_spacing_mm)[2:] == (218, 218)
        xs.append(x)
        ys.append(y)
    x, y = np.concatenate(xs), np.concatenate(ys)
    assert seen["x"].shape == x.shape == (42, 3, 128, 128)
    assert float(np.abs(seen["x"].astype(np.float32) - x.astype(np.float32)).max()) < 1e-2
    assert np.array_equal(seen["y"], y) and not seen["y"][28:].any()  # tr13n: tumour-free
    card = json.loads((out / "cnn-rec" / "training.json").read_text())
    for seed in (0, 1):
        name = f"unet_flair_seed{seed}"
        assert (out / "cnn-rec" / f"{name}.npz").read_bytes() == f"not a network {seed}".encode()
        assert card["models"][name]["file"] == f"{name}.npz"
    assert card["cnn_settings"]["epochs"] == 2
    assert [c["unet_slices"] for c in result.cases] == [14, 14, 14]
    assert result.cases[2]["unet_tumour_slices"] == 0 < result.cases[0]["unet_tumour_slices"]
    again = run_training(
        manifest, out / "cnn-rec2", store_dir=str(out / "model" / ".tumor3d-store"),
        num_rounds=ROUNDS, command="test", cnn=True, cnn_settings=UNET_TINY,
    )  # fmt: skip
    assert again.cached_patients == 3
    assert [c["unet_slices_digest"] for c in again.cases] == [
        c["unet_slices_digest"] for c in result.cases
    ]


@pytest.mark.parametrize("seeds", [(), (0, 0)])
def test_cnn_seeds_must_be_distinct_and_are_checked_before_any_patient(
    trained, monkeypatch, tmp_path, seeds
):
    import tumor3d.flows.train as train_mod

    manifest, _, _ = trained
    monkeypatch.setattr(train_mod, "require_torch", lambda: None)
    monkeypatch.setattr(train_mod, "_patient_rows", lambda *a, **k: pytest.fail("a patient ran"))
    with pytest.raises(InputError, match="distinct seeds"):
        run_training(manifest, tmp_path / "m", cnn=True, cnn_seeds=seeds, cnn_settings=UNET_TINY)


@pytest.mark.parametrize("key, value", [("framing", "slice"), ("size", 64), ("context", 2)])
def test_cnn_settings_of_the_slice_grid_are_refused_before_any_patient(
    trained, monkeypatch, tmp_path, key, value
):
    """The unet-slices stage cuts every patient's slices on the shipped grid (size,
    context and framing), so a net trained on other settings would not match them."""
    import tumor3d.flows.train as train_mod

    manifest, _, _ = trained
    monkeypatch.setattr(train_mod, "require_torch", lambda: None)
    monkeypatch.setattr(train_mod, "_patient_rows", lambda *a, **k: pytest.fail("a patient ran"))
    with pytest.raises(InputError, match=f"{key} is fixed by the unet-slices stage"):
        run_training(manifest, tmp_path / "m", cnn=True, cnn_settings={key: value})


def test_cnn_trains_a_unet_the_numpy_forward_pass_reads(trained):
    pytest.importorskip("torch")  # CI has no torch: run with the train extra
    from tumor3d.learned.cnn import unet_from_bytes, unet_probability
    from tumor3d.learned.cnn_train import unet_meta, unet_slices

    manifest, out, _ = trained
    result = run_training(
        manifest, out / "cnn", store_dir=str(out / "model" / ".tumor3d-store"),
        num_rounds=ROUNDS, command="test", cnn=True, cnn_settings=UNET_TINY, cnn_threads=1,
        cnn_seeds=(3,),
    )  # fmt: skip
    assert set(result.models) == {"hyper", "unet_flair_seed3"}
    data = (out / "cnn" / "unet_flair_seed3.npz").read_bytes()
    net = unet_from_bytes(data, source="trained")
    assert net.levels == 2 and net.in_channels == 3
    meta = unet_meta(data)
    assert meta["training_cases"] == ["tr11", "tr12", "tr13n"]
    assert meta["settings"]["epochs"] == 2 and meta["trainer"].startswith("torch ")
    assert meta["seed"] == 3
    p = make_phantom_patient(5, modality="flair", n_slices=14)
    label = np.asarray(p.slice_masks) > 0.5
    prob = unet_probability(
        net, unet_slices(p.scan.image, label, pixel_mm=p.scan.pixel_spacing_mm)[0]
    )
    assert prob.shape == (14, 128, 128) and np.all((prob >= 0) & (prob <= 1))


def test_cnn_without_torch_is_refused_in_one_line(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "torch", None)  # "import torch" raises ImportError
    patient = make_phantom_patient(3, modality="flair", patient_id="nt", n_slices=10)
    manifest = write_manifest([write_phantom_patient(patient, tmp_path / "nt")], tmp_path / "m.csv")
    res = CliRunner().invoke(
        app, ["train", str(manifest), "--out", str(tmp_path / "model"), "--cnn"]
    )
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "tumor3d[train]" in lines[0], res.output
    assert not (tmp_path / "model").exists()

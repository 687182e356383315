"""Stage adapters called directly (``task.fn``, no Prefect): declarations and edge cases."""

from __future__ import annotations

import inspect
from fnmatch import fnmatch

import nibabel as nib
import numpy as np
import pandas as pd
import pytest

from tumor3d.config import PipelineConfig, SimplifyConfig
from tumor3d.flows.patient import run_stages_direct
from tumor3d.geometry.mesh import Mesh
from tumor3d.imaging.preprocess import brain_mask_notes
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.patient_outputs import join_notes, split_notes
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.storage.store import ArtifactStore
from tumor3d.tasks import stages
from tumor3d.tasks.spec import StageOutput


def preprocess_notes(values):
    """The run's notes on the brain mask from the preprocess stage's values, in a run's
    order (tumor3d.imaging.preprocess.brain_mask_notes: skull removal, then voxel size)."""
    skull, size = brain_mask_notes(values)
    return skull + size


# Small phantoms (128 x 128 pixels of 1.875 mm, the default field of view, 16 slices) where
# the image size is not the question: a run costs a third.
SMALL = {"n_slices": 16, "matrix_size": (128, 128)}


@pytest.fixture(scope="module")
def tumour_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("direct")
    patient = make_phantom_patient(2, patient_id="direct2", **SMALL)
    image = write_phantom_patient(patient, tmp / "in").image
    run = run_stages_direct(image, tmp / "store", patient_id="direct2")
    return run, ArtifactStore(tmp / "store")


def test_specs_match_the_adapters_signatures_and_products(tumour_run):
    run, _ = tumour_run
    config_fields = {type(getattr(PipelineConfig(), f)): f for f in PipelineConfig.model_fields}
    for name, spec in stages.STAGES.items():
        params = set(inspect.signature(spec.task.fn.__wrapped__).parameters) - {"store_root"}
        declared = set(spec.inputs) | ({"config"} if spec.config_model else set())
        assert params == declared, name
        if spec.config_model is not None:
            assert spec.config_model in config_fields, name
        out = run.outputs[name]
        assert isinstance(out, StageOutput) and out.verify(), name
        for artifact, ref in out.artifacts.items():
            kind = spec.outputs.get(artifact) or next(
                (k for pattern, k in spec.outputs.items() if fnmatch(artifact, pattern)), None
            )
            assert kind == ref.kind, (name, artifact)
    assert list(run.outputs) == list(stages.STAGES)


def test_tumour_free_patient_completes_with_zero_volume_and_no_render(tmp_path):
    patient = make_phantom_patient(1, tumor=False, patient_id="normal1", **SMALL)
    image = write_phantom_patient(patient, tmp_path / "in").image
    run = run_stages_direct(image, tmp_path / "store", patient_id="normal1")
    volumes = run.outputs["measure-volume"].values
    for key in ("volume_eq7_mm3", "volume_voxel_mm3", "volume_mesh_mm3"):
        assert volumes[key] == 0.0
    assert volumes["n_tumor_slices"] == 0
    assert run.outputs["extract-surface"].values["faces"] == 0
    assert run.outputs["render-views"].artifacts == {}


def _tetrahedron() -> Mesh:
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=float)
    return Mesh(v, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))


@pytest.mark.parametrize("percent", [60.0, 99.0])
def test_mesh_too_small_to_simplify_passes_through(tmp_path, percent):
    store = ArtifactStore(tmp_path)
    ref = store.put_mesh(_tetrahedron())
    out = stages.STAGES["simplify-mesh"].task.fn(
        mesh=ref, config=SimplifyConfig(reduction_percent=percent), store_root=str(store.root)
    )
    assert out.values["simplified"] is False
    assert out.values["faces"] == 4 and out.values["watertight"] is True
    assert out.artifacts["mesh"].digest == ref.digest  # unchanged, same artifact


def test_measure_stage_counts_the_tumour_tip_beyond_the_abnormal_slices(tumour_run):
    """Eq. 7 sums a slice where segmentation found tumour that was not flagged abnormal."""
    run, store = tumour_run
    outs = run.outputs
    seg = store.get_table(outs["segment-tumor"].artifacts["segmentation"])
    tumour = seg["tumor_pixels"].to_numpy() > 0
    assert tumour.any()
    # Un-flag the first tumour slice: it becomes a tip that only segmentation saw.
    tip = int(np.flatnonzero(tumour)[0])
    seg = seg.copy()
    seg.loc[seg["slice_index"] == tip, "flagged"] = False
    flagged = seg["flagged"].to_numpy(bool)
    scan = outs["ingest-scan"].artifacts["scan"]
    kwargs = dict(
        scan=scan, segmentation=store.put_table(seg),
        tumor_mask_slices=outs["segment-tumor"].artifacts["tumor_mask_slices"],
        tumor_mask=outs["interpolate-slices"].artifacts["tumor_mask"],
        mesh=outs["extract-surface"].artifacts["mesh"],
        mesh_simplified=outs["simplify-mesh"].artifacts["mesh"], store_root=str(store.root),
    )  # fmt: skip
    got = stages.STAGES["measure-volume"].task.fn(**kwargs).values
    dy, dx = scan.metadata["pixel_spacing_mm"]
    slab = got["slab_height_mm"]
    # independent expectation: every segmented tumour pixel counts once
    expected = slab * dy * dx * int(seg["tumor_pixels"].sum())
    assert got["volume_eq7_mm3"] == pytest.approx(expected, rel=1e-12)
    assert got["eq7_slice_rule"] == "segmented"
    assert got["n_eq7_slices"] == int((flagged | tumour).sum())
    assert got["n_abnormal_slices"] == int(flagged.sum())
    assert got["volume_eq7_ml"] == pytest.approx(got["volume_eq7_mm3"] / 1000.0)
    tip_mm3 = slab * dy * dx * int(seg.loc[seg["slice_index"] == tip, "tumor_pixels"].iloc[0])
    assert tip_mm3 > 0  # so the tip really matters to the assertion above


def test_a_robust_run_flags_the_slices_its_detection_flagged(tumour_run):
    run, store = tumour_run
    outs = run.outputs
    det = store.get_table(outs["detect-abnormal"].artifacts["detection"])
    seg = store.get_table(outs["segment-tumor"].artifacts["segmentation"])
    assert outs["segment-tumor"].values["segment_method"] in ("robust", "paper")
    np.testing.assert_array_equal(seg["flagged"].to_numpy(bool), det["abnormal"].to_numpy(bool))
    assert outs["measure-volume"].values["n_abnormal_slices"] == int(det["abnormal"].sum())


def test_a_method_reading_every_slice_flags_its_tumour_slices_not_the_detections(tmp_path):
    """The histogram detection made to flag nothing; the multi-Otsu peer, which reads every
    slice, still finds the phantom's tumour: its slices are the ones flagged abnormal (the
    console's "N flagged abnormal", the overlay's frames), not the detection's none."""
    import tumor3d

    patient = make_phantom_patient(3, patient_id="every3", **SMALL)
    image = write_phantom_patient(patient, tmp_path / "in").image
    cfg = {
        "detect": {"method": "histogram", "abnormal_min_modes": 10},
        "segment": {"method": "multiotsu"},
    }
    run = run_stages_direct(image, tmp_path / "store", config=cfg, patient_id="every3")
    store = ArtifactStore(tmp_path / "store")
    det = store.get_table(run.outputs["detect-abnormal"].artifacts["detection"])
    seg = store.get_table(run.outputs["segment-tumor"].artifacts["segmentation"])
    assert not det["abnormal"].any()
    tumour = seg["tumor_pixels"].to_numpy() > 0
    assert tumour.any()
    np.testing.assert_array_equal(seg["flagged"].to_numpy(bool), tumour)
    measured = run.outputs["measure-volume"].values
    assert measured["n_abnormal_slices"] == measured["n_tumor_slices"] == int(tumour.sum())
    # the API says the same
    api = tumor3d.reconstruct(str(image), modality="t2", config=cfg)
    assert api.metrics["n_abnormal_slices"] == int(tumour.sum())


def test_preprocess_counts_the_slices_with_brain_and_with_tissue(tumour_run):
    run, store = tumour_run
    outs = run.outputs
    values = outs["preprocess"].values
    brain, _ = store.get_volume(outs["preprocess"].artifacts["brain_mask"])
    image, _ = store.get_volume(outs["ingest-scan"].artifacts["scan"])
    flat = image.reshape(len(image), -1)
    # independent expectations: the stored mask's slices, the scan's non-constant slices
    assert values["brain_slices"] == int(brain.any(axis=(1, 2)).sum())
    assert values["tissue_slices"] == int((flat.max(axis=1) > flat.min(axis=1)).sum())
    assert 0 < values["brain_slices"] <= values["tissue_slices"] <= len(image)
    assert preprocess_notes(values) == []  # the phantom's whole head: no note


@pytest.mark.parametrize("below_min", [0.0, 250.0])
def test_preprocess_tissue_slices_leave_out_constant_background_slices(tmp_path, below_min):
    import nibabel as nib

    from tumor3d.config import PreprocessConfig
    from tumor3d.storage.readers import read_scan

    # slices beyond the head of one constant gray, as a skull-stripped volume's background:
    # the image's minimum, or below it (a z-scored volume's negative background)
    patient = make_phantom_patient(3, patient_id="padded3", **SMALL)
    data = patient.scan.image.transpose(2, 1, 0)
    pad = np.full(data.shape[:2] + (3,), float(data.min()) - below_min, dtype=data.dtype)
    padded = np.concatenate([pad, data, pad], axis=2)
    nib.save(nib.Nifti1Image(padded, patient.scan.affine), str(tmp_path / "padded.nii.gz"))
    store = ArtifactStore(tmp_path / "store")
    ref = store.put_scan(read_scan(tmp_path / "padded.nii.gz", modality="t2"))
    values = (
        stages.STAGES["preprocess"]
        .task.fn(scan=ref, config=PreprocessConfig(), store_root=str(store.root))
        .values
    )
    assert values["tissue_slices"] == data.shape[2]  # the six padded slices left out
    assert values["tissue_slices"] < padded.shape[2]


def test_preprocess_notes_say_when_the_brain_mask_lost_most_slices():
    lost = {"brain_volume_ml": 480.0, "brain_slices": 3, "tissue_slices": 26,
            "brain_extraction": "skull_strip"}  # fmt: skip
    (note,) = preprocess_notes(lost)
    assert note.startswith("brain mask on 3 of the 26 slices that hold tissue")
    assert "overlay_brain.png" in note
    assert split_notes(join_notes([note])) == [note]
    # half the slices or more: no note; a mask the user gave: theirs, no note
    assert preprocess_notes({**lost, "brain_slices": 13}) == []
    assert preprocess_notes({**lost, "brain_slices": 12}) != []
    assert preprocess_notes({**lost, "brain_extraction": "given"}) == []
    # the advice does not name the extraction that failed
    assert "brain_extraction: head" in note
    (head,) = preprocess_notes({**lost, "brain_extraction": "head"})
    assert "brain_extraction: head" not in head and "--brain-mask" in head
    # values cached before the counts were stored: no note; the volume note stays
    assert preprocess_notes({"brain_volume_ml": 480.0}) == []
    (big,) = preprocess_notes({"brain_volume_ml": 3257.0, "brain_extraction": "given"})
    assert big.startswith("brain mask of 3257 mL")


def test_stage_outputs_are_sealed_and_detect_edits(tumour_run):
    run, _ = tumour_run
    out = run.outputs["measure-volume"]
    assert out.verify()
    edited = out.model_copy(
        update={"values": {**out.values, "volume_eq7_mm3": out.values["volume_eq7_mm3"] / 10}}
    )
    assert not edited.verify()
    assert not out.model_copy(update={"digest": ""}).verify()
    assert edited.sealed().verify()


def test_interpolate_stage_resolves_the_automatic_slice_count_in_the_core(tumour_run):
    from tumor3d.geometry.interpolate import slices_between_auto

    run, _ = tumour_run
    scan = run.outputs["ingest-scan"].values
    expected = slices_between_auto(scan["slice_step_mm"], tuple(scan["pixel_spacing_mm"]))
    assert run.outputs["interpolate-slices"].values["slices_between"] == expected


def test_slice_table_rows_match_detection(tumour_run):
    from tumor3d.storage.slice_table import slice_table

    run, store = tumour_run
    det = store.get_table(run.outputs["detect-abnormal"].artifacts["detection"])
    seg = store.get_table(run.outputs["segment-tumor"].artifacts["segmentation"])
    table = slice_table(det, seg, pixel_area_mm2=0.5)
    assert len(table) == len(det)
    pd.testing.assert_series_equal(
        table["tumor_area_mm2"], table["tumor_pixels"].fillna(0).astype(float) * 0.5,
        check_names=False,
    )  # fmt: skip


def _count_lesion_runs(monkeypatch):
    import tumor3d.segmentation.detect as detect_mod
    import tumor3d.segmentation.lesion.model as lesion_mod
    import tumor3d.segmentation.segment as segment_mod
    from tumor3d.segmentation.lesion import patient_lesion, segment_hyperintense_lesion

    calls: list[str] = []
    for mod in (detect_mod, segment_mod):

        def counted(*args, _name=mod.__name__, **kwargs):
            # what the lesion model itself receives, not this test's reading of it: the
            # parameters and whether the scan's geometry reached it (the phantom's slices
            # are anisotropic and its affine has a left-right axis)
            def seen(*a, **k):
                geometry = k["lr_axis"] is not None and len(set(k["spacing_mm"])) > 1
                calls.append((_name, k["seed_sigmas"], geometry))
                return segment_hyperintense_lesion(*a, **k)

            with monkeypatch.context() as m:
                m.setattr(lesion_mod, "segment_hyperintense_lesion", seen)
                return patient_lesion(*args, **kwargs)

        monkeypatch.setattr(mod, "patient_lesion", counted)
    return calls


def test_the_lesion_model_runs_once_in_detect_and_segment_keeps_its_mask(tmp_path, monkeypatch):
    calls = _count_lesion_runs(monkeypatch)
    patient = make_phantom_patient(2, patient_id="once2", **SMALL)
    image = write_phantom_patient(patient, tmp_path / "in").image
    cfg = {"detect": {"method": "robust"}, "segment": {"method": "robust"}}
    run = run_stages_direct(image, tmp_path / "store", config=cfg, patient_id="once2")
    assert calls == [("tumor3d.segmentation.detect", 2.0, True)]
    store = ArtifactStore(tmp_path / "store")
    det_out = run.outputs["detect-abnormal"]
    assert det_out.values["lesion_computed"] is True
    lesion, _ = store.get_volume(det_out.artifacts["lesion"])
    tumour, _ = store.get_volume(run.outputs["segment-tumor"].artifacts["tumor_mask_slices"])
    abnormal = np.zeros(lesion.shape[0], bool)
    abnormal[det_out.values["abnormal_slices"]] = True
    assert tumour.any()
    # independent expectation: the detect stage's lesion on the flagged slices
    assert np.array_equal(tumour, lesion & abnormal[:, None, None])
    # the artifact records the mid-sagittal plane the symmetry rule used: the phantom's
    # head is straight (columns run left-right) and centred on the grid's middle
    plane = det_out.artifacts["lesion"].metadata["lesion"]["mirror_plane"]
    assert plane["lr_axis"] == 2 and abs(plane["yaw_deg"]) <= 1.0
    scan = patient.scan
    middle_mm = (scan.image.shape[2] - 1) / 2 * scan.pixel_spacing_mm[1]
    assert abs(plane["offset_mm"] - middle_mm) <= 2.0


def test_histogram_detection_then_robust_segment_uses_the_detect_lesion_params(
    tmp_path, monkeypatch
):
    calls = _count_lesion_runs(monkeypatch)
    patient = make_phantom_patient(2, patient_id="hist2", **SMALL)
    image = write_phantom_patient(patient, tmp_path / "in").image
    cfg = {
        "detect": {"method": "histogram", "lesion": {"seed_sigmas": 2.5}},
        "segment": {"method": "robust"},
    }
    run = run_stages_direct(image, tmp_path / "store", config=cfg, patient_id="hist2")
    assert calls == [("tumor3d.segmentation.segment", 2.5, True)]
    assert run.outputs["detect-abnormal"].values["lesion_computed"] is False
    assert run.outputs["segment-tumor"].values["tumor_pixels_total"] > 0


def test_the_lesion_artifact_metadata_round_trips_the_mirror_plane():
    # what the detect stage stores is what the segment stage rebuilds: the scalars and
    # the mid-sagittal plane (JSON-able: plain floats and ints)
    import json

    from tumor3d.segmentation.lesion import LesionResult, MirrorPlane, NormalModel
    from tumor3d.segmentation.patient import lesion_from_record
    from tumor3d.tasks.detect import lesion_metadata

    mask = np.zeros((2, 4, 4), dtype=bool)
    mask[1, 1:3, 1:3] = True
    plane = MirrorPlane(2, -3.25, 117.5)
    original = LesionResult(
        mask, NormalModel(120.0, 20.0, 160.0, float("inf")), 200.0, 160.0, 1, plane
    )
    meta = json.loads(json.dumps(lesion_metadata(original, {})))
    rebuilt = lesion_from_record(mask, meta)
    assert rebuilt.plane == plane
    assert rebuilt.model == original.model and rebuilt.n_components == 1
    without = LesionResult(mask, original.model, 200.0, 160.0, 1)
    without_meta = json.loads(json.dumps(lesion_metadata(without, {})))
    assert lesion_from_record(mask, without_meta).plane is None
    # step 3f's flag (found without the symmetry rule's confirmation) round-trips too; an
    # artifact written before the flag existed reads as "not found by step 3f"
    assert not rebuilt.midline
    flagged = LesionResult(mask, original.model, 200.0, 160.0, 1, plane, True)
    assert lesion_from_record(mask, json.loads(json.dumps(lesion_metadata(flagged, {})))).midline
    old_meta = {k: v for k, v in meta.items() if k != "midline"}
    assert not lesion_from_record(mask, old_meta).midline


def test_preprocess_notes_say_when_the_brain_is_smaller_than_any_human_brain():
    from tumor3d.imaging.preprocess import MIN_BRAIN_SLICE_MM2

    base = {"brain_volume_ml": 1.7, "brain_slices": 20, "tissue_slices": 26,
            "brain_extraction": "foreground"}  # fmt: skip
    (note,) = preprocess_notes({**base, "brain_max_slice_mm2": 150.0})
    assert note.startswith("brain mask of at most 1.5 cm2 on any slice")
    assert "voxel size" in note and split_notes(join_notes([note])) == [note]
    assert preprocess_notes({**base, "brain_max_slice_mm2": MIN_BRAIN_SLICE_MM2}) == []
    assert preprocess_notes({**base, "brain_max_slice_mm2": MIN_BRAIN_SLICE_MM2 - 1}) != []
    # a mask the user gave is checked too (a wrong voxel size shrinks it as well)
    given = {**base, "brain_extraction": "given", "brain_max_slice_mm2": 150.0}
    assert [n[:30] for n in preprocess_notes(given)] == [note[:30]]


def test_preprocess_stage_stores_the_largest_brain_slice_in_mm2(tmp_path):
    """Independent expectation: the mask's largest slice count x the pixel area."""
    rng = np.random.default_rng(5)
    data = rng.normal(100.0, 3.0, (40, 30, 6)).astype(np.float32)
    data[5:35, 5:25, :] += 200.0  # a bright block the skull removal keeps
    path = tmp_path / "p.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([0.7, 0.5, 4.0, 1.0])), path)
    run = run_stages_direct(path, tmp_path / "store", patient_id="p1")
    values = run.outputs["preprocess"].values
    store = ArtifactStore(tmp_path / "store")
    brain, _ = store.get_volume(run.outputs["preprocess"].artifacts["brain_mask"])
    largest = int(brain.reshape(brain.shape[0], -1).sum(axis=1).max())
    assert values["brain_max_slice_mm2"] == pytest.approx(largest * 0.7 * 0.5)
    assert values["brain_max_slice_mm2"] > 0


def test_the_air_outside_a_raw_head_reaches_the_segment_stage_and_a_stripped_one_has_none(
    tumour_run, tmp_path
):
    """The preprocess stage stores the air of a raw head (the phantom's), all False for a
    skull-stripped volume; a deep tumour gets no scalp caveat from it."""
    run, store = tumour_run
    ext, _ = store.get_volume(run.outputs["preprocess"].artifacts["head_exterior"])
    brain, _ = store.get_volume(run.outputs["preprocess"].artifacts["brain_mask"])
    ext, brain = ext.astype(bool), brain.astype(bool)
    assert ext.any() and not (ext & brain).any()
    assert not any("air outside the head" in c for c in run.outputs["segment-tumor"].values[
        "caveats"])  # fmt: skip
    # the same brain skull-stripped: a foreground volume, no air stored
    scan, affine = store.get_volume(run.outputs["ingest-scan"].artifacts["scan"])
    stripped = np.where(brain, scan, 0.0).astype(np.float32)
    path = tmp_path / "stripped.nii.gz"
    nib.save(nib.Nifti1Image(stripped.transpose(2, 1, 0), affine), path)
    again = run_stages_direct(path, tmp_path / "store", patient_id="s1")
    assert again.outputs["preprocess"].values["brain_extraction"] == "foreground"
    ext2, _ = ArtifactStore(tmp_path / "store").get_volume(
        again.outputs["preprocess"].artifacts["head_exterior"]
    )
    assert not ext2.any()


def test_every_declared_input_is_produced_by_an_earlier_stage_of_the_same_kind():
    from tumor3d.tasks.train import SPEC as TRAINING_ROWS

    assert stages.wiring_errors(stages.STAGES.values()) == []
    pipeline = [stages.STAGES[n] for n in ("ingest-scan", "preprocess", "detect-abnormal")]
    assert stages.wiring_errors([*pipeline, TRAINING_ROWS]) == []
    # independent expectation: the check catches each way a declaration goes wrong
    surface = stages.STAGES["extract-surface"]
    order = list(stages.STAGES.values())
    swapped = [s for s in order if s is not surface]
    swapped.insert(order.index(stages.STAGES["interpolate-slices"]), surface)  # too early
    assert any("has not run before" in e for e in stages.wiring_errors(swapped))
    from dataclasses import replace

    from tumor3d.tasks.spec import Input

    wrong = Input("mesh", "interpolate-slices.tumor_mask")
    wrong_kind = replace(surface, inputs={"tumor_mask": wrong})
    errors = stages.wiring_errors([s if s is not surface else wrong_kind for s in order])
    assert errors == [
        "extract-surface.tumor_mask: interpolate-slices.tumor_mask is 'mask', not 'mesh'"
    ]
    missing = replace(surface, inputs={"tumor_mask": Input("mask", "interpolate-slices.nothing")})
    assert stages.wiring_errors([s if s is not surface else missing for s in order])


def test_the_stages_another_needs_are_read_from_the_declarations():
    from tumor3d.tasks.train import SPEC as TRAINING_ROWS
    from tumor3d.tasks.train import UNET_SLICES

    def names(specs):
        return [s.name for s in specs]

    # independent expectation: the inputs each stage's adapter module names, followed back
    assert names(stages.upstream(TRAINING_ROWS)) == ["ingest-scan", "preprocess", "detect-abnormal"]
    assert names(stages.upstream(UNET_SLICES)) == ["ingest-scan"]
    assert names(stages.upstream(stages.STAGES["ingest-scan"])) == []
    assert names(stages.upstream(stages.STAGES["extract-surface"])) == [
        "ingest-scan", "preprocess", "detect-abnormal", "segment-tumor", "interpolate-slices"
    ]  # fmt: skip
    # the volumes need neither surface of the brain nor the renders
    assert names(stages.upstream(stages.STAGES["measure-volume"])) == [
        "ingest-scan", "preprocess", "detect-abnormal", "segment-tumor", "interpolate-slices",
        "extract-surface", "simplify-mesh",
    ]  # fmt: skip
    from dataclasses import replace

    from tumor3d.tasks.spec import Input

    lost = replace(UNET_SLICES, inputs={"scan": Input("scan", "no-such-stage.scan")})
    with pytest.raises(KeyError, match="no-such-stage"):
        stages.upstream(lost)


def test_a_declared_input_names_the_product_it_takes(tumour_run):
    run, _ = tumour_run
    segment = stages.STAGES["segment-tumor"]
    detection = run.outputs["detect-abnormal"].artifacts["detection"]
    assert stages.product(run.outputs, segment.inputs["detection"]) is detection
    with pytest.raises(ValueError, match="given:segmentation"):
        stages.product(run.outputs, segment.inputs["given_mask"])


def test_a_declaration_that_breaks_the_wiring_is_refused_by_name():
    """check_wiring (run once when the registry is imported) names the wrong input."""
    from dataclasses import replace

    from tumor3d.tasks import surface
    from tumor3d.tasks.spec import Input

    stages.check_wiring(stages.STAGES.values())  # the shipped declarations wire up
    wrong = replace(
        surface.SPEC, inputs={"tumor_mask": Input("mesh", "interpolate-slices.tumor_mask")}
    )
    with pytest.raises(TypeError, match="stage declarations do not wire up") as info:
        stages.check_wiring([*stages.STAGES.values(), wrong])
    assert "extract-surface.tumor_mask: interpolate-slices.tumor_mask is 'mask', not 'mesh'" in (
        str(info.value)
    )


def test_metrics_columns_come_from_the_stage_declarations(tumour_run):
    run, _ = tumour_run
    row = stages.metric_columns(run.outputs)
    outs = run.outputs
    # independent expectation: the columns the published metrics have always held
    assert row["faces_mc"] == outs["extract-surface"].values["faces"]
    assert row["faces_simplified"] == outs["simplify-mesh"].values["faces"]
    assert row["faces_target"] == outs["simplify-mesh"].values["faces_target"]
    assert row["mesh_watertight"] is outs["extract-surface"].values["watertight"]
    assert row["slices_between"] == outs["interpolate-slices"].values["slices_between"]
    assert row["segment_method"] == outs["segment-tumor"].values["segment_method"]
    assert {k: row[k] for k in outs["measure-volume"].values} == outs["measure-volume"].values
    for name, spec in stages.STAGES.items():  # every declared column has a description
        if isinstance(spec.metrics, dict):
            assert all(m.description for m in spec.metrics.values()), name


def test_an_undeclared_product_is_refused(tmp_path):
    from tumor3d.tasks.spec import Input, StageResult, stage

    @stage("probe", entry=len, inputs={"mesh": Input("mesh", "extract-surface.mesh")},
           outputs={"mesh": "mesh"})  # fmt: skip
    def probe(mesh: object) -> StageResult:
        return StageResult(artifacts={"other": mesh}, values={})

    store = ArtifactStore(tmp_path)
    with pytest.raises(TypeError, match="'other' is not declared"):
        probe.task.fn(mesh=store.put_mesh(_tetrahedron()), store_root=str(store.root))

"""The real-data benchmarks run the default as the segment stage does, with out-of-fold models.

``benchmarks/real_segmentation.py``'s harness (used by ``real_robustness.py``,
``pseudo_healthy.py``, ``transplant.py``) must run the learned method where the
configuration resolves to it (without its models ``segment_tumor`` falls back to the
robust method), and ``benchmarks/oof_models.py`` must give each case the forest of the
cross-validation fold that held its patient out. Phantoms and synthetic rows only.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from benchmark_scripts import benchmark_module

from tumor3d.learned.features import FEATURE_NAMES
from tumor3d.phantom.patient import make_phantom_patient
from tumor3d.segmentation.lesion import left_right_axis
from tumor3d.segmentation.segment import segment_tumor

lgb = pytest.importorskip("lightgbm")
learned_cv = benchmark_module("learned_cv")
rs = benchmark_module("real_segmentation")
oof_models = benchmark_module("oof_models")


def _forest(seed: int, meta: dict):
    """A small forest on synthetic rows (lesion: the first feature above 0)."""
    from tumor3d.learned.training import TrainingRows, train_forest

    rng = np.random.default_rng(seed)
    x = rng.normal(size=(400, len(FEATURE_NAMES))).astype(np.float32)
    y = (x[:, 0] > 0).astype(np.float32)
    return train_forest(
        TrainingRows(x, y, np.ones_like(y)),
        num_rounds=5,
        params={"min_data_in_leaf": 10},
        meta=meta,
    )


@pytest.fixture
def fold_dir(tmp_path: Path) -> Path:
    """Two folds as ``learned_cv.py --save-models`` writes them: patient a in fold 0, b in 1."""
    specs = [
        SimpleNamespace(patient="a", image=str(tmp_path / "a_flair.nii.gz")),
        SimpleNamespace(patient="a", image=str(tmp_path / "a_t2.nii.gz")),
        SimpleNamespace(patient="b", image=str(tmp_path / "b_flair.nii.gz")),
    ]
    folds = {"a": 0, "b": 1}
    args = SimpleNamespace(threshold=0.5, t1c_threshold=0.65, keep_fraction=1.0, prior=True)
    learned_cv.write_fold_map(tmp_path / "folds.json", specs, folds)
    for k in (0, 1):
        meta = learned_cv._fold_meta("hyper", ("flair", "t2"), k, folds, args)
        (tmp_path / f"hyper_fold{k}.npz").write_bytes(_forest(k, meta).to_bytes())
    return tmp_path


def test_each_case_gets_the_forest_of_the_fold_that_held_its_patient_out(fold_dir: Path):
    oof = oof_models.OutOfFold(fold_dir)
    for image, fold in (("a_flair", 0), ("a_t2", 0), ("b_flair", 1)):
        # the forest alone (segment.learned_cnn off: no fold U-Nets given)
        models = oof.models(fold_dir / f"{image}.nii.gz", image.split("_")[1], "off")
        assert models["model"].meta["fold"] == fold
        assert models["model"].meta["held_out_patients"] == [image[0]]
        assert models["cnn"] is None
    with pytest.raises(KeyError, match="not a case of the cross-validation"):
        oof.models(fold_dir / "c_flair.nii.gz", "flair", "off")


def test_a_forest_that_saw_the_patient_is_refused(fold_dir: Path):
    # fold 1's file swapped for fold 0's: patient b would be scored by a model trained on it
    (fold_dir / "hyper_fold1.npz").write_bytes((fold_dir / "hyper_fold0.npz").read_bytes())
    with pytest.raises(ValueError, match="other held-out patients"):
        oof_models.OutOfFold(fold_dir).models(fold_dir / "b_flair.nii.gz", "flair", "off")


def test_the_harness_runs_the_learned_default_and_the_given_models():
    p = make_phantom_patient(3, modality="flair", matrix_size=(128, 128))
    scan = p.scan
    args = (scan.image.astype(np.float64), rs.default_config(), "flair", None)
    geometry = (scan.spacing_zyx_mm, left_right_axis(scan.affine))
    _, _, default, _ = rs.run_pipeline(*args, *geometry)
    # the default resolves to the learned method on FLAIR and runs it with the shipped models
    assert default.method == "learned" and default.probability is not None
    robust_cfg = rs.default_config(rs.ROOT / "configs" / "robust.yaml")
    _, _, robust, _ = rs.run_pipeline(args[0], robust_cfg, "flair", None, *geometry)
    assert robust.method == "robust" and robust.probability is None
    # given models (the out-of-fold ones) are the ones used, exactly: the harness's result
    # is segment_tumor's with that forest and no U-Net (not the shipped nets beside it)
    given = {"model": _forest(0, {"threshold": 0.5, "keep_fraction": 1.0}), "cnn": None}
    pre, det, other, _ = rs.run_pipeline(*args, *geometry, given)
    assert other.method == "learned"
    assert not np.allclose(other.probability, default.probability)
    cfg = rs.default_config()
    direct = segment_tumor(
        pre.enhanced, pre.brain_mask, det, modality="flair", spacing_mm=geometry[0],
        lr_axis=geometry[1], **cfg.segment.model_dump(), image=args[0], **given,
    )  # fmt: skip
    np.testing.assert_array_equal(other.probability, direct.probability)
    np.testing.assert_array_equal(other.tumor_mask, direct.tumor_mask)


def _net_file(path: Path, fold: int | None) -> None:
    """A random 2-level U-Net weight file (no torch) recording ``fold`` as cnn_cv.py does."""
    rng = np.random.default_rng(0)
    a, c = {}, 3
    for i, o in enumerate((2, 4)):
        for j, ci in enumerate((c, o)):
            a[f"enc{i}_{j}_w"] = rng.normal(0, 0.3, (o, ci, 3, 3))
            a[f"enc{i}_{j}_b"] = rng.normal(0, 0.1, o)
        c = o
    for j, ci in enumerate((c + 2, 2)):
        a[f"dec0_{j}_w"] = rng.normal(0, 0.3, (2, ci, 3, 3))
        a[f"dec0_{j}_b"] = rng.normal(0, 0.1, 2)
    a["head_w"], a["head_b"] = rng.normal(0, 1.0, (1, 2, 1, 1)), np.array([0.5])
    meta = {"settings": {"size": 32, "context": 1}}
    if fold is not None:
        meta["fold"] = fold
    arrays = {k: v.astype(np.float32) for k, v in a.items()}
    blob = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with path.open("wb") as f:
        np.savez(f, **arrays, meta_json=blob)


def test_flair_gets_the_fold_nets_and_a_net_of_another_fold_is_refused(fold_dir: Path):
    seeds = [fold_dir / "seed0", fold_dir / "seed1"]
    for d in seeds:
        d.mkdir()
        for k in (0, 1):
            _net_file(d / f"unet_fold{k}.npz", k if d.name == "seed1" else None)
    oof = oof_models.OutOfFold(fold_dir, [str(d) for d in seeds])
    flair = oof.models(fold_dir / "b_flair.nii.gz", "flair")
    assert len(flair["cnn"]) == 2 and flair["cnn"][1].meta["fold"] == 1
    # T2 has no U-Net (tumor3d.learned.shipped.CNN_MODELS), nor does segment.learned_cnn off
    assert oof.models(fold_dir / "a_t2.nii.gz", "t2")["cnn"] is None
    assert oof.models(fold_dir / "a_flair.nii.gz", "flair", "off")["cnn"] is None
    # without fold nets, FLAIR would be scored with the forest alone as if it were the default
    with pytest.raises(ValueError, match="give the fold U-Nets"):
        oof_models.OutOfFold(fold_dir).models(fold_dir / "a_flair.nii.gz", "flair")
    # a net recording another fold than the one it is filed as
    _net_file(seeds[1] / "unet_fold0.npz", 1)
    oof_models._net.cache_clear()
    with pytest.raises(ValueError, match="trained as fold 1, not 0"):
        oof_models.OutOfFold(fold_dir, [str(d) for d in seeds]).models(
            fold_dir / "a_flair.nii.gz", "flair"
        )


def test_case_models_are_the_shipped_ones_without_oof_and_cnn_folds_need_oof(fold_dir: Path):
    cfg = rs.default_config()
    assert rs.case_models(None, "any.nii.gz", "flair", cfg) is None  # run_pipeline: shipped
    ap = argparse.ArgumentParser()
    rs.add_oof_arguments(ap)
    with pytest.raises(SystemExit):
        rs.oof_from_args(ap.parse_args(["--cnn-folds", str(fold_dir)]))
    oof = rs.oof_from_args(ap.parse_args(["--oof-models", str(fold_dir)]))
    models = rs.case_models(oof, str(fold_dir / "a_t2.nii.gz"), "t2", cfg)
    assert models["model"].meta["fold"] == 0

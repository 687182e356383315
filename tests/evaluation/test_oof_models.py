"""The real-data benchmarks run the default as the segment stage does, with out-of-fold models.

``benchmarks/real_segmentation.py``'s harness (used by ``real_robustness.py``,
``pseudo_healthy.py``, ``transplant.py``) must run the learned method where the
configuration resolves to it (without its models ``segment_tumor`` falls back to the
robust method), and ``benchmarks/oof_models.py`` must give each case the forest of the
cross-validation fold that held its patient out. Phantoms and synthetic rows only.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from benchmark_scripts import benchmark_module

from tumor3d.learned.features import FEATURE_NAMES
from tumor3d.phantom.patient import make_phantom_patient
from tumor3d.segmentation.lesion import left_right_axis

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
        models = oof.models(fold_dir / f"{image}.nii.gz", image.split("_")[1])
        assert models["model"].meta["fold"] == fold
        assert models["model"].meta["held_out_patients"] == [image[0]]
        assert models["cnn"] is None  # no fold U-Nets given
    with pytest.raises(KeyError, match="not a case of the cross-validation"):
        oof.models(fold_dir / "c_flair.nii.gz", "flair")


def test_a_forest_that_saw_the_patient_is_refused(fold_dir: Path):
    # fold 1's file swapped for fold 0's: patient b would be scored by a model trained on it
    (fold_dir / "hyper_fold1.npz").write_bytes((fold_dir / "hyper_fold0.npz").read_bytes())
    with pytest.raises(ValueError, match="other held-out patients"):
        oof_models.OutOfFold(fold_dir).models(fold_dir / "b_flair.nii.gz", "flair")


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
    # given models (the out-of-fold ones) are the ones used: a forest that calls every
    # voxel with a low first feature lesion gives another probability than the shipped one
    given = {"model": _forest(0, {"threshold": 0.5, "keep_fraction": 1.0}), "cnn": None}
    _, _, other, _ = rs.run_pipeline(*args, *geometry, given)
    assert other.method == "learned"
    assert not np.allclose(other.probability, default.probability)

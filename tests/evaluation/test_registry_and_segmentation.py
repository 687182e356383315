"""The evaluation registry and the built-in segmentation evaluation on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.evaluation import EvaluationCase, EvaluationRows, registered_evaluations
from tumor3d.evaluation.registry import register_evaluation


def _case(
    pred_slices, ref_slices, *, reference=None, pred_on_reference=None, metrics=None, det=None
):
    aff = np.diag([1.0, 1.0, 5.0, 1.0])
    return EvaluationCase(
        patient_id="p1",
        reference_kind="truth",
        slice_axis=2,
        acquired_affine=aff,
        pred_slices=pred_slices,
        ref_slices=ref_slices,
        detector_abnormal=det,
        pred_fine=pred_slices,
        pred_fine_affine=aff,
        reference=reference,
        reference_affine=None if reference is None else np.diag([1.0, 1.0, 1.0, 1.0]),
        pred_on_reference=pred_on_reference,
        metrics=metrics or {},
    )


def test_builtin_is_registered():
    evals = registered_evaluations()
    assert "segmentation" in evals
    assert evals["segmentation"].description


def test_register_a_new_evaluation_and_reject_a_clash(monkeypatch):
    # a copy of the registry for this test: the probe must not stay registered for the
    # tests and doctests after it (selected_evaluations' doctest lists the defaults)
    import tumor3d.evaluation.registry as registry

    # the built-in ones registered first, in the registry kept: run first in a process,
    # the copy took them and the restored registry lacked them for the tests after
    registered_evaluations()
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))

    @register_evaluation("unit-test-eval", description="counts slices")
    def count(case):
        return EvaluationRows(patient={"n": int(case.pred_slices.shape[case.slice_axis])})

    evals = registered_evaluations()
    assert evals["unit-test-eval"].fn(_case(np.zeros((3, 3, 4), bool), None)).patient == {"n": 4}
    with pytest.raises(InputError, match="already registered"):

        @register_evaluation("unit-test-eval", description="other")
        def other(case):  # pragma: no cover
            return EvaluationRows()


def test_slice_counts_confusion_dice_and_volumes():
    # slices along axis 2; 4 slices: ref tumour on 1, 2; pred tumour on 1 (half) and 3 (false)
    ref = np.zeros((4, 4, 4), bool)
    ref[:2, :2, 1] = True  # 4 px
    ref[:2, :, 2] = True  # 8 px
    pred = np.zeros_like(ref)
    pred[:2, :1, 1] = True  # 2 px, inside the 4
    pred[0, 0, 3] = True  # 1 px false positive slice
    reference = np.zeros((6, 6, 6), bool)
    reference[1:5, 1:5, 1:5] = True  # 64 mm3
    metrics = {"volume_eq7_mm3": 32.0, "volume_voxel_mm3": 64.0, "volume_mesh_mm3": 80.0}
    det = np.array([False, True, True, True])
    ev = registered_evaluations()["segmentation"].fn
    full = ev(_case(pred, ref, reference=reference, pred_on_reference=reference,
                    metrics=metrics, det=det))  # fmt: skip
    row = full.patient
    assert (row["tp"], row["fp"], row["tn"], row["fn"]) == (1, 1, 1, 1)
    assert (row["det_tp"], row["det_fp"], row["det_tn"], row["det_fn"]) == (2, 1, 1, 0)
    assert (row["n_p"], row["n_g"]) == (3, 12)
    assert row["eq9_percent"] == pytest.approx(75.0)
    # slice 1: Dice 2*2/(2+4) = 2/3; slice 2: Dice 0 -> mean 1/3
    assert row["dice_slices_mean"] == pytest.approx((2 / 3 + 0.0) / 2)
    assert row["dice_pooled"] == pytest.approx(2 * 2 / (3 + 12))
    assert row["dice_3d"] == 1.0 and row["hd95_mm"] == 0.0 and row["hd_max_mm"] == 0.0
    assert row["ref_volume_mm3"] == pytest.approx(64.0)
    assert row["volume_eq7_error_percent"] == pytest.approx(-50.0)
    assert row["volume_voxel_error_percent"] == pytest.approx(0.0)
    assert row["volume_mesh_error_percent"] == pytest.approx(25.0)
    by_index = {s["slice_index"]: s for s in full.slices}
    assert by_index[1]["dice"] == pytest.approx(2 / 3) and np.isnan(by_index[0]["dice"])
    assert by_index[3]["pred_abnormal"] and not by_index[3]["truly_abnormal"]
    assert row["reference_kind"] == "truth"


def test_case_validation():
    with pytest.raises(InputError, match="acquired grid"):
        _case(np.zeros((3, 3, 4), bool), np.zeros((3, 3, 5), bool))

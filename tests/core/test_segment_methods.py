"""The registry of segmentation methods: one registration adds a method everywhere."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tumor3d.config import SegmentConfig, parse_config
from tumor3d.errors import ConfigError, InputError
from tumor3d.segmentation import methods
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.segment import SegmentationResult, lesion_definition, segment_tumor

README = Path(__file__).resolve().parents[2] / "README.md"
THRESHOLD = 200


@pytest.fixture
def registry(monkeypatch):
    """A copy of the registry: what a test registers is gone after it."""
    methods.registered_methods()  # the shipped methods registered first
    monkeypatch.setattr(methods, "_REGISTRY", dict(methods._REGISTRY))
    return methods


def _register_toy(registry, seen, **extra):
    @registry.register_method(
        "toy",
        description="brain pixels at or above gray 200 on the abnormal slices",
        measures="the pixels at or above gray 200 on {seq}",
        **extra,
    )
    def segment_toy(enhanced, brain_mask, detection, *, modality, min_tumor_pixels):
        seen.update(modality=modality, min_tumor_pixels=min_tumor_pixels)
        mask = (enhanced >= THRESHOLD) & brain_mask & detection.abnormal[:, None, None]
        nz = mask.shape[0]
        return SegmentationResult(
            tumor_mask=mask,
            tumor_pixels=mask.sum(axis=(1, 2)).astype(np.int64),
            reference_centers=np.full(3, np.nan),
            tumor_center_gray=np.full(nz, np.nan),
            selection=np.where(mask.any(axis=(1, 2)), "toy", "").astype(str),
        )

    return segment_toy


def _case():
    """Three slices of a square brain; a bright 4x5 block on slices 1 and 2, slice 2 normal."""
    rng = np.random.default_rng(3)
    enhanced = rng.integers(60, 150, size=(3, 24, 24)).astype(np.uint8)
    brain = np.zeros(enhanced.shape, dtype=bool)
    brain[:, 2:22, 2:22] = True
    enhanced[~brain] = 0
    enhanced[1:, 8:12, 9:14] = 230
    abnormal = np.array([False, True, False])
    det = SliceDetection(
        n_modes=np.where(abnormal, 4, 3).astype(np.int64),
        abnormal=abnormal,
        peaks_gray=tuple(np.array([80.0, 120.0, 230.0]) for _ in range(3)),
        brain_pixels=brain.sum(axis=(1, 2)).astype(np.int64),
    )
    return enhanced, brain, det


def test_a_registered_method_runs_through_the_config_and_the_segment_entry(registry):
    seen: dict = {}
    _register_toy(registry, seen)
    enhanced, brain, det = _case()
    cfg = parse_config({"segment": {"method": "toy", "min_tumor_pixels": 5}}).segment
    res = segment_tumor(enhanced, brain, det, modality="flair", **cfg.model_dump())
    # the independent expectation: the bright block on the one abnormal slice
    expected = np.zeros(enhanced.shape, dtype=bool)
    expected[1, 8:12, 9:14] = True
    np.testing.assert_array_equal(res.tumor_mask, expected)
    assert res.method == "toy" and res.tumor_pixels.tolist() == [0, 20, 0]
    # only the keywords it names, with the configuration's values
    assert seen == {"modality": "flair", "min_tumor_pixels": 5}
    assert lesion_definition("toy", "t2") == "the pixels at or above gray 200 on T2"
    assert "toy" in SegmentConfig.model_json_schema()["properties"]["method"]["enum"]


def test_the_config_refuses_an_unknown_method_naming_the_registered_ones(registry):
    with pytest.raises(ConfigError) as err:
        parse_config({"segment": {"method": "kmeans"}})
    listed = "auto, learned, multiotsu, paper, robust"
    assert f"unknown segmentation method 'kmeans': expected one of {listed}" in str(err.value)
    _register_toy(registry, {})
    with pytest.raises(ConfigError, match=f"expected one of {listed}, toy"):
        parse_config({"segment": {"method": "kmeans"}})
    with pytest.raises(InputError, match="unknown segmentation method 'kmeans'"):
        segment_tumor(*_case(), method="kmeans")


def test_a_method_runs_only_on_the_modalities_it_declares(registry):
    _register_toy(registry, {}, modalities=("flair",))
    enhanced, brain, det = _case()
    assert segment_tumor(enhanced, brain, det, modality="FLAIR", method="toy").method == "toy"
    with pytest.raises(InputError, match="the toy method does not segment t2: it takes flair"):
        segment_tumor(enhanced, brain, det, modality="t2", method="toy")


def test_registration_refuses_auto_a_taken_name_and_unknown_modalities(registry):
    with pytest.raises(InputError, match="other than 'auto'"):
        registry.register_method("auto", description="x", measures="x")
    with pytest.raises(InputError, match="modalities must be some of t2, flair, t1c"):
        registry.register_method("t1only", description="x", measures="x", modalities=("t1",))
    with pytest.raises(InputError, match="'robust' is already registered"):
        registry.register_method("robust", description="x", measures="x")(lambda *a: None)


def test_the_shipped_methods_declare_what_the_adapters_load():
    every = methods.registered_methods()
    assert {n for n, m in every.items() if m.uses_lesion} == {"robust", "learned"}
    assert {n for n, m in every.items() if m.needs_model} == {"learned"}
    assert methods.method_uses_lesion("auto") and not methods.method_uses_lesion("multiotsu")


def test_the_readme_table_lists_every_registered_method():
    text = README.read_text(encoding="utf-8")
    section = text.split("## Segmentation methods and accuracy", 1)[1]
    table = section.split("| method | what it is |", 1)[1].split("\n\n", 1)[0]
    rows = re.findall(r"^\| `([a-z0-9_-]+)`", table, flags=re.MULTILINE)
    assert sorted(rows) == list(methods.method_names())

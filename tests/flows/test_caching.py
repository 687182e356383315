"""Cache keys: content-derived, from one place, blind to locations and run ids."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from storage.store import ArtifactRef
from tasks.caching import StageCachePolicy, code_digest, fingerprint, stage_cache_key
from tasks.stages import STAGES, InputSource
from tumor3d.config import PipelineConfig, SimplifyConfig

MODULES = ("tumor3d.config",)


def _ref(digest_char: str, relpath: str = "objects/aa/x.nii.gz") -> ArtifactRef:
    return ArtifactRef(kind="mask", digest=digest_char * 64, relpath=relpath, metadata={})


def test_key_is_deterministic_and_ignores_store_location():
    inputs = {"mesh": _ref("a"), "config": SimplifyConfig(), "store_root": "/tmp/one"}
    k1 = stage_cache_key("simplify-mesh", MODULES, inputs)
    k2 = stage_cache_key("simplify-mesh", MODULES, {**inputs, "store_root": "/elsewhere"})
    assert k1 == k2
    assert k1.startswith("simplify-mesh-")


def test_key_changes_with_config_input_digest_and_stage():
    base = {"mesh": _ref("a"), "config": SimplifyConfig(), "store_root": "/s"}
    k = stage_cache_key("simplify-mesh", MODULES, base)
    other_cfg = {**base, "config": SimplifyConfig(reduction_percent=40)}
    other_input = {**base, "mesh": _ref("b")}
    assert stage_cache_key("simplify-mesh", MODULES, other_cfg) != k
    assert stage_cache_key("simplify-mesh", MODULES, other_input) != k
    assert stage_cache_key("render-views", MODULES, base) != k


def test_artifact_identity_is_its_digest_not_its_path():
    assert fingerprint(_ref("c", "objects/x/1.ply")) == fingerprint(_ref("c", "elsewhere/2.ply"))


def test_input_source_location_is_not_part_of_the_key():
    a = InputSource(path="/data/a/flair.nii.gz", name="flair.nii.gz", digest="d" * 64,
                    modality="flair", patient_id="p1")  # fmt: skip
    b = a.model_copy(update={"path": "/moved/flair.nii.gz"})
    c = a.model_copy(update={"digest": "e" * 64})
    assert stage_cache_key("ingest-scan", MODULES, {"source": a}) == stage_cache_key(
        "ingest-scan", MODULES, {"source": b}
    )
    assert stage_cache_key("ingest-scan", MODULES, {"source": a}) != stage_cache_key(
        "ingest-scan", MODULES, {"source": c}
    )


def test_arrays_cannot_sneak_into_keys():
    with pytest.raises(TypeError, match="ndarray"):
        fingerprint(np.zeros(3))


def test_code_digest_follows_module_source(tmp_path, monkeypatch):
    mod = tmp_path / "t3d_probe_mod.py"
    mod.write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    code_digest.cache_clear()
    d1 = code_digest(("t3d_probe_mod",))
    mod.write_text("X = 2\n")
    code_digest.cache_clear()
    d2 = code_digest(("t3d_probe_mod",))
    assert d1 != d2
    sys.modules.pop("t3d_probe_mod", None)
    code_digest.cache_clear()


def test_every_stage_has_importable_code_modules():
    for name, modules in STAGES.items():
        assert len(code_digest(modules)) == 64, name


def test_policy_delegates_to_the_single_key_function():
    policy = StageCachePolicy(stage="simplify-mesh", modules=MODULES)
    inputs = {"mesh": _ref("a"), "config": PipelineConfig().simplify, "store_root": "/s"}
    assert policy.compute_key(None, inputs, {}) == stage_cache_key("simplify-mesh", MODULES, inputs)

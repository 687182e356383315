"""Each stage's config model and its core function agree.

A task calls ``core_function(data, **config.model_dump())``: every config
field must be a keyword of the function, and where the function has a
default it must equal the config's default (two sources of one default drift
apart silently otherwise).
"""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import yaml

from tumor3d.config import (
    DetectConfig,
    InterpolateConfig,
    LesionConfig,
    PipelineConfig,
    PreprocessConfig,
    RenderConfig,
    SegmentConfig,
    SimplifyConfig,
    SurfaceConfig,
    parse_config,
)
from tumor3d.errors import ConfigError
from tumor3d.geometry.interpolate import interpolate_stack
from tumor3d.geometry.surface import extract_surface
from tumor3d.imaging.preprocess import preprocess_volume
from tumor3d.segmentation.detect import detect_abnormal_slices
from tumor3d.segmentation.lesion import LESION_DEFAULTS, segment_hyperintense_lesion
from tumor3d.segmentation.segment import segment_tumor
from tumor3d.simplify import simplify_mesh
from tumor3d.visual.render import render_views

PAIRS = [
    (PreprocessConfig, preprocess_volume),
    (DetectConfig, detect_abnormal_slices),
    (LesionConfig, segment_hyperintense_lesion),
    (SegmentConfig, segment_tumor),
    (InterpolateConfig, interpolate_stack),
    (SurfaceConfig, extract_surface),
    (SimplifyConfig, simplify_mesh),
    (RenderConfig, render_views),
]

#: Deliberate differences: (function, keyword) -> reason.
DIFFERENT_DEFAULTS = {
    ("interpolate_stack", "end_caps"): "the core default is the paper's flat caps; "
    "the pipeline default (taper) is a measured improvement",
    ("detect_abnormal_slices", "lesion"): "None = LESION_DEFAULTS (checked against "
    "LesionConfig below)",
}

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _normalise(value):
    return list(value) if isinstance(value, tuple) else value


@pytest.mark.parametrize(("model", "fn"), PAIRS, ids=[m.__name__ for m, _ in PAIRS])
def test_every_config_field_is_a_keyword_with_the_same_default(model, fn):
    params = inspect.signature(fn).parameters
    defaults = model()
    for name in type(defaults).model_fields:
        assert name in params, f"{fn.__name__} lacks keyword {name!r} of {model.__name__}"
        assert params[name].kind is inspect.Parameter.KEYWORD_ONLY, (fn.__name__, name)
        default = params[name].default
        if default is inspect.Parameter.empty or (fn.__name__, name) in DIFFERENT_DEFAULTS:
            continue
        assert _normalise(default) == _normalise(getattr(defaults, name)), (fn.__name__, name)


def test_default_yaml_is_exactly_the_code_defaults():
    text = (CONFIGS / "default.yaml").read_text()
    parsed = parse_config(text, source="default.yaml")
    assert parsed == PipelineConfig()
    # and it lists every key, as the README says (a key left out reads its default too)
    assert yaml.safe_load(text) == PipelineConfig().model_dump(mode="json")


def test_paper_yaml_is_valid_and_reads_the_paper_method():
    # The measured reading of the paper (configs/paper.yaml's comments,
    # reports/PAPER.md): sharpening and equalisation off (they erase the
    # histogram modes the method counts), the boundary decided by partial
    # volume, the slices linked in 3-D; Otsu skull mask, literal largest
    # component, Algorithm 1 interpolation without end caps.
    paper = parse_config((CONFIGS / "paper.yaml").read_text(), source="paper.yaml")
    assert not paper.preprocess.sharpen and not paper.preprocess.equalize
    assert paper.preprocess.skull_threshold == "otsu"
    assert paper.segment.keep_largest_3d_component and paper.segment.refine_boundary
    assert paper.segment.rim_px == 0
    assert paper.interpolate.end_caps == "none"


@pytest.mark.parametrize("name", sorted(p.name for p in CONFIGS.glob("*.yaml")))
def test_every_shipped_config_parses(name):
    # the configurations the README and the reports name (--config configs/<name>)
    parse_config((CONFIGS / name).read_text(), source=name)


@pytest.mark.parametrize("modality", ["flair", "t2", "t1c", None])
def test_robust_yaml_runs_the_rule_based_method_on_every_sequence(modality):
    # configs/robust.yaml: the robust lesion model whatever the sequence (no trained model),
    # as reports/segmentation.md measures it; the default resolves otherwise on FLAIR
    from tumor3d.segmentation.segment.definition import resolve_method

    robust = parse_config((CONFIGS / "robust.yaml").read_text(), source="robust.yaml")
    assert resolve_method(robust.segment.method, modality) == "robust"
    assert resolve_method(PipelineConfig().segment.method, "flair") == "learned"
    # only the method differs from the default
    assert robust.model_copy(update={"segment": PipelineConfig().segment}) == PipelineConfig()


def test_lesion_defaults_are_the_lesion_config():
    assert LESION_DEFAULTS == LesionConfig().model_dump()


@pytest.mark.parametrize("section", ["detect", "segment"])
def test_an_old_lesion_key_names_its_new_place(section):
    with pytest.raises(
        ConfigError,
        match=rf"{section}\.lesion_seed_sigmas moved to detect\.lesion"
        r"\.seed_sigmas",
    ):
        parse_config(f"{section}:\n  lesion_seed_sigmas: 2.5\n", source="old.yaml")


@pytest.mark.parametrize(
    ("section", "old", "new"),
    [
        ("detect.lesion", "smoothing_px", "smoothing_mm"),
        ("detect.lesion", "min_region_pixels", "min_region_mm2"),
        ("detect.lesion", "boundary_rings", "boundary_mm"),
        ("detect", "lesion_min_slice_pixels", "lesion_min_slice_mm2"),
    ],
)
def test_a_pixel_key_names_its_key_in_mm(section, old, new):
    # the lesion model's lengths became mm: a configuration written before says which key
    # replaced its pixel count, instead of "extra inputs are not permitted"
    outer, _, inner = section.partition(".")
    text = f"{outer}:\n  {inner}:\n    {old}: 3\n" if inner else f"{outer}:\n  {old}: 3\n"
    with pytest.raises(ConfigError, match=rf"{section}\.{old} is now {section}\.{new}: .* mm"):
        parse_config(text, source="old.yaml")


@pytest.mark.parametrize("old", ["smoothing_px", "min_region_pixels", "boundary_rings"])
def test_a_pixel_key_of_the_old_layout_names_its_place_and_its_key_in_mm(old):
    # detect.lesion_<key> of the layout before detect.lesion, with a key now in mm
    new = {"smoothing_px": "smoothing_mm", "min_region_pixels": "min_region_mm2"}.get(
        old, "boundary_mm"
    )
    with pytest.raises(ConfigError, match=rf"detect\.lesion_{old} moved to detect\.lesion\.{new}"):
        parse_config(f"detect:\n  lesion_{old}: 3\n", source="old.yaml")

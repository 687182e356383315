"""Validated configuration of every pipeline stage.

One frozen pydantic model per stage; :class:`PipelineConfig` groups them.
Unknown keys and out-of-range values are errors that name the key
(``extra="forbid"`` and ``Field`` bounds). Each stage's core function takes
keyword-only parameters with the same names as its model's fields, so a
task calls ``core_function(data, **config.model_dump())``.

The defaults are the recommended choices of ``ALGORITHMS.md`` ([A1]-[A29]);
``configs/paper.yaml`` spells out the paper's own settings.
"""

from __future__ import annotations

import json
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from tumor3d.errors import ConfigError

__all__ = [
    "DetectConfig",
    "InterpolateConfig",
    "PipelineConfig",
    "PreprocessConfig",
    "RenderConfig",
    "SegmentConfig",
    "SimplifyConfig",
    "SurfaceConfig",
    "canonical_json",
    "parse_config",
]


class _StageConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class PreprocessConfig(_StageConfig):
    """Preprocessing (spec section 1).

    ``sharpen`` and ``equalize`` default to False, a measured deviation from
    the paper's chain (see ``tumor3d.preprocess.preprocess_volume``):
    per-slice histogram equalisation flattens the histogram whose modes
    section 2 counts, and the unsharp kernel adds noise/edge modes. Set
    both to True for the paper's literal chain.
    """

    window_percentiles: tuple[float, float] = Field(
        (0.5, 99.5),
        description="Percentiles of the foreground intensities mapped to 0 and 255 "
        "when the float volume is converted to 8-bit slices (one window per volume).",
    )
    median_size: int = Field(3, ge=1, le=9, description="Median filter size (odd), [P] 3x3.")
    sharpen: bool = Field(
        False, description="Apply fspecial('unsharp') (paper step 2); off: it adds histogram modes."
    )
    unsharp_alpha: float = Field(0.2, ge=0.0, le=1.0, description="[A1] fspecial('unsharp') alpha.")
    equalize: bool = Field(
        False,
        description="Per-slice histogram equalisation (paper step 3); off: it flattens "
        "the histogram that section 2 counts modes on.",
    )
    equalize_levels: int = Field(
        256, ge=2, le=256, description="[A2] histogram equalisation levels."
    )
    skull_threshold: Literal["multiotsu", "otsu"] = Field(
        "multiotsu",
        description="[A3] binarisation: lower 3-class Otsu threshold (tissue vs air/bone, "
        "robust on T2) or the 2-class Otsu threshold.",
    )
    skull_opening_radius: int = Field(2, ge=0, le=10, description="[A3] disk radius, pixels.")

    @model_validator(mode="after")
    def _check(self) -> PreprocessConfig:
        lo, hi = self.window_percentiles
        if not (0.0 <= lo < hi <= 100.0):
            raise ValueError("window_percentiles must satisfy 0 <= low < high <= 100")
        if self.median_size % 2 == 0:
            raise ValueError("median_size must be odd")
        return self


class DetectConfig(_StageConfig):
    """Abnormal-slice detection by histogram mode counting (spec section 2, [A5], [A6]).

    ``min_valley_significance`` (not in the spec) also merges two modes when
    the valley between them is not significantly below the lower peak
    (in units of the Poisson noise of the smoothed counts). Without it,
    noise bumps in sparse histogram tails give normal real slices up to 9
    modes, violating [A5] step 6 (every normal slice k <= 3).
    """

    n_bins: int = Field(64, ge=8, le=256)
    smoothing_sigma_bins: float = Field(1.0, ge=0.0, le=10.0)
    min_mode_area: float = Field(0.005, ge=0.0, lt=0.5, description="Fraction of brain pixels.")
    min_peak_distance_bins: int = Field(3, ge=0, le=64)
    min_valley_significance: float = Field(
        3.0,
        ge=0.0,
        le=50.0,
        description="Merge modes whose valley is less than this many noise standard deviations "
        "below the lower peak; 0 disables the test.",
    )
    abnormal_min_modes: int = Field(4, ge=2, le=10, description="[A6] abnormal iff k >= this.")
    min_brain_pixels: int = Field(
        500, ge=0, description="Slices with fewer brain pixels are never abnormal."
    )


class SegmentConfig(_StageConfig):
    """Wavelet + histogram fuzzy c-means segmentation (spec section 3, [A7], [A8])."""

    wavelet: Literal["haar"] = "haar"
    fuzziness: float = Field(2.0, gt=1.0, le=5.0, description="FCM exponent m.")
    tol: float = Field(1e-3, gt=0.0, le=1.0, description="Stop when max |dv| < tol.")
    max_num_iter: int = Field(100, ge=1, le=10000)
    min_tumor_pixels: int = Field(
        20, ge=1, description="A tumour component smaller than this on a slice is dropped."
    )
    keep_largest_3d_component: bool = Field(
        True,
        description="Keep only the largest group of slice masks linked across slices "
        "(a single tumour); drops isolated partial-volume false positives.",
    )
    component_tolerance_px: int = Field(
        3, ge=0, le=50, description="In-plane tolerance (pixels) for linking masks across slices."
    )
    rim_px: int = Field(
        3,
        ge=0,
        le=50,
        description="Tumour components are seeded at least this far inside the "
        "brain mask (pixels); 0 = literal largest component.",
    )
    max_brain_fraction: float = Field(
        0.5,
        gt=0.0,
        le=1.0,
        description="A tumour covering more of a slice's brain is "
        "partial volume of the brain surface; 1 disables the check.",
    )
    refine_boundary: bool = Field(
        True,
        description="Re-decide the tumour's boundary pixels by partial volume "
        "(tumour fraction > 1/2) instead of by cluster label.",
    )
    min_tumor_slices: int = Field(
        2,
        ge=1,
        le=100,
        description="With keep_largest_3d_component: the kept tumour must span "
        "at least this many acquired slices (drops isolated partial-volume slices).",
    )


class InterpolateConfig(_StageConfig):
    """Inter-slice interpolation (spec section 4, [A9]-[A14]).

    The defaults (``shape-edt``, ``parts: matched``, ``end_caps: taper``) are
    the combination that measured best on real expert labels
    (``reports/interpolation.md``); ``configs/paper.yaml`` holds Algorithm 1
    literally (``enhanced``, ``whole``, ``none``).
    """

    method: Literal["enhanced", "enhanced-edt", "shape", "shape-edt", "linear"] = Field(
        "shape-edt",
        description="enhanced = SE, chamfer + centroid alignment (Algorithm 1); enhanced-edt = "
        "SE with the exact Euclidean distance in mm; shape = original shape-based (SO, "
        "city-block, no alignment); shape-edt = shape-based with the exact Euclidean distance; "
        "linear = linear interpolation of the masks (LG mask variant).",
    )
    slices_between: int | None = Field(
        None, ge=0, le=50, description="[A10] inserted slices per gap; None = round(dz/dxy) - 1."
    )
    end_caps: Literal["none", "taper"] = Field(
        "taper",
        description="Beyond the first and last tumour slices: none = flat caps (the paper); "
        "taper = the end shape eroded linearly to nothing at the next acquired slice "
        "(unbiased for smooth objects; see tumor3d.interpolate).",
    )
    parts: Literal["matched", "whole"] = Field(
        "matched",
        description="matched = split each slice into 8-connected parts, match them by overlap "
        "and interpolate each group on its own (unmatched parts shrink to nothing); "
        "whole = whole slices, one centroid per slice (the paper).",
    )


class SurfaceConfig(_StageConfig):
    """Marching cubes (spec section 5, [A15], [A16])."""

    level: float = Field(0.5, gt=0.0, lt=1.0)
    padding: int = Field(1, ge=1, le=5, description="[A15] zero padding in voxels.")


class SimplifyConfig(_StageConfig):
    """Mesh simplification (spec section 6)."""

    method: Literal["qem"] = Field("qem", description="qem = quadric error metric (QSlim).")
    reduction_percent: float = Field(
        60.0, ge=0.0, lt=100.0, description="P of Algorithm 2: F_target = floor(F0 (1 - P/100))."
    )


class RenderConfig(_StageConfig):
    """Offscreen rendering (spec section 7, [A25])."""

    width: int = Field(640, ge=64, le=4096)
    height: int = Field(480, ge=64, le=4096)
    azimuths_deg: tuple[float, ...] = Field((0.0, 90.0, 180.0, 270.0), min_length=1, max_length=36)
    elevation_deg: float = Field(20.0, ge=-89.0, le=89.0)
    field_of_view_deg: float = Field(40.0, gt=1.0, lt=120.0)
    color_rgb: tuple[float, float, float] = (0.85, 0.35, 0.3)
    background_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @model_validator(mode="after")
    def _check(self) -> RenderConfig:
        for name in ("color_rgb", "background_rgb"):
            if not all(0.0 <= c <= 1.0 for c in getattr(self, name)):
                raise ValueError(f"{name} components must lie in [0, 1]")
        return self


class PipelineConfig(_StageConfig):
    """Configuration of the whole single-patient pipeline."""

    preprocess: PreprocessConfig = PreprocessConfig()
    detect: DetectConfig = DetectConfig()
    segment: SegmentConfig = SegmentConfig()
    interpolate: InterpolateConfig = InterpolateConfig()
    surface: SurfaceConfig = SurfaceConfig()
    simplify: SimplifyConfig = SimplifyConfig()
    render: RenderConfig = RenderConfig()


def _format_validation_error(err: ValidationError, source: str) -> str:
    lines = []
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"]) or "<root>"
        if e["type"] == "extra_forbidden":
            lines.append(f"unknown key '{key}'")
        else:
            got = e.get("input")
            shown = "" if isinstance(got, dict) else f" (got {got!r})"
            lines.append(f"key '{key}': {e['msg']}{shown}")
    return f"invalid configuration in {source}: " + "; ".join(lines)


def parse_config(data: Any, *, source: str = "<config>") -> PipelineConfig:
    """Validate a mapping (or YAML text) into a :class:`PipelineConfig`.

    Parameters
    ----------
    data : mapping, str or None
        The configuration as a nested mapping, or YAML text. ``None`` or an
        empty document gives the defaults.
    source : str
        Where the data came from, for error messages (usually a file name).

    Returns
    -------
    PipelineConfig

    Raises
    ------
    ConfigError
        On YAML syntax errors, unknown keys or out-of-range values; the
        message names the source and each offending key.

    Examples
    --------
    >>> parse_config({"simplify": {"reduction_percent": 40}}).simplify.reduction_percent
    40.0
    """
    if isinstance(data, str):
        try:
            data = yaml.safe_load(data)
        except yaml.YAMLError as exc:
            raise ConfigError(f"not valid YAML: {exc}", path=source) from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError("the configuration must be a mapping of stage names", path=source)
    try:
        return PipelineConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(exc, source)) from None


def canonical_json(model: BaseModel | dict[str, Any]) -> str:
    """Canonical JSON of a config (sorted keys, no whitespace): the cache-key form."""
    data = model.model_dump(mode="json") if isinstance(model, BaseModel) else model
    return json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)

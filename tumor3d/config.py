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
import os
from types import UnionType
from typing import Any, ClassVar, Literal, Union, get_args, get_origin

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from tumor3d.errors import ConfigError, InputError
from tumor3d.safe_yaml import load_yaml, yaml_reads_as_text
from tumor3d.validation import short_repr

__all__ = [
    "DetectConfig",
    "InterpolateConfig",
    "LesionConfig",
    "PipelineConfig",
    "PreprocessConfig",
    "RenderConfig",
    "SegmentConfig",
    "SimplifyConfig",
    "SurfaceConfig",
    "as_config",
    "canonical_json",
    "load_yaml",
    "parse_config",
]


class _StageConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    @field_validator("*", mode="before")
    @classmethod
    def _numbers_are_numbers(cls, value: Any, info: ValidationInfo) -> Any:
        """A number's key takes a number: ``true`` or ``"3"`` is refused, not coerced to 1 or 3."""
        field = cls.model_fields.get(info.field_name or "")
        if field is not None and isinstance(value, bool | str) and _is_number(field.annotation):
            if isinstance(value, str) and yaml_reads_as_text(value):
                raise ValueError(
                    f"must be a number, not text: YAML reads {value} as text (write it with a "
                    "point and a signed exponent, as 1.0e+1, or in full)"
                )
            kind = "true/false" if isinstance(value, bool) else "text (quoted)"
            raise ValueError(f"must be a number, not {kind}")
        return value


def _is_number(annotation: Any) -> bool:
    """True for ``int``, ``float`` and their optional forms (``float | None``)."""
    if annotation in (int, float):
        return True
    args = [a for a in get_args(annotation) if a is not type(None)]
    return (
        bool(args)
        and get_origin(annotation) in (Union, UnionType)
        and all(a in (int, float) for a in args)
    )


class PreprocessConfig(_StageConfig):
    """Preprocessing (spec section 1).

    ``sharpen`` and ``equalize`` default to False, a measured deviation from
    the paper's chain (see ``tumor3d.imaging.preprocess.preprocess_volume``):
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
    brain_extraction: Literal["auto", "skull_strip", "foreground", "head"] = Field(
        "auto",
        description="skull_strip = [A3] skull removal; foreground = the volume is already "
        "skull-stripped (voxels above its constant minimum, whole brain kept); head = 3-D "
        "brain extraction in mm for a raw clinical head whose scalp the per-slice skull "
        "removal keeps (tumor3d.imaging.brain_extraction); auto = foreground when >= "
        "masked_background_fraction of the voxels equal the minimum, else skull_strip.",
    )
    masked_background_fraction: float = Field(
        0.3,
        gt=0.0,
        le=1.0,
        description="auto rule: share of voxels at exactly the minimum that marks a "
        "masked (skull-stripped) background; raw MR air is noisy, never one value.",
    )

    @model_validator(mode="after")
    def _check(self) -> PreprocessConfig:
        lo, hi = self.window_percentiles
        if not (0.0 <= lo < hi <= 100.0):
            raise ValueError("window_percentiles must satisfy 0 <= low < high <= 100")
        if self.median_size % 2 == 0:
            raise ValueError("median_size must be odd")
        return self


class LesionConfig(_StageConfig):
    """The patient lesion model of the robust method (:mod:`tumor3d.segmentation.lesion`).

    One section, ``detect.lesion``: the detect stage computes the model once
    (its slices flag the abnormal slices) and the segment stage reuses its
    mask. The fields are the keywords of
    :func:`tumor3d.segmentation.lesion.segment_hyperintense_lesion`.
    """

    smoothing_mm: float = Field(
        2.0,
        ge=0.0,
        le=20.0,
        description="In-plane Gaussian sigma (mm) of the spatial regularisation "
        "before the patient-pooled normal-tissue model.",
    )
    seed_sigmas: float = Field(
        2.0,
        gt=0.0,
        le=10.0,
        description="Lesion seeds lie this many robust SDs (1.4826 MAD) above the "
        "median of the smoothed brain (chosen by leave-one-case-out).",
    )
    min_region_mm2: float = Field(
        50.0,
        gt=0.0,
        description="Smallest significant lesion cross-section on a slice, mm2 (on pixels "
        "coarser than 1 mm: this many pixels).",
    )
    min_slices: int = Field(
        2,
        ge=1,
        le=100,
        description="Consecutive slices on which a lesion must reach that cross-section.",
    )
    keep_largest: bool = Field(True, description="Keep only the largest lesion (one tumour).")
    refine_boundary: bool = Field(
        True, description="Partial-volume boundary (lesion fraction > 1/2) at the border."
    )
    fill_core: bool = Field(
        True, description="Fill the enclosed (necrotic) core and cavities at the rim."
    )
    boundary_mm: float = Field(
        3.0,
        ge=0.0,
        le=20.0,
        description="Width (mm) of the partial-volume growth against the local lesion "
        "gray, grown one pixel ring at a time; 0 disables it.",
    )
    floor_sigmas: float = Field(
        1.0,
        ge=0.0,
        le=10.0,
        description="That growth never goes below median + this many robust SDs "
        "(chosen by leave-one-case-out).",
    )

    @model_validator(mode="before")
    @classmethod
    def _pixel_keys(cls, data: Any) -> Any:
        return _refuse_pixel_keys("detect.lesion", data)


#: Keys in pixels that became lengths and areas in mm (old key -> new key); the robust
#: model's constants were chosen on 1 mm pixels, where the numbers are the same.
_PIXEL_KEYS = {
    "smoothing_px": "smoothing_mm",
    "min_region_pixels": "min_region_mm2",
    "boundary_rings": "boundary_mm",
    "lesion_min_slice_pixels": "lesion_min_slice_mm2",
}


def _refuse_renamed_keys(data: Any, renamed: dict[str, str], message) -> Any:
    """``data`` unchanged, or ValueError(``message(key, new)``) for its first renamed key."""
    if isinstance(data, dict):
        for key in data:
            if key in renamed:
                raise ValueError(message(key, renamed[key]))
    return data


def _refuse_pixel_keys(section: str, data: Any) -> Any:
    return _refuse_renamed_keys(
        data,
        _PIXEL_KEYS,
        lambda key, new: (
            f"{section}.{key} is now {section}.{new}: the robust model's "
            "lengths and areas are in mm and mm2, converted to pixels through the "
            "scan's pixel spacing (the same number at 1 mm pixels)"
        ),
    )


#: Keys of the lesion model that lived in ``detect`` and ``segment`` before
#: ``detect.lesion`` (old name -> field of :class:`LesionConfig`; those that were pixel
#: counts then name their field in mm).
_MOVED_LESION_KEYS = {
    **{f"lesion_{name}": name for name in LesionConfig.model_fields},
    **{
        f"lesion_{old}": new for old, new in _PIXEL_KEYS.items() if new in LesionConfig.model_fields
    },
}


def _refuse_moved_lesion_keys(section: str, data: Any) -> Any:
    return _refuse_renamed_keys(
        data,
        _MOVED_LESION_KEYS,
        lambda key, new: (
            f"{section}.{key} moved to detect.lesion.{new} "
            "(one lesion model, computed by the detect stage and reused by segment)"
        ),
    )


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
    method: Literal["auto", "robust", "histogram"] = Field(
        "auto",
        description="robust = slices holding a patient-level lesion (tumor3d.segmentation.lesion); "
        "histogram = the paper's mode count ([A5], [A6]); auto = robust on FLAIR/T1c, "
        "on T2 histogram where >= 95 % of the slices show 3 modes (the paper's premise) "
        "and robust otherwise, histogram without modality.",
    )
    lesion: LesionConfig = Field(
        default_factory=lambda: LesionConfig(),
        description="robust: the patient lesion model (tumor3d.segmentation.lesion), computed once "
        "by the "
        "detect stage and reused by the segment stage.",
    )
    lesion_min_slice_mm2: float = Field(
        20.0,
        gt=0.0,
        description="robust: a slice holding this much lesion (mm2; on pixels coarser than "
        "1 mm: this many pixels) is abnormal.",
    )

    @model_validator(mode="before")
    @classmethod
    def _moved_keys(cls, data: Any) -> Any:
        return _refuse_pixel_keys("detect", _refuse_moved_lesion_keys("detect", data))


class SegmentConfig(_StageConfig):
    """Tumour segmentation (spec section 3): robust default, the paper's method, a peer.

    The robust method's lesion model is configured in ``detect.lesion``
    (:class:`LesionConfig`): the detect stage computes it once and this stage
    keeps its mask on the abnormal slices. ``keep_largest_3d_component``,
    ``refine_boundary`` and ``min_tumor_slices`` here are the paper method's
    (the lesion model has its own ``keep_largest`` and ``refine_boundary``);
    ``min_tumor_pixels`` applies to every method.
    """

    method: str = Field(
        "auto",
        description="The segmentation method: a registered one "
        "(tumor3d.segmentation.methods; `tumor3d methods` lists them), or auto = the "
        "learned method on FLAIR/T1c; on T2 paper where >= 95 % of the slices show 3 "
        "histogram modes (the paper's premise), robust otherwise.",
        json_schema_extra=lambda schema: _method_schema(schema),
    )
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
    multiotsu_classes: int = Field(4, ge=2, le=6, description="multiotsu peer: classes.")
    learned_cnn: Literal["auto", "off"] = Field(
        "auto",
        description="learned method: auto = the probability is the mean of the forest's and "
        "the shipped 2-D U-Net ensemble's (two seeds, averaged) where one is shipped for the "
        "sequence (FLAIR; trained on FLAIR only: T2 and T1c keep the forest alone), before the "
        "same cut and main region (reports/learned_cv.md); off = the forest alone.",
    )
    #: The models folder keys the segment stage through its stored files (their bytes and
    #: the folder: ``given:models``), only where a run uses them (tumor3d.tasks.stages).
    __cache_exclude__: ClassVar[frozenset[str]] = frozenset({"learned_models"})

    learned_models: str | None = Field(
        None,
        min_length=1,
        description="learned method: a folder `tumor3d train --out DIR` wrote, whose models "
        "replace the shipped ones (hyper.npz: FLAIR and T2, t1c.npz: T1c; its FLAIR U-Nets "
        "unet_flair_seed<k>.npz, or none: the forest alone); their bytes enter the segment "
        "stage's cache key and provenance.json. Relative: from the working directory. Unset: "
        "the shipped models.",
    )

    @field_validator("method")
    @classmethod
    def _registered_method(cls, value: str) -> str:
        """``auto`` or a method of the registry; the error lists the registered ones."""
        from tumor3d.segmentation.methods import check_method_name

        try:
            return check_method_name(value)
        except InputError as exc:
            raise ValueError(exc.problem) from None

    @model_validator(mode="before")
    @classmethod
    def _moved_keys(cls, data: Any) -> Any:
        return _refuse_moved_lesion_keys("segment", data)


def _method_schema(schema: dict[str, Any]) -> None:
    """JSON schema of ``segment.method``: the registered methods as its ``enum``, described."""
    from tumor3d.segmentation.methods import method_names, registered_methods

    schema["enum"] = list(method_names())
    listed = "; ".join(f"{m.name} = {m.description}" for m in registered_methods().values())
    schema["description"] = f"{schema.get('description', '')} Registered: {listed}."


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
        "(unbiased for smooth objects; see tumor3d.geometry.interpolate).",
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

    method: Literal["curvature", "memoryless", "qem"] = Field(
        "memoryless",
        description="curvature = the paper's Algorithm 2; memoryless = Lindstrom-Turk "
        "(default: keeps the enclosed volume exactly and the surface closed, and has the "
        "smallest surface error at P >= 60 %, reports/simplification.md); "
        "qem = quadric error metric (QSlim, fast-simplification; may break manifoldness).",
    )
    reduction_percent: float = Field(
        60.0, ge=0.0, lt=100.0, description="P of Algorithm 2: F_target = floor(F0 (1 - P/100))."
    )
    curvedness: Literal["sqrt", "no_root"] = Field(
        "sqrt",
        description="[A17] R = sqrt(max(0, 2H^2 - K)) (Koenderink curvedness) or its square; "
        "used by method=curvature only.",
    )
    ring_update: Literal["lazy", "eager"] = Field(
        "lazy",
        description="Algorithm 2 step 6 for a neighbour already in the candidate set: lazy = "
        "its R is recomputed when it reaches the top of the heap (re-keyed or dropped then); "
        "eager = at once, the paper's order. Lazy is 1.56x fast-simplification against 1.74x "
        "and has lower errors (reports/benchmarks.md); used by method=curvature only.",
    )


class RenderConfig(_StageConfig):
    """Rendering of the tumour inside the brain (spec section 7, [A25]).

    The fields are the keywords of :func:`tumor3d.visual.render.render_views`.
    ``renderer`` defaults to the numba z-buffer renderer: on this project's
    reference machine (llvmpipe, no GPU) it renders 8 views of a
    100,000-face tumour with a 170,000-face brain ~70x faster than Open3D's
    Filament (1.7 s against 123 s, ``benchmarks/bench_render.py``); ``auto`` uses Open3D and
    falls back to numpy, ``open3d`` insists on Open3D.
    """

    width: int = Field(640, ge=64, le=4096)
    height: int = Field(480, ge=64, le=4096)
    views: tuple[Literal["anterior", "posterior", "right", "left", "superior", "inferior"], ...] = (
        "anterior",
        "posterior",
        "right",
        "left",
        "superior",
        "inferior",
    )
    cutaways: tuple[Literal["axial", "coronal", "sagittal"], ...] = ("axial", "coronal")
    turntable_frames: int = Field(24, ge=0, le=360)
    turntable_elevation_deg: float = Field(20.0, ge=-89.0, le=89.0)
    color_rgb: tuple[float, float, float] = (0.85, 0.35, 0.3)
    brain_color_rgb: tuple[float, float, float] = (0.78, 0.78, 0.82)
    brain_opacity: float = Field(0.25, gt=0.0, le=1.0)
    background_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ambient: float = Field(0.15, ge=0.0, le=1.0)
    diffuse: float = Field(0.7, ge=0.0, le=1.0)
    specular: float = Field(0.3, ge=0.0, le=1.0)
    shininess: float = Field(32.0, ge=1.0, le=1000.0)
    annotate: bool = True
    renderer: Literal["numpy", "auto", "open3d"] = "numpy"

    @model_validator(mode="after")
    def _check(self) -> RenderConfig:
        for name in ("color_rgb", "brain_color_rgb", "background_rgb"):
            if not all(0.0 <= c <= 1.0 for c in getattr(self, name)):
                raise ValueError(f"{name} components must lie in [0, 1]")
        if len(set(self.views)) != len(self.views):
            raise ValueError("views lists a view twice")
        if len(set(self.cutaways)) != len(self.cutaways):
            raise ValueError("cutaways lists a plane twice")
        if not self.views and not self.cutaways and self.turntable_frames == 0:
            raise ValueError("nothing to render: views, cutaways and turntable_frames are empty")
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


_MAX_LISTED_ERRORS = 5


def _format_validation_error(err: ValidationError, source: str) -> str:
    """One line naming each offending key (at most 5, then a count); values cut short."""
    lines = []
    errors = err.errors()
    for e in errors[:_MAX_LISTED_ERRORS]:
        key = ".".join(str(p) for p in e["loc"]) or "<root>"
        if e["type"] == "extra_forbidden":
            lines.append(f"unknown key '{key}'")
        else:
            got = e.get("input")
            shown = "" if isinstance(got, dict) else f" (got {short_repr(got)})"
            lines.append(f"key '{key}': {e['msg']}{shown}")
    if len(errors) > _MAX_LISTED_ERRORS:
        lines.append(f"and {len(errors) - _MAX_LISTED_ERRORS} more problem(s)")
    return f"invalid configuration in {source}: " + "; ".join(lines)


def parse_config(data: Any, *, source: str = "<config>") -> PipelineConfig:
    """Validate a mapping (or YAML text) into a :class:`PipelineConfig`.

    Parameters
    ----------
    data : mapping, str or None
        The configuration as a nested mapping, or YAML text (parsed by
        :func:`load_yaml`: alias bombs and oversized documents refused).
        ``None`` or an empty document gives the defaults.
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
    text = data if isinstance(data, str) else None
    if text is not None:
        data = load_yaml(text, source=source)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        hint = ""
        if (
            text is not None
            and "\n" not in text.strip()
            and text.strip().endswith((".yaml", ".yml"))
        ):
            hint = f" (got the text {text.strip()!r}: a file's name? pass the file's text)"
        raise ConfigError(f"the configuration must be a mapping of stage names{hint}", path=source)
    try:
        return PipelineConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(exc, source)) from None


def as_config(config: Any, *, source: str = "config") -> PipelineConfig:
    """A Python caller's ``config=``: a :class:`PipelineConfig`, a mapping, YAML text or None.

    The one rule of every Python entry point (``tumor3d.reconstruct``, ``run_patient``,
    ``run_cohort``), as ``--config`` reads a file's text.

    >>> as_config(None) == as_config({}) == as_config(PipelineConfig())
    True
    >>> as_config("simplify: {reduction_percent: 40}").simplify.reduction_percent
    40.0
    """
    if isinstance(config, PipelineConfig):
        return config
    if config is None or isinstance(config, str | dict):
        return parse_config(config, source=source)
    from collections.abc import Mapping

    if isinstance(config, Mapping):
        return parse_config(dict(config), source=source)
    raise ConfigError(
        f"must be a PipelineConfig, a dict or YAML text, got {type(config).__name__}"
        + (" (a file's path? pass the file's text)" if isinstance(config, os.PathLike) else ""),
        path=source,
    )


def canonical_json(model: BaseModel | dict[str, Any]) -> str:
    """Canonical JSON of a config (sorted keys, no whitespace): the cache-key form."""
    data = model.model_dump(mode="json") if isinstance(model, BaseModel) else model
    return json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)

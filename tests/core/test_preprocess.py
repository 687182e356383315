"""Tests of tumor3d.imaging.preprocess (specification section 1)."""

from __future__ import annotations

import numpy as np
import pytest
from simple_phantom import LABELS, make_head_phantom

from tumor3d.config import PreprocessConfig
from tumor3d.errors import InputError
from tumor3d.imaging.preprocess import (
    equalize_slices,
    preprocess_volume,
    remove_skull,
    to_uint8,
    unsharp_kernel,
)

DEFAULTS = PreprocessConfig().model_dump()


@pytest.fixture(scope="module")
def phantom():
    return make_head_phantom(tumor=True, seed=1)


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


# --------------------------------------------------------------------------- unsharp kernel


@pytest.mark.parametrize("alpha", [0.0, 0.2, 0.5, 1.0])
def test_unsharp_kernel_is_matlab_formula(alpha):
    # fspecial('unsharp', a) = 1/(a+1) [[-a, a-1, -a], [a-1, a+5, a-1], [-a, a-1, -a]]
    a = alpha
    expected = np.array([[-a, a - 1, -a], [a - 1, a + 5, a - 1], [-a, a - 1, -a]]) / (a + 1)
    np.testing.assert_allclose(unsharp_kernel(alpha), expected, rtol=0, atol=1e-15)
    assert unsharp_kernel(alpha).sum() == pytest.approx(1.0)


def test_unsharp_kernel_default_equals_matlab_printout():
    # values printed by MATLAB for fspecial('unsharp') (alpha = 0.2)
    matlab = np.array(
        [[-0.1667, -0.6667, -0.1667], [-0.6667, 4.3333, -0.6667], [-0.1667, -0.6667, -0.1667]]
    )
    np.testing.assert_allclose(unsharp_kernel(0.2), matlab, atol=5e-5)


def _naive_unsharp(img: np.ndarray, alpha: float) -> np.ndarray:
    """Explicit zero-padded 3x3 convolution, rounded half up and saturated to uint8."""
    h = unsharp_kernel(alpha)
    ny, nx = img.shape
    out = np.zeros((ny, nx), dtype=np.uint8)
    for y in range(ny):
        for x in range(nx):
            acc = 0.0
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    yy, xx = y - dy, x - dx  # convolution (h is symmetric anyway)
                    if 0 <= yy < ny and 0 <= xx < nx:
                        acc += h[dy + 1, dx + 1] * float(img[yy, xx])
            out[y, x] = int(np.floor(min(max(acc, 0.0), 255.0) + 0.5))
    return out


def test_sharpening_matches_naive_convolution():
    rng = np.random.default_rng(3)
    stack = rng.integers(0, 256, size=(2, 7, 9), dtype=np.uint8)
    everything = np.ones(stack.shape, dtype=bool)
    res = preprocess_volume(
        stack,
        **{**DEFAULTS, "median_size": 1, "sharpen": True, "unsharp_alpha": 0.3},
        brain_mask=everything,
    )
    for z in range(stack.shape[0]):
        np.testing.assert_array_equal(res.enhanced[z], _naive_unsharp(stack[z], 0.3))


def test_median_is_per_slice_with_zero_padding():
    rng = np.random.default_rng(4)
    stack = rng.integers(0, 256, size=(3, 6, 5), dtype=np.uint8)
    res = preprocess_volume(stack, **DEFAULTS, brain_mask=np.ones(stack.shape, dtype=bool))
    padded = np.pad(stack, ((0, 0), (1, 1), (1, 1)))
    for z in range(3):
        for y in range(6):
            for x in range(5):
                assert res.enhanced[z, y, x] == np.median(padded[z, y : y + 3, x : x + 3])


# --------------------------------------------------------------------------- equalisation


def test_equalization_maps_gray_levels_to_their_cumulative_frequency():
    rng = np.random.default_rng(5)
    sl = np.clip(rng.normal(90, 20, size=(1, 40, 50)), 0, 255).astype(np.uint8)
    out = equalize_slices(sl)
    g = sl.ravel()
    cdf = np.cumsum(np.bincount(g, minlength=256)) / g.size
    # T(g) = round(255 cdf(g)): each output level is within half a level of 255 cdf(g)
    assert np.all(np.abs(out.ravel().astype(float) - 255 * cdf[g]) <= 0.5 + 1e-9)
    # monotone: a brighter input is never darker in the output
    order = np.argsort(g, kind="stable")
    assert np.all(np.diff(out.ravel()[order].astype(int)) >= 0)


def test_equalization_with_64_levels_and_per_slice():
    rng = np.random.default_rng(6)
    stack = rng.integers(0, 256, size=(2, 30, 30), dtype=np.uint8)
    stack[1] //= 4  # a darker slice equalises to the same full range
    out = equalize_slices(stack, levels=64)
    assert np.unique(out).size <= 64
    assert out[0].max() == 255 and out[1].max() == 255


def test_equalize_option_changes_only_enhanced(phantom):
    plain = preprocess_volume(phantom.image, **DEFAULTS)
    eq = preprocess_volume(phantom.image, **{**DEFAULTS, "equalize": True})
    np.testing.assert_array_equal(plain.brain_mask, eq.brain_mask)
    np.testing.assert_array_equal(plain.original_u8, eq.original_u8)
    assert not np.array_equal(plain.enhanced, eq.enhanced)


# --------------------------------------------------------------------------- 8-bit window


def test_to_uint8_window_over_foreground_only():
    vol = np.full((1, 10, 10), -3.0)  # z-scored style constant background
    vol[0, :5, :] = np.linspace(1.0, 2.0, 50).reshape(5, 10)
    out = to_uint8(vol, window_percentiles=(0, 100))
    assert out.dtype == np.uint8
    assert np.all(out[0, 5:] == 0)  # background -> 0
    assert out[0, 0, 0] == 0 and out[0, 4, 9] == 255  # foreground min/max span 0..255
    np.testing.assert_array_equal(
        out[0, :5].ravel(), np.floor(np.linspace(0, 255, 50) + 0.5).astype(np.uint8)
    )


def test_to_uint8_clips_outside_the_window():
    vol = np.zeros((1, 1, 101))
    vol[0, 0, 1:] = np.arange(1, 101)
    out = to_uint8(vol, window_percentiles=(10, 90))
    lo, hi = np.percentile(np.arange(1, 101), [10, 90])
    assert out[0, 0, 1] == 0 and out[0, 0, 100] == 255
    assert out[0, 0, 50] == int(np.floor((50 - lo) / (hi - lo) * 255 + 0.5))


# --------------------------------------------------------------------------- skull removal


@pytest.mark.parametrize("threshold", ["multiotsu", "otsu"])
def test_brain_mask_matches_phantom_brain_and_excludes_scalp(phantom, threshold):
    res = preprocess_volume(phantom.image, **{**DEFAULTS, "skull_threshold": threshold})
    assert _dice(res.brain_mask, phantom.brain) > 0.95
    n_brain = phantom.brain.sum()
    assert not np.any(res.brain_mask & (phantom.labels == LABELS["scalp"]))
    # only partial-volume pixels at the inner skull border may be included
    assert np.count_nonzero(res.brain_mask & (phantom.labels == LABELS["skull"])) < 0.03 * n_brain
    assert np.count_nonzero(phantom.brain & ~res.brain_mask) < 0.01 * n_brain
    # every slice individually, too
    for z in range(phantom.image.shape[0]):
        assert _dice(res.brain_mask[z], phantom.brain[z]) > 0.9


def test_scalp_bridge_is_cut_by_the_opening():
    # disc (brain) joined to a ring (scalp) by a 2-pixel bridge
    yy, xx = np.mgrid[0:80, 0:80]
    r = np.hypot(yy - 40, xx - 40)
    img = np.zeros((1, 80, 80), dtype=np.uint8)
    img[0][r < 25] = 150
    img[0][(r > 30) & (r < 36)] = 200
    img[0, 39:41, 60:72] = 180  # bridge through the dark gap
    mask = remove_skull(img, opening_radius=2)[0]
    assert not mask[(r > 30) & (r < 36)].any()
    assert mask[r < 23].all()
    without = remove_skull(img, opening_radius=0)[0]
    assert without[(r > 30) & (r < 36)].all()  # the bridge joins them without the opening


def test_background_only_slices_get_empty_mask(phantom):
    vol = np.concatenate([np.zeros((1,) + phantom.image.shape[1:]), phantom.image])
    res = preprocess_volume(vol, **DEFAULTS)
    assert not res.brain_mask[0].any()
    assert not res.enhanced[0].any()
    assert res.brain_mask[1:].any(axis=(1, 2)).all()


def test_given_brain_mask_replaces_skull_removal(phantom):
    res = preprocess_volume(phantom.image, **DEFAULTS, brain_mask=phantom.brain)
    np.testing.assert_array_equal(res.brain_mask, phantom.brain)
    assert not res.enhanced[~phantom.brain].any()


# --------------------------------------------------------------------------- invariants


def test_result_types_and_inputs_unchanged(phantom):
    image = phantom.image.copy()
    res = preprocess_volume(image, **{**DEFAULTS, "sharpen": True, "equalize": True})
    np.testing.assert_array_equal(image, phantom.image)
    assert res.original_u8.dtype == np.uint8 and res.enhanced.dtype == np.uint8
    assert res.brain_mask.dtype == bool
    assert res.original_u8.shape == res.enhanced.shape == res.brain_mask.shape == image.shape
    np.testing.assert_array_equal(res.original_u8, to_uint8(image))

    u8 = res.original_u8.copy()
    mask = phantom.brain.copy()
    again = preprocess_volume(u8, **DEFAULTS, brain_mask=mask)
    np.testing.assert_array_equal(u8, res.original_u8)
    np.testing.assert_array_equal(mask, phantom.brain)
    np.testing.assert_array_equal(again.original_u8, u8)  # uint8 input is used as it is


# --------------------------------------------------------------------------- validation


def test_rejects_wrong_ndim():
    with pytest.raises(InputError, match="3-D"):
        preprocess_volume(np.zeros((5, 5)), **DEFAULTS)


def test_rejects_nan():
    vol = np.ones((2, 4, 4))
    vol[1, 2, 2] = np.nan
    with pytest.raises(InputError, match="NaN"):
        preprocess_volume(vol, **DEFAULTS)


def test_rejects_non_real_dtype():
    with pytest.raises(InputError, match="real numbers"):
        to_uint8(np.ones((2, 3, 3), dtype=complex))


def test_rejects_constant_float_volume():
    with pytest.raises(InputError, match="constant"):
        to_uint8(np.full((2, 4, 4), 7.0))


def test_rejects_constant_uint8_volume():
    with pytest.raises(InputError, match="constant"):
        preprocess_volume(np.full((2, 4, 4), 9, dtype=np.uint8), **DEFAULTS)


def test_rejects_mask_shape_mismatch(phantom):
    with pytest.raises(InputError, match="brain_mask shape"):
        preprocess_volume(phantom.image, **DEFAULTS, brain_mask=phantom.brain[:, :-1])


def test_rejects_bad_percentiles():
    with pytest.raises(InputError, match="window_percentiles"):
        to_uint8(np.arange(8.0).reshape(2, 2, 2), window_percentiles=(60, 40))


def test_rejects_even_median_size(phantom):
    with pytest.raises(InputError, match="median_size"):
        preprocess_volume(phantom.image, **{**DEFAULTS, "median_size": 4})


def test_rejects_unknown_skull_threshold(phantom):
    with pytest.raises(InputError, match="skull_threshold"):
        preprocess_volume(phantom.image, **{**DEFAULTS, "skull_threshold": "triangle"})


def test_rejects_bad_alpha(phantom):
    with pytest.raises(InputError, match="unsharp_alpha"):
        preprocess_volume(phantom.image, **{**DEFAULTS, "unsharp_alpha": 1.5})


def test_rejects_bad_equalize_levels(phantom):
    with pytest.raises(InputError, match="equalize_levels"):
        preprocess_volume(phantom.image, **{**DEFAULTS, "equalize_levels": 1})


# --------------------------------------------------------------------------- skull-stripped input


def test_zscored_skull_stripped_volume_keeps_the_whole_brain():
    # BraTS-like: z-scored intensities, the masked background a negative constant
    rng = np.random.default_rng(1)
    nz, n = 5, 64
    yy, xx = np.mgrid[:n, :n]
    brain2d = (yy - 32) ** 2 + (xx - 32) ** 2 < 25**2
    tissue = np.clip(rng.normal(0.0, 1.0, (nz, n, n)), -3.0, None)
    vol = np.where(brain2d, tissue, -3.16).astype(np.float32)
    vol[0, 32, 32] = 1e4  # one extreme outlier voxel
    from tumor3d.imaging.preprocess import preprocess_volume

    res = preprocess_volume(vol)  # brain_extraction="auto" -> foreground
    expect = np.broadcast_to(brain2d, vol.shape)
    assert np.array_equal(res.brain_mask, expect)  # nothing eaten at the rim, speck dropped
    skull = preprocess_volume(vol, brain_extraction="skull_strip")
    assert skull.brain_mask.sum() < expect.sum()  # the paper's skull removal erodes the rim
    # the outlier does not set the window: the tissue median stays mid-range
    assert 110 < np.median(res.enhanced[res.brain_mask]) < 145


def _zscored_brain(background: float, seed: int = 1):
    """A z-scored skull-stripped volume (tissue mean 0, SD 1) and its brain."""
    rng = np.random.default_rng(seed)
    nz, n = 5, 64
    yy, xx = np.mgrid[:n, :n]
    brain2d = (yy - 32) ** 2 + (xx - 32) ** 2 < 25**2
    tissue = np.clip(rng.normal(0.0, 1.0, (nz, n, n)), -3.0, 3.0)
    vol = np.where(brain2d, tissue, background)
    return vol, np.broadcast_to(brain2d, vol.shape)


def test_a_resampled_skull_stripped_volume_keeps_its_brain():
    # a resampling (linear interpolation in float64) leaves the masked background equal
    # up to a few ulps: some of it just below the mask value, so that "exactly the
    # minimum" held 0.01 % of the voxels and the volume was taken for a raw head
    from tumor3d.imaging.preprocess import preprocess_volume

    exact, brain = _zscored_brain(-3.16)
    rng = np.random.default_rng(2)
    resampled = exact.copy()
    outside = ~brain & (rng.random(exact.shape) < 0.5)
    resampled[outside] = np.nextafter(-3.16, -np.inf)
    resampled[~brain & ~outside & (rng.random(exact.shape) < 0.01)] = np.nextafter(-3.16, 0.0)
    assert np.count_nonzero(resampled == resampled.min()) / resampled.size < 0.5  # premise
    ref = preprocess_volume(exact)
    got = preprocess_volume(resampled)
    assert ref.brain_extraction == got.brain_extraction == "foreground"
    assert np.array_equal(got.brain_mask, brain)
    assert np.array_equal(got.enhanced, ref.enhanced)


def test_a_zero_background_below_negative_tissue_is_the_background():
    # a brain z-scored to negative and positive values with the mask's 0 around it: the
    # background is the value the mask left (0), not the volume's minimum
    from tumor3d.imaging.preprocess import preprocess_volume

    vol, brain = _zscored_brain(0.0)
    assert vol.min() < 0.0
    res = preprocess_volume(vol)
    assert res.brain_extraction == "foreground"
    assert np.array_equal(res.brain_mask, brain)


def test_brain_extraction_rejects_unknown_mode():
    from tumor3d.imaging.preprocess import preprocess_volume

    with pytest.raises(InputError, match="brain_extraction"):
        preprocess_volume(np.arange(27.0).reshape(3, 3, 3), brain_extraction="bet")


def test_fill_holes_per_slice_matches_slice_by_slice_filling():
    from scipy import ndimage as ndi

    from tumor3d.imaging.preprocess import fill_holes_per_slice

    rng = np.random.default_rng(0)
    mask = rng.random((5, 40, 40)) > 0.6
    expect = np.stack([ndi.binary_fill_holes(m) for m in mask])
    assert np.array_equal(fill_holes_per_slice(mask), expect)


# --------------------------------------------------------------------------- fast paths vs naive


def _random_masks(rng, n):
    for _ in range(n):
        shape = (int(rng.integers(1, 5)), int(rng.integers(1, 25)), int(rng.integers(1, 25)))
        yield rng.random(shape) < rng.uniform(0.2, 0.9)


def test_fill_holes_per_slice_matches_scipy_per_slice_on_random_masks():
    from scipy import ndimage as ndi

    from tumor3d.imaging.preprocess import fill_holes_per_slice

    rng = np.random.default_rng(11)
    for mask in _random_masks(rng, 150):
        expect = np.stack([ndi.binary_fill_holes(m) for m in mask])
        assert np.array_equal(fill_holes_per_slice(mask), expect)
    # a box hole that touches nothing, and one that touches the border
    ring = np.zeros((2, 9, 9), dtype=bool)
    ring[:, 2:7, 2:7] = True
    ring[:, 4, 4] = False
    ring[1, 4, 2:] = False
    expect = np.stack([ndi.binary_fill_holes(m) for m in ring])
    assert np.array_equal(fill_holes_per_slice(ring), expect)
    assert not fill_holes_per_slice(np.zeros((3, 4, 4), dtype=bool)).any()


def test_median3_fast_path_matches_scipy_rank_filter():
    from scipy import ndimage as ndi

    from tumor3d.imaging.preprocess.filters import _median_stack

    rng = np.random.default_rng(12)
    for _ in range(150):
        shape = (int(rng.integers(1, 4)), int(rng.integers(1, 20)), int(rng.integers(1, 20)))
        levels = int(rng.choice([2, 3, 7, 256]))  # few levels: many ties
        stack = rng.integers(0, levels, size=shape).astype(np.uint8)
        stack[rng.random(shape) < 0.3] = 0
        expect = ndi.median_filter(stack, size=(1, 3, 3), mode="constant", cval=0)
        assert np.array_equal(_median_stack(stack, 3), expect)


def _naive_remove_skull(stack, radius, threshold):
    """The per-slice loop of [A3] as written in the specification (reference)."""
    from scipy import ndimage as ndi
    from skimage.morphology import disk

    from tumor3d.imaging.preprocess.skull import _skull_threshold

    footprint = disk(radius).astype(bool) if radius > 0 else None
    mask = np.zeros(stack.shape, dtype=bool)
    for z, sl in enumerate(stack):
        if sl.min() == sl.max():
            continue
        binary = sl > _skull_threshold(sl, threshold)
        if footprint is not None:
            binary = ndi.binary_erosion(binary, structure=footprint)
        labels, n = ndi.label(binary, structure=np.ones((3, 3), dtype=bool))
        if n == 0:
            continue
        sizes = np.bincount(labels.ravel())
        sizes[0] = 0
        brain = labels == int(np.argmax(sizes))
        if footprint is not None:
            brain = ndi.binary_dilation(brain, structure=footprint)
        mask[z] = ndi.binary_fill_holes(brain)
    return _naive_keep_nested(mask)


def _naive_keep_nested(mask):
    from scipy import ndimage as ndi
    from skimage.morphology import disk

    from tumor3d.imaging.preprocess.skull import _NESTING_MAX_OUTSIDE, _NESTING_TOLERANCE_PX

    areas = mask.sum(axis=(1, 2))
    if not areas.any():
        return mask
    footprint = disk(_NESTING_TOLERANCE_PX).astype(bool)

    def kept_by_walk(centre):
        keep = np.zeros(len(mask), dtype=bool)
        keep[centre] = True
        for step in (1, -1):
            z = centre + step
            while 0 <= z < len(mask):
                inner = ndi.binary_dilation(mask[z - step], structure=footprint)
                outside = np.count_nonzero(mask[z] & ~inner)
                if outside > _NESTING_MAX_OUTSIDE * max(1, np.count_nonzero(mask[z])):
                    break
                keep[z] = True
                z += step
        return keep

    keep = kept_by_walk(int(np.argmax(areas)))
    with_mask = areas > 0
    n_kept = np.count_nonzero(keep & with_mask)
    if np.count_nonzero(with_mask & ~keep) > n_kept:  # the widest slice was no brain's
        again = kept_by_walk(int(np.argmax(np.where(with_mask & ~keep, areas, -1))))
        if np.count_nonzero(again & with_mask) > n_kept:
            keep = again
    out = mask.copy()
    out[~keep] = False
    return out


def test_remove_skull_matches_per_slice_reference_on_random_stacks():
    from scipy import ndimage as ndi

    rng = np.random.default_rng(13)
    for _ in range(40):
        shape = (int(rng.integers(1, 6)), int(rng.integers(3, 30)), int(rng.integers(3, 30)))
        sigma = (0, rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0))
        smooth = ndi.gaussian_filter(rng.random(shape), sigma)
        stack = (255 * (smooth - smooth.min()) / (np.ptp(smooth) + 1e-12)).astype(np.uint8)
        stack[rng.integers(0, shape[0])] = 7  # a constant slice
        for radius in (0, 1, 2):
            for threshold in ("otsu", "multiotsu"):
                assert np.array_equal(
                    remove_skull(stack, opening_radius=radius, threshold=threshold),
                    _naive_remove_skull(stack, radius, threshold),
                )


def test_keep_nested_slices_matches_sequential_walk():
    from tumor3d.imaging.preprocess.skull import _keep_nested_slices

    rng = np.random.default_rng(14)
    yy, xx = np.mgrid[:40, :40]
    stops = 0
    for _ in range(100):
        # one random disc per slice (some empty): the walk stops where a disc leaves its
        # inner neighbour's
        nz = int(rng.integers(1, 9))
        mask = np.zeros((nz, 40, 40), dtype=bool)
        for z in range(nz):
            cy, cx, r = rng.uniform(5, 35), rng.uniform(5, 35), rng.uniform(0, 14)
            mask[z] = (yy - cy) ** 2 + (xx - cx) ** 2 < r * r
        expect = _naive_keep_nested(mask)
        stops += not np.array_equal(expect, mask)
        assert np.array_equal(_keep_nested_slices(mask), expect)
    assert stops > 10  # the clearing branch is exercised


def test_to_uint8_fused_window_matches_numpy_expression():
    rng = np.random.default_rng(15)
    for dtype in (np.float32, np.float64, np.int16, np.uint16):
        for _ in range(10):
            # tissue above 10 and a masked background of 0 (the minimum, also for the
            # unsigned dtype: a negative value would wrap to its top)
            vol = np.clip(rng.normal(100.0, 40.0, size=(3, 11, 13)), 10.0, None)
            vol[rng.random(vol.shape) < 0.3] = 0.0  # masked background
            vol = vol.astype(dtype)
            lo_p, hi_p = sorted(rng.uniform(0, 100, size=2))
            fg = vol[vol > vol.min()].astype(np.float64)
            lo, hi = np.percentile(fg, [lo_p, hi_p])
            if not hi > lo:
                lo, hi = float(vol.min()), float(vol.max())
            scaled = (vol.astype(np.float64) - lo) * (255.0 / (hi - lo))
            expect = np.floor(np.clip(scaled, 0.0, 255.0) + 0.5).astype(np.uint8)
            got = to_uint8(vol, window_percentiles=(lo_p, hi_p))
            assert np.array_equal(got, expect)


def test_the_air_outside_a_raw_head_is_found_and_no_brain_voxel_comes_near_it():
    """Anatomy: the brain lies at least the scalp plus skull (5 mm) inside the head."""
    from scipy import ndimage as ndi

    from tumor3d.imaging.brain_extraction import SCALP_SKULL_MIN_MM
    from tumor3d.phantom.patient import make_phantom_patient

    scan = make_phantom_patient(2).scan
    pre = preprocess_volume(scan.image, **PreprocessConfig().model_dump())
    assert pre.brain_extraction == "skull_strip" and pre.head_exterior is not None
    ext = pre.head_exterior
    # independent expectation: the image's corner pixels are air, the head's centre is not
    # (beyond the head's ends, a slice is air throughout)
    brain_slices = np.flatnonzero(pre.brain_mask.any(axis=(1, 2)))
    assert ext[:, 0, 0].all() and ext[:, -1, -1].all()
    assert not ext[brain_slices, 128, 128].any()
    for z in brain_slices:
        dist = ndi.distance_transform_edt(~ext[z], sampling=scan.pixel_spacing_mm)
        assert dist[pre.brain_mask[z]].min() >= SCALP_SKULL_MIN_MM, z
    # a skull-stripped volume (its brain borders the masked background) has no such air
    stripped = np.where(pre.brain_mask, scan.image, 0.0)
    assert preprocess_volume(stripped).brain_extraction == "foreground"
    assert preprocess_volume(stripped).head_exterior is None
    given = preprocess_volume(scan.image, brain_mask=pre.brain_mask)
    assert given.brain_extraction == "given" and given.head_exterior is None


@pytest.fixture(scope="module")
def stripped_head():
    """Phantom 4 skull-stripped and z-scored as BraTS, and its preprocessing (read-only)."""
    from tumor3d.phantom.patient import make_phantom_patient

    scan = make_phantom_patient(4).scan
    pre = preprocess_volume(scan.image, **PreprocessConfig().model_dump())
    inside = scan.image[pre.brain_mask]
    zscored = (scan.image - inside.mean()) / inside.std()  # as BraTS: range about 10
    stripped = np.where(pre.brain_mask, zscored, -3.16).astype(np.float32)
    clean = preprocess_volume(stripped, **PreprocessConfig().model_dump())
    for arr in (stripped, clean.brain_mask, clean.original_u8):
        arr.setflags(write=False)
    return stripped, clean


@pytest.mark.parametrize("spike", [1e7, -1e7, 1e12])
@pytest.mark.parametrize("where", ["background", "brain"])
def test_one_extreme_voxel_leaves_a_skull_stripped_brain_as_it_was(spike, where, stripped_head):
    """Issue 7's bad input 'one extreme outlier voxel', on a skull-stripped volume.

    The masked background's tolerance is a share of the volume's intensity range; with
    the plain maximum one voxel at 1e7 made it wide enough to take the whole brain.
    Independent expectation: the same volume without the spike.
    """
    stripped, clean = stripped_head
    assert clean.brain_extraction == "foreground"
    spiked = stripped.copy()
    zyx = (0, 0, 0) if where == "background" else tuple(np.argwhere(clean.brain_mask)[1000])
    spiked[zyx] = spike
    got = preprocess_volume(spiked, **PreprocessConfig().model_dump())
    assert got.brain_extraction == "foreground"
    differ = got.brain_mask != clean.brain_mask
    differ[zyx] = False  # the spike itself may count as foreground
    assert not differ.any()
    # the 8-bit window is set by percentiles of the foreground: one voxel more moves them
    # by a fraction of a gray level at most
    inside = clean.brain_mask.copy()
    inside[zyx] = False
    step = np.abs(got.original_u8[inside].astype(int) - clean.original_u8[inside])
    assert step.max() <= 1 and np.mean(step) < 0.05


def test_the_background_range_sample_does_not_alias_with_the_rows():
    """A review: a stride of size // 200,000 that is a multiple of the row length samples
    one column only; if that column is background, the range (and tolerance) is 0 and a
    resampled background (equal up to a few ulps) is lost."""
    from tumor3d.imaging.preprocess import masked_background

    rng = np.random.default_rng(3)
    shape = (10_000, 20, 20)  # size // 200_000 = 20: a multiple of the row length
    vol = rng.normal(1.0, 0.5, shape).astype(np.float32)
    background = np.zeros(shape, bool)
    background[:, :, :3] = True
    background[:, :3, :] = True
    ulps = rng.integers(-2, 3, shape).astype(np.float32) * np.spacing(np.float32(3.16))
    vol[background] = (np.float32(-3.16) + ulps)[background]
    bg = masked_background(vol)
    assert bg.share == pytest.approx(background.mean(), abs=1e-6)
    assert np.array_equal(bg.mask, background)

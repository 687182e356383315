"""Tests of tumor3d.geometry.distance (spec section 4, [A11], [A29])."""

from __future__ import annotations

import heapq
import math

import numpy as np
import pytest
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.geometry.distance import (
    chamfer_distance,
    cityblock_distance,
    euclidean_distance_mm,
    signed_distance,
)

SQRT2 = math.sqrt(2.0)
# max of chamfer(1, sqrt2) / Euclidean, reached at 22.5 degrees
CHAMFER_MAX_RATIO = math.cos(math.pi / 8) + (SQRT2 - 1.0) * math.sin(math.pi / 8)


def disk(shape, centre, radius):
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 <= radius**2


def dijkstra_chamfer(mask):
    """Exact chamfer metric: shortest paths in the 8-neighbour graph (weights 1, sqrt2).

    Sources: every pixel outside the mask and a one-pixel frame beyond the border.
    """
    h, w = mask.shape
    big = np.zeros((h + 2, w + 2), dtype=bool)
    big[1:-1, 1:-1] = mask
    dist = np.full(big.shape, np.inf)
    heap = []
    for y, x in np.argwhere(~big):
        dist[y, x] = 0.0
        heap.append((0.0, int(y), int(x)))
    heapq.heapify(heap)
    steps = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
    while heap:
        d, y, x = heapq.heappop(heap)
        if d > dist[y, x]:
            continue
        for dy, dx in steps:
            yy, xx = y + dy, x + dx
            if 0 <= yy < h + 2 and 0 <= xx < w + 2:
                nd = d + (SQRT2 if dy and dx else 1.0)
                if nd < dist[yy, xx]:
                    dist[yy, xx] = nd
                    heapq.heappush(heap, (nd, yy, xx))
    return dist[1:-1, 1:-1]


def brute_signed_distance(mask, metric, spacing=(1.0, 1.0)):
    """Closed-form metric, min over all pixels of the other set (plus the frame inside)."""

    def pair_metric(dy, dx):
        dy, dx = np.abs(dy), np.abs(dx)
        if metric == "taxicab":
            return dy + dx
        if metric == "euclidean":
            return np.hypot(spacing[0] * dy, spacing[1] * dx)
        return np.maximum(dy, dx) + (SQRT2 - 1.0) * np.minimum(dy, dx)

    half = 0.5 * min(spacing) if metric == "euclidean" else 0.5

    h, w = mask.shape
    big = np.zeros((h + 2, w + 2), dtype=bool)
    big[1:-1, 1:-1] = mask
    background = np.argwhere(~big) - 1  # includes the frame beyond the border
    objects = np.argwhere(mask)
    out = np.empty(mask.shape)
    for y in range(h):
        for x in range(w):
            if mask[y, x]:
                d = pair_metric(background[:, 0] - y, background[:, 1] - x).min()
                out[y, x] = d - half
            elif len(objects):
                d = pair_metric(objects[:, 0] - y, objects[:, 1] - x).min()
                out[y, x] = -(d - half)
            else:
                out[y, x] = -np.inf
    return out


# --------------------------------------------------------------------------
# distance transforms


def test_chamfer_distance_matches_dijkstra_on_random_masks():
    rng = np.random.default_rng(20130601)
    cases = [np.ones((7, 9), dtype=bool), np.ones((1, 1), dtype=bool), np.zeros((4, 3), bool)]
    for _ in range(40):
        shape = tuple(rng.integers(1, 14, size=2))
        density = rng.uniform(0.3, 0.95)
        cases.append(rng.random(shape) < density)
    for mask in cases:
        got = chamfer_distance(mask)
        np.testing.assert_allclose(got, dijkstra_chamfer(mask), rtol=0, atol=1e-12)
        assert np.all(got[~mask] == 0.0)


def test_chamfer_distance_of_disk_is_within_chamfer_bound_of_euclidean():
    mask = disk((81, 81), (40.0, 40.0), 34.0)
    got = chamfer_distance(mask)
    # Euclidean distance to the nearest background pixel (the frame counts as background)
    edt = ndi.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
    inside = mask
    ratio = got[inside] / edt[inside]
    assert ratio.min() >= 1.0 - 1e-12
    assert ratio.max() <= CHAMFER_MAX_RATIO + 1e-12
    # not the Euclidean transform: the 22.5-degree overestimate shows up
    assert ratio.max() > 1.04
    # at the centre both are close to the radius (34 plus the half pixel to the background)
    assert abs(got[40, 40] - 35.0) < 0.08 * 35.0


@pytest.mark.parametrize("metric", ["chamfer", "taxicab"])
def test_signed_distance_matches_brute_force(metric):
    rng = np.random.default_rng(7)
    masks = [
        rng.random(tuple(rng.integers(1, 12, size=2))) < rng.uniform(0.1, 0.9) for _ in range(25)
    ]
    masks += [np.ones((5, 6), dtype=bool), np.zeros((5, 6), dtype=bool)]
    for mask in masks:
        got = signed_distance(mask, metric=metric)
        ref = brute_signed_distance(mask, metric)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("spacing", [(1.0, 1.0), (0.7, 1.9), (3.0, 0.5)])
def test_euclidean_signed_distance_matches_brute_force_in_mm(spacing):
    rng = np.random.default_rng(31)
    masks = [
        rng.random(tuple(rng.integers(1, 12, size=2))) < rng.uniform(0.1, 0.9) for _ in range(25)
    ]
    masks += [np.ones((5, 6), dtype=bool), np.zeros((5, 6), dtype=bool)]
    for mask in masks:
        got = signed_distance(mask, metric="euclidean", spacing_mm=spacing)
        ref = brute_signed_distance(mask, "euclidean", spacing)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
        inside = euclidean_distance_mm(mask, spacing_mm=spacing)
        np.testing.assert_allclose(inside[mask], ref[mask] + 0.5 * min(spacing), atol=1e-9)
        assert np.all(inside[~mask] == 0.0)


def test_euclidean_distance_matches_scipy_on_large_masks():
    rng = np.random.default_rng(77)
    for _ in range(10):
        shape = tuple(rng.integers(20, 90, size=2))
        spacing = tuple(rng.uniform(0.3, 2.5, size=2))
        mask = ndi.binary_opening(rng.random(shape) < 0.6)
        ref = ndi.distance_transform_edt(np.pad(mask, 1), sampling=spacing)[1:-1, 1:-1]
        got = euclidean_distance_mm(mask, spacing_mm=spacing)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-9)
        if mask.any():
            outside = ndi.distance_transform_edt(~mask, sampling=spacing)
            d = signed_distance(mask, metric="euclidean", spacing_mm=spacing)
            half = 0.5 * min(spacing)
            np.testing.assert_allclose(d[~mask], half - outside[~mask], atol=1e-9)


def test_cityblock_distance_is_the_taxicab_inside_part():
    rng = np.random.default_rng(5)
    for _ in range(20):
        mask = rng.random(tuple(rng.integers(1, 12, size=2))) < 0.7
        ref = brute_signed_distance(mask, "taxicab")
        got = cityblock_distance(mask)
        np.testing.assert_allclose(got[mask], ref[mask] + 0.5)
        assert np.all(got[~mask] == 0.0)


def test_euclidean_distance_of_disk_is_the_radius_gap():
    """Exact EDT: at the centre of a disk of radius 30 px the distance is ~ 31 px (in mm)."""
    mask = disk((81, 81), (40.0, 40.0), 30.0)
    d = euclidean_distance_mm(mask, spacing_mm=(0.5, 0.5))
    # the nearest background pixel centre lies within (30, 31] pixels of the centre
    assert 30.0 * 0.5 < d[40, 40] <= 31.0 * 0.5
    # no chamfer overestimate: at 22.5 degrees the chamfer metric is 8 % long
    p = (40 + round(20 * math.sin(math.pi / 8)), 40 + round(20 * math.cos(math.pi / 8)))
    bg = np.argwhere(~np.pad(mask, 1)) - 1
    exact = 0.5 * np.hypot(bg[:, 0] - p[0], bg[:, 1] - p[1]).min()
    assert d[p] == pytest.approx(exact, abs=1e-9)
    assert 0.5 * chamfer_distance(mask)[p] > 1.03 * exact


def test_distance_validation():
    with pytest.raises(InputError, match="metric must be one of"):
        signed_distance(np.ones((4, 4), bool), metric="manhattan")
    with pytest.raises(InputError, match="spacing_mm applies only to metric='euclidean'"):
        signed_distance(np.ones((4, 4), bool), metric="chamfer", spacing_mm=(1.0, 1.0))
    with pytest.raises(InputError, match=r"spacing_mm must be a pair \(dy, dx\)"):
        euclidean_distance_mm(np.ones((4, 4), bool), spacing_mm=(1.0,))
    with pytest.raises(InputError, match="spacing_mm must hold positive finite mm"):
        signed_distance(np.ones((4, 4), bool), metric="euclidean", spacing_mm=(1.0, 0.0))
    with pytest.raises(InputError, match="spacing_mm must hold numbers"):
        euclidean_distance_mm(np.ones((4, 4), bool), spacing_mm=("a", 1.0))
    with pytest.raises(InputError, match="mask must be a 2-D mask"):
        chamfer_distance(np.zeros((2, 3, 4), dtype=bool))
    with pytest.raises(InputError, match="must not be empty"):
        cityblock_distance(np.zeros((0, 4), dtype=bool))
    with pytest.raises(InputError, match="must be binary"):
        euclidean_distance_mm(np.full((3, 3), 2))

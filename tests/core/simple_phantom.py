"""A small seeded head phantom for the tests of preprocessing, detection and segmentation.

Deliberately independent of ``tumor3d.phantom`` (written in parallel): it only
has to give known answers for sections 1-3 of the specification.

Geometry of slice ``z`` (concentric ellipses around the image centre, x radii
divided by 0.92, every radius scaled by ``s(z) = sqrt(1 - (0.6 (z - zc) / zc)^2)``
so the head narrows towards the end slices, like an ellipsoid):

=========  ===================  ================  ===================
tissue     radii (pixels)       T2 intensity      FLAIR-like intensity
=========  ===================  ================  ===================
air        outside 38           0                 0
scalp      33 .. 38             0.70 (fat)        0.70
skull      30 .. 33             0.04              0.04
CSF rim    27.5 .. 30           1.00              0.10 (suppressed)
GM         23 .. 27.5           0.55              0.55
WM         0 .. 23              0.33              0.40
ventricle  ellipse 6 x 3        1.00 (CSF)        0.10
tumour     ellipsoid, r = 9     0.78              0.90 (hyperintense)
=========  ===================  ================  ===================

The ventricle is centred 5 pixels below and 6 left of the centre. The
tumour ellipsoid is centred at pixel ``(y, x) = (40, 56)`` (inside the WM)
and at slice 5.5 with a half-depth of 2.2 slices, so it appears on slices
4-7 with in-plane radii of 6.6-8.8 pixels. Intensities are averaged over
4x4 sub-pixels (partial volume at every border) and Rician noise of standard
deviation ``noise_sigma`` is added (magnitude of a complex Gaussian), so the
background is not constant either.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Phantom", "make_head_phantom"]

T2_INTENSITY = {
    "air": 0.0,
    "scalp": 0.70,
    "skull": 0.04,
    "csf": 1.00,
    "gm": 0.55,
    "wm": 0.33,
    "tumor": 0.78,
}
FLAIR_INTENSITY = {
    "air": 0.0,
    "scalp": 0.70,
    "skull": 0.04,
    "csf": 0.10,
    "gm": 0.55,
    "wm": 0.40,
    "tumor": 0.90,
}
LABELS = {"air": 0, "scalp": 1, "skull": 2, "csf": 3, "gm": 4, "wm": 5, "tumor": 6}


@dataclass(frozen=True, eq=False)
class Phantom:
    """Image, tissue labels and ground-truth masks, all ``(z, y, x)``."""

    image: np.ndarray  # float64
    labels: np.ndarray  # int8, see LABELS
    brain: np.ndarray  # bool: CSF rim, GM, WM, ventricle and tumour
    tumor: np.ndarray  # bool


def _labels(n_slices: int, size: int, tumor: bool, supersample: int) -> np.ndarray:
    """Tissue labels on a grid ``supersample`` times finer in y and x."""
    n = size * supersample
    zc = (n_slices - 1) / 2.0
    # pixel-centre coordinates of the fine grid, in coarse pixel units
    coords = (np.arange(n) + 0.5) / supersample - 0.5
    yy, xx = np.meshgrid(coords, coords, indexing="ij")
    c = (size - 1) / 2.0
    r = np.hypot(yy - c, (xx - c) / 0.92)  # slightly elliptic head
    labels = np.zeros((n_slices, n, n), dtype=np.int8)
    for z in range(n_slices):
        s = np.sqrt(1.0 - (0.6 * (z - zc) / zc) ** 2)
        lab = np.full((n, n), LABELS["air"], dtype=np.int8)
        lab[r < 38 * s] = LABELS["scalp"]
        lab[r < 33 * s] = LABELS["skull"]
        lab[r < 30 * s] = LABELS["csf"]
        lab[r < 27.5 * s] = LABELS["gm"]
        lab[r < 23 * s] = LABELS["wm"]
        ventricle = ((yy - c - 5.0) / (3.0 * s)) ** 2 + ((xx - c + 6.0) / (6.0 * s)) ** 2 < 1.0
        lab[ventricle] = LABELS["csf"]
        labels[z] = lab
    if tumor:
        zz = np.arange(n_slices, dtype=float)[:, None, None]
        # ellipsoid: 2.2 slices deep, 9 pixels wide
        inside = ((zz - 5.5) / 2.2) ** 2 + ((yy - 40.0) ** 2 + (xx - 56.0) ** 2) / 9.0**2 < 1.0
        labels[inside & (labels >= LABELS["csf"])] = LABELS["tumor"]
    return labels


def make_head_phantom(
    *,
    n_slices: int = 12,
    size: int = 96,
    tumor: bool = True,
    noise_sigma: float = 0.04,
    supersample: int = 4,
    intensities: dict[str, float] | None = None,
    seed: int = 0,
) -> Phantom:
    """Build the phantom described in the module docstring.

    Intensities are averaged over ``supersample x supersample`` sub-pixels,
    so border pixels have partial-volume values; a pixel belongs to a
    ground-truth mask when at least half of its sub-pixels do, and its label
    is the majority label of its sub-pixels.
    """
    rng = np.random.default_rng(seed)
    fine = _labels(n_slices, size, tumor, supersample)
    lut = np.zeros(len(LABELS))
    for name, value in (intensities or T2_INTENSITY).items():
        lut[LABELS[name]] = value
    k = supersample

    def block_mean(a: np.ndarray) -> np.ndarray:
        return a.reshape(n_slices, size, k, size, k).mean(axis=(2, 4))

    clean = block_mean(lut[fine])
    onehot = np.stack([block_mean((fine == v).astype(float)) for v in LABELS.values()])
    labels = np.argmax(onehot, axis=0).astype(np.int8)
    noisy = np.hypot(
        clean + rng.normal(0.0, noise_sigma, clean.shape),
        rng.normal(0.0, noise_sigma, clean.shape),
    )
    brain_fraction = onehot[LABELS["csf"] :].sum(axis=0)
    return Phantom(
        image=noisy,
        labels=labels,
        brain=brain_fraction >= 0.5,
        tumor=onehot[LABELS["tumor"]] >= 0.5,
    )

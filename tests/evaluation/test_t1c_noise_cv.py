"""benchmarks/t1c_noise_cv.py's Rician noise: background kept, the SD asked for, seeded."""

from __future__ import annotations

import numpy as np
from benchmark_scripts import benchmark_module

t1c_noise_cv = benchmark_module("t1c_noise_cv")


def test_rician_noise_has_the_sd_asked_for_and_keeps_the_background():
    img = np.full((4, 64, 64), 1000.0)
    img[:, :8] = 5.0  # the background: the image's minimum
    noisy = t1c_noise_cv.rician(img, 0.04, seed=3)
    np.testing.assert_array_equal(noisy[:, :8], 5.0)
    # at this signal-to-noise ratio Rician noise is nearly Gaussian: SD 4 % of the
    # foreground's median (995 above the background), its mean barely raised
    fg = noisy[:, 8:] - 5.0
    assert abs(fg.std() - 0.04 * 995.0) < 0.05 * 0.04 * 995.0
    assert abs(fg.mean() - 995.0) < 2.0
    np.testing.assert_array_equal(noisy, t1c_noise_cv.rician(img, 0.04, seed=3))
    assert not np.array_equal(noisy, t1c_noise_cv.rician(img, 0.04, seed=4))

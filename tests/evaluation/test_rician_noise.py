"""The Rician noise of benchmarks/real_robustness.py's "noise 8 %" column and of
benchmarks/t1c_noise_cv.py's training copies: background kept, the SD asked for, seeded."""

from __future__ import annotations

import numpy as np
from benchmark_scripts import benchmark_module

real_robustness = benchmark_module("real_robustness")
t1c_noise_cv = benchmark_module("t1c_noise_cv")


def test_rician_noise_has_the_sd_asked_for_and_keeps_the_background():
    img = np.full((4, 64, 64), 1000.0)
    img[:, :8] = 5.0  # the background: the image's minimum
    noisy = real_robustness.rician(img, 0.04, seed=3)
    np.testing.assert_array_equal(noisy[:, :8], 5.0)
    # at this signal-to-noise ratio Rician noise is nearly Gaussian: SD 4 % of the
    # foreground's median (995 above the background), its mean barely raised
    fg = noisy[:, 8:] - 5.0
    assert abs(fg.std() - 0.04 * 995.0) < 0.05 * 0.04 * 995.0
    assert abs(fg.mean() - 995.0) < 2.0
    np.testing.assert_array_equal(noisy, real_robustness.rician(img, 0.04, seed=3))
    assert not np.array_equal(noisy, real_robustness.rician(img, 0.04, seed=4))
    # the column is this noise at 8 %, seed 0; the T1c experiment's copies are the same noise
    np.testing.assert_array_equal(
        real_robustness._variant(img, "noise 8 %", 2), real_robustness.rician(img, 0.08, seed=0)
    )
    assert t1c_noise_cv.rician.__module__ == "real_robustness"  # imported, not a copy

"""Benchmark: the phantom renderer's purity test near a head boundary.

The renderer (:func:`tumor3d.phantom.raster._render`) supersamples a pixel only when it
cannot prove that one tissue fills the pixel's sample box. Two proofs are compared, in
one process, alternately, on the same phantoms:

- **Lipschitz ball** (the renderer before): every field farther from its thresholds
  than its global Lipschitz bound times the half diagonal of the box. Run by giving
  the renderer an infinite Hessian bound (``head[13:15]``), which turns the second
  proof off.
- **Lipschitz ball, then the box's own bound** (now): where the first proof fails near
  a head threshold, :func:`tumor3d.phantom.raster._fields_pure_near` bounds the fields
  over the box from the gradient at its centre and a Hessian bound.

Both must give the image and labels of full supersampling bit for bit (checked against
``adaptive=False`` on the first case of each size, whose full render takes seconds).
Sizes: the tests' small phantoms (16 x 128 x 128), the default preset (~30 x 256 x 256),
the paper preset (~30 x 480 x 640). Prints the median render time of each proof and
their ratio, and the whole ``make_phantom_patient`` time for scale.

Usage::

    python benchmarks/bench_phantom.py [--seeds 4] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.phantom import make_phantom_patient  # noqa: E402
from tumor3d.phantom import patient as patient_module  # noqa: E402
from tumor3d.phantom.raster import _render  # noqa: E402

SIZES = {
    "small (tests)": {"n_slices": 16, "matrix_size": (128, 128)},
    "default": {},
    "paper": {"preset": "paper"},
}


def render_args(seed: int, kw: dict) -> tuple[float, tuple]:
    """The renderer's arguments for phantom ``seed``, as ``make_phantom_patient`` passes them.

    Taken from the call itself (the renderer wrapped while the phantom is made), without
    the last one, ``adaptive``; and the time the whole phantom took.
    """
    calls: list[tuple] = []

    def recording(*args):
        calls.append(args[:-1])
        return _render(*args)

    patient_module._render = recording
    try:
        t0 = time.perf_counter()
        make_phantom_patient(seed, **kw)
        made_s = time.perf_counter() - t0
    finally:
        patient_module._render = _render
    (args,) = calls
    return made_s, args


def lipschitz_only(args: tuple) -> tuple:
    head = args[6].copy()
    head[13:15] = np.inf  # no Hessian bound: the box's own proof never passes
    return (*args[:6], head, *args[7:])


def timed(args: tuple) -> tuple[float, np.ndarray, np.ndarray]:
    t0 = time.perf_counter()
    image, labels = _render(*args, True)
    return time.perf_counter() - t0, image, labels


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    timed(render_args(1, SIZES["small (tests)"])[1])  # compile / load the kernels
    print("| phantoms | render, Lipschitz ball (before) | render, + the box's bound (now) "
          "| ratio | make_phantom_patient (now) |")  # fmt: skip
    print("|---|---|---|---|---|")
    for name, kw in SIZES.items():
        before, now, made = [], [], []
        for seed in range(1000, 1000 + a.seeds):
            made_s, args = render_args(seed, kw)
            made.append(made_s)
            old = lipschitz_only(args)
            for r in range(a.repeat):
                pair = ((old, before), (args, now))
                for peer_args, times in pair if r % 2 == 0 else pair[::-1]:
                    times.append(timed(peer_args)[0])
            if seed == 1000:
                full_image, full_labels = _render(*args, False)
                for peer_args in (old, args):
                    _, image, labels = timed(peer_args)
                    assert np.array_equal(image, full_image), name
                    assert np.array_equal(labels, full_labels), name
        b, n = statistics.median(before), statistics.median(now)
        print(f"| {name} x{a.seeds} | {b * 1e3:.0f} ms | {n * 1e3:.0f} ms | {b / n:.2f}x "
              f"| {statistics.median(made) * 1e3:.0f} ms |")  # fmt: skip
    print("\nboth proofs gave full supersampling's image and labels bit for bit")


if __name__ == "__main__":
    main()

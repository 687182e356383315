"""A small 2-D U-Net's forward pass in numpy (no torch at inference).

The network (``benchmarks/cnn_cv.py`` trains it with PyTorch, an optional
extra) is a U-Net (Ronneberger et al. 2015) of ``levels`` levels: at level
``i`` two 3 x 3 convolutions (``base * 2**i`` channels, ReLU; the training
batch normalisation folded into their weights and biases), 2 x 2 max pooling
down, nearest-neighbour x2 upsampling up, the skip concatenated *after* the
upsampled map, and a 1 x 1 convolution to one logit. Input ``(n, c, h, w)``
with ``h`` and ``w`` divisible by ``2 ** (levels - 1)``.

Weights come from the bytes of an ``.npz`` read with ``allow_pickle=False``
(:func:`unet_from_bytes`): arrays
``enc{i}_{j}_w`` / ``enc{i}_{j}_b`` (encoder level ``i``, convolution
``j`` in 0, 1), ``dec{i}_{j}_w`` / ``dec{i}_{j}_b`` (decoder step ``i`` from
the deepest), ``head_w`` / ``head_b``; weights are ``(out, in, kh, kw)`` as
PyTorch stores them. Nothing here reads a file.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError

__all__ = ["UNetWeights", "conv2d", "unet_from_bytes", "unet_logits", "unet_probability"]


@dataclass(frozen=True)
class UNetWeights:
    """The arrays of one U-Net, by name (see the module docstring), and its depth."""

    arrays: dict[str, np.ndarray]
    levels: int

    @property
    def in_channels(self) -> int:
        """Channels of the input (the slice and its neighbours)."""
        return int(self.arrays["enc0_0_w"].shape[1])


def unet_from_bytes(data: bytes, *, source: str = "weights") -> UNetWeights:
    """The U-Net of an ``.npz``'s bytes (plain arrays only: never unpickles).

    ``source`` names it in errors. The caller reads the bytes (nothing here
    touches the file system).
    """
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: np.asarray(z[k], dtype=np.float32) for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"{source}: not a readable .npz of plain arrays ({exc})") from exc
    levels = sum(1 for k in arrays if k.startswith("enc") and k.endswith("_0_w"))
    if levels < 1 or "head_w" not in arrays:
        raise InputError(f"{source}: not a U-Net weight file (no enc0_0_w / head_w)")
    return UNetWeights(arrays, levels)


def conv2d(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """'Same' 2-D cross-correlation (zero padding) of channel-last ``x`` (h, w, c).

    ``w`` is ``(out, in, k, k)`` with odd ``k``; returns ``(h, w, out)``
    float32. One matrix product over the ``k * k`` shifted copies of ``x``.
    """
    o, i, kh, kw = w.shape
    if x.shape[-1] != i:
        raise InputError(f"conv2d: input has {x.shape[-1]} channels, weights want {i}")
    h, wd = x.shape[0], x.shape[1]
    if kh == 1 and kw == 1:
        out = x.reshape(-1, i) @ w[:, :, 0, 0].T
        return (out + b).reshape(h, wd, o).astype(np.float32, copy=False)
    ph, pw = kh // 2, kw // 2
    xp = np.pad(x, ((ph, ph), (pw, pw), (0, 0)))
    cols = np.empty((h, wd, kh, kw, i), np.float32)
    for dy in range(kh):
        for dx in range(kw):
            cols[:, :, dy, dx, :] = xp[dy : dy + h, dx : dx + wd, :]
    wm = np.ascontiguousarray(w.transpose(2, 3, 1, 0).reshape(kh * kw * i, o))
    out = cols.reshape(h * wd, kh * kw * i) @ wm
    return (out + b).reshape(h, wd, o).astype(np.float32, copy=False)


def _block(x: np.ndarray, net: UNetWeights, name: str) -> np.ndarray:
    a = net.arrays
    for j in (0, 1):
        x = np.maximum(conv2d(x, a[f"{name}_{j}_w"], a[f"{name}_{j}_b"]), 0.0)
    return x


def _pool(x: np.ndarray) -> np.ndarray:
    h, w, c = x.shape
    return x.reshape(h // 2, 2, w // 2, 2, c).max(axis=(1, 3))


def _up(x: np.ndarray) -> np.ndarray:
    return np.repeat(np.repeat(x, 2, axis=0), 2, axis=1)


def unet_logits(net: UNetWeights, images: np.ndarray) -> np.ndarray:
    """Logits ``(n, h, w)`` of ``images`` ``(n, c, h, w)``, one image at a time."""
    x = np.asarray(images, dtype=np.float32)
    if x.ndim != 4 or x.shape[1] != net.in_channels:
        raise InputError(f"images must be (n, {net.in_channels}, h, w), got shape {tuple(x.shape)}")
    m = 2 ** (net.levels - 1)
    if x.shape[2] % m or x.shape[3] % m:
        raise InputError(f"image size {x.shape[2:]} must be divisible by {m}")
    out = np.empty((x.shape[0], x.shape[2], x.shape[3]), np.float32)
    for n in range(x.shape[0]):
        h = np.ascontiguousarray(x[n].transpose(1, 2, 0))
        skips = []
        for i in range(net.levels):
            h = _block(h, net, f"enc{i}")
            if i < net.levels - 1:
                skips.append(h)
                h = _pool(h)
        for i in range(net.levels - 1):
            h = _block(np.concatenate([_up(h), skips.pop()], axis=-1), net, f"dec{i}")
        out[n] = conv2d(h, net.arrays["head_w"], net.arrays["head_b"])[..., 0]
    return out


def unet_probability(net: UNetWeights, images: np.ndarray) -> np.ndarray:
    """Sigmoid of :func:`unet_logits`, float32 in [0, 1]."""
    z = unet_logits(net, images)
    return (0.5 * (1.0 + np.tanh(0.5 * z))).astype(np.float32)

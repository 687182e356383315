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
PyTorch stores them; optionally ``meta_json``, the UTF-8 bytes (uint8) of a
JSON object saying what it was trained on (``settings.size`` and
``settings.context`` set the input grid; 128 and 1 without it). Nothing here
reads a file.

Speed (``benchmarks/bench_learned.py``): all slices go through each layer
together, channel-last, in float32; a 3 x 3 convolution is one matrix product
per kernel tap on the unpadded input (weights laid out once, when loaded) whose
shifted results are summed, so no padded or column copy of the input is made;
the matrix products run on one BLAS thread (:func:`single_blas_thread`): BLAS's
own threads spin and collapse on a shared, loaded machine, and the learned
method runs the network beside the forest instead
(:func:`tumor3d.learned.segment.segment_learned`).
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import hashlib
import io
import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import cache
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.learned.archive import UNREADABLE, archive_error, check_archive

__all__ = [
    "META_KEY",
    "UNetWeights",
    "as_nets",
    "conv2d",
    "decode_meta",
    "single_blas_thread",
    "unet_from_bytes",
    "unet_logits",
    "unet_member_probabilities",
    "unet_probability",
    "unet_volume_probability",
]

#: The array of a weight file holding its metadata: the UTF-8 bytes (uint8) of a JSON document.
#: The largest U-Net read (the shipped ones: 4 levels, 64 channels at most): the reader's
#: dry pass and every inference cost grow with both (a hostile file may declare anything).
MAX_LEVELS = 6
MAX_CHANNELS = 512

META_KEY = "meta_json"


def decode_meta(raw: np.ndarray) -> Any:
    """The JSON document of a weight file's :data:`META_KEY` array (uint8 UTF-8 bytes).

    >>> decode_meta(np.frombuffer(b'{"size": 128}', np.uint8))
    {'size': 128}
    """
    return json.loads(np.asarray(raw, np.uint8).tobytes().decode())


#: Input grid of a weight file without ``meta_json`` (the settings of the CV, run2).
DEFAULT_SIZE = 128
DEFAULT_CONTEXT = 1

#: Widest input (channels) a convolution copies into its row's taps side by side: one
#: product per kernel row beats one per tap there (measured, 31 slices, one thread:
#: 128 x 128 x 3 -> 8 channels 18 against 40 ms, 8 -> 8 25 against 35 ms; 24 -> 8 68
#: against 60 ms).
_ROW_COPY_CHANNELS = 16

#: Slices per batch through the network: 2 ran fastest (the layers stay in cache;
#: 0.36 CPU-s for 31 slices against 0.45 at 8 and 0.48 at 31), and bound the memory.
_BATCH_SLICES = 2


def _taps(w: np.ndarray) -> np.ndarray:
    """``(o, i, kh, kw)`` -> ``(kh * kw, i, o)`` float32, one ``(i, o)`` matrix per tap."""
    o, i, kh, kw = w.shape
    return np.ascontiguousarray(w.transpose(2, 3, 1, 0).reshape(kh * kw, i, o), np.float32)


@dataclass(frozen=True)
class UNetWeights:
    """The arrays of one U-Net, by name (see the module docstring), and its depth.

    ``meta`` is the file's ``meta_json`` (empty without one), ``sha256`` the
    digest of the bytes it was read from (empty when built from arrays).
    """

    arrays: dict[str, np.ndarray]
    levels: int
    meta: dict[str, Any] = field(default_factory=dict)
    sha256: str = ""
    _taps: dict[str, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        taps = {k[:-2]: _taps(v) for k, v in self.arrays.items() if k.endswith("_w")}
        object.__setattr__(self, "_taps", taps)

    @property
    def in_channels(self) -> int:
        """Channels of the input (the slice and its neighbours)."""
        return int(self.arrays["enc0_0_w"].shape[1])

    @property
    def size(self) -> int:
        """Side of the square grid the slices are resampled to."""
        return int(self.meta.get("settings", {}).get("size", DEFAULT_SIZE))

    @property
    def framing(self) -> str:
        """What of each slice the net sees (:data:`tumor3d.learned.cnn_data.FRAMINGS`)."""
        return str(self.meta.get("settings", {}).get("framing", "slice"))

    @property
    def context(self) -> int:
        """Neighbour slices each side in the input (``in_channels = 2 context + 1``)."""
        return int(self.meta.get("settings", {}).get("context", DEFAULT_CONTEXT))


def unet_from_bytes(data: bytes, *, source: str = "weights") -> UNetWeights:
    """The U-Net of an ``.npz``'s bytes (plain arrays only: never unpickles).

    ``source`` names it in errors. The caller reads the bytes (nothing here
    touches the file system).
    """
    check_archive(data, source=source)
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            raw = {k: z[k] for k in z.files}
        meta = raw.pop(META_KEY, None)
        meta = {} if meta is None else decode_meta(meta)
        arrays = {k: np.asarray(v, dtype=np.float32) for k, v in raw.items()}
    except UNREADABLE as exc:
        why = archive_error(exc)
        raise InputError(f"{source}: not a readable .npz of plain arrays ({why})") from None
    levels = sum(1 for k in arrays if k.startswith("enc") and k.endswith("_0_w"))
    if levels < 1 or "head_w" not in arrays or not isinstance(meta, dict):
        raise InputError(f"{source}: not a U-Net weight file (no enc0_0_w / head_w)")
    needed = [f"{p}{i}_{j}_{t}" for p, n in (("enc", levels), ("dec", levels - 1))
              for i in range(n) for j in (0, 1) for t in "wb"]  # fmt: skip
    missing = [k for k in needed + ["head_b"] if k not in arrays]
    if missing:
        raise InputError(f"{source}: not a U-Net weight file (missing {', '.join(missing[:3])})")
    if any(arrays[k].ndim != (4 if k.endswith("_w") else 1) for k in needed + ["head_w", "head_b"]):
        raise InputError(f"{source}: not a U-Net weight file (a layer of the wrong rank)")
    widest = max(max(arrays[k].shape[:2]) for k in needed + ["head_w"] if k.endswith("_w"))
    if levels > MAX_LEVELS or widest > MAX_CHANNELS:
        raise InputError(
            f"{source}: {levels} levels and {widest} channels, larger than any tumor3d U-Net "
            f"({MAX_LEVELS} levels, {MAX_CHANNELS} channels at most)"
        )
    try:
        net = UNetWeights(arrays, levels, meta, hashlib.sha256(data).hexdigest())
        m = 2 ** (levels - 1)  # a dry pass: the layers' shapes must chain
        _forward(net, np.zeros((1, 2 * m, 2 * m, net.in_channels), np.float32))
    except (ValueError, IndexError, TypeError, MemoryError) as exc:
        raise InputError(
            f"{source}: not a U-Net weight file (its layers do not fit together: {exc})"
        ) from None
    if net.in_channels != 2 * net.context + 1:
        raise InputError(
            f"{source}: {net.in_channels} input channels but context {net.context} "
            f"(2 context + 1 expected)"
        )
    from tumor3d.learned.cnn_data import FRAMINGS

    if net.framing not in FRAMINGS:
        raise InputError(
            f"{source}: framing {net.framing!r} unknown (expected one of {', '.join(FRAMINGS)})"
        )
    return net


@cache
def _blas_local_threads() -> Any:
    """OpenBLAS's per-thread thread count setter, if numpy's BLAS is an OpenBLAS >= 0.3.27."""
    here = os.path.dirname(np.__file__)
    for lib in sorted(glob.glob(os.path.join(here, os.pardir, "numpy.libs", "*openblas*"))):
        try:
            fn = ctypes.CDLL(lib).openblas_set_num_threads_local
        except (OSError, AttributeError):
            continue
        fn.argtypes, fn.restype = [ctypes.c_int], ctypes.c_int
        return fn
    return None


@contextlib.contextmanager
def single_blas_thread() -> Iterator[bool]:
    """Matrix products of the calling thread on one BLAS thread, within the block.

    Only this thread's setting changes (OpenBLAS's thread-local count, numpy's
    own OpenBLAS); with another BLAS it does nothing. Yields whether it applied.
    """
    fn = _blas_local_threads()
    if fn is None:
        yield False
        return
    old = fn(1)
    try:
        yield True
    finally:
        fn(old)


def conv2d(x: np.ndarray, w: np.ndarray, b: np.ndarray, *, taps: np.ndarray | None = None):
    """'Same' 2-D cross-correlation (zero padding) of channel-last ``x`` (..., h, w, c).

    ``w`` is ``(out, in, k, k)`` with odd ``k``; returns ``(..., h, w, out)``
    float32 (``taps``: ``w`` laid out by tap, as :class:`UNetWeights` keeps it).
    Each kernel row is one matrix product whose result is added to the output
    shifted by its row: on the ``k`` column-shifted copies of the input side by
    side when the input has at most :data:`_ROW_COPY_CHANNELS` channels (one
    product of ``k * c`` columns), else on the unpadded input itself, one
    product per tap (no copy of a wide input).
    """
    o, i, kh, kw = w.shape
    if x.shape[-1] != i:
        raise InputError(f"conv2d: input has {x.shape[-1]} channels, weights want {i}")
    t = _taps(w) if taps is None else taps
    x = np.asarray(x, np.float32)
    h, wd = x.shape[-3], x.shape[-2]
    out = np.empty((*x.shape[:-1], o), np.float32)
    out[...] = b
    ph, pw = kh // 2, kw // 2
    cols = None
    if i <= _ROW_COPY_CHANNELS and kw > 1:
        cols = np.zeros((*x.shape[:-1], kw, i), np.float32)  # the row's taps side by side
        for dx in range(kw):
            x0, x1 = max(0, pw - dx), min(wd, wd + pw - dx)
            cols[..., x0:x1, dx, :] = x[..., x0 + dx - pw : x1 + dx - pw, :]
        cols = cols.reshape(-1, kw * i)
    flat = x.reshape(-1, i)
    for dy in range(kh):
        y0, y1 = max(0, ph - dy), min(h, h + ph - dy)  # output rows this kernel row reaches
        if y1 <= y0:
            continue
        sy = dy - ph
        if cols is not None:
            r = (cols @ t[dy * kw : (dy + 1) * kw].reshape(kw * i, o)).reshape(out.shape)
            out[..., y0:y1, :, :] += r[..., y0 + sy : y1 + sy, :, :]
            continue
        for dx in range(kw):
            x0, x1 = max(0, pw - dx), min(wd, wd + pw - dx)
            if x1 <= x0:
                continue
            r = (flat @ t[dy * kw + dx]).reshape(out.shape)
            sx = dx - pw
            out[..., y0:y1, x0:x1, :] += r[..., y0 + sy : y1 + sy, x0 + sx : x1 + sx, :]
    return out


def _block(x: np.ndarray, net: UNetWeights, name: str) -> np.ndarray:
    a = net.arrays
    for j in (0, 1):
        k = f"{name}_{j}"
        x = conv2d(x, a[f"{k}_w"], a[f"{k}_b"], taps=net._taps[k])
        np.maximum(x, 0.0, out=x)
    return x


def _pool(x: np.ndarray) -> np.ndarray:
    n, h, w, c = x.shape
    return x.reshape(n, h // 2, 2, w // 2, 2, c).max(axis=(2, 4))


def _up(x: np.ndarray) -> np.ndarray:
    return np.repeat(np.repeat(x, 2, axis=1), 2, axis=2)


def _forward(net: UNetWeights, x: np.ndarray) -> np.ndarray:
    """Logits ``(n, h, w)`` of channel-last ``x`` ``(n, h, w, c)``."""
    h = x
    skips = []
    for i in range(net.levels):
        h = _block(h, net, f"enc{i}")
        if i < net.levels - 1:
            skips.append(h)
            h = _pool(h)
    for i in range(net.levels - 1):
        h = _block(np.concatenate([_up(h), skips.pop()], axis=-1), net, f"dec{i}")
    head = net.arrays["head_w"][:, :, 0, 0]
    return (h @ head[0] + net.arrays["head_b"][0]).astype(np.float32)


def unet_logits(net: UNetWeights, images: np.ndarray) -> np.ndarray:
    """Logits ``(n, h, w)`` of images ``(n, c, h, w)``, a few slices at a time."""
    x = np.asarray(images)
    if x.ndim != 4 or x.shape[1] != net.in_channels:
        raise InputError(f"images must be (n, {net.in_channels}, h, w), got shape {tuple(x.shape)}")
    m = 2 ** (net.levels - 1)
    if x.shape[2] % m or x.shape[3] % m:
        raise InputError(f"image size {x.shape[2:]} must be divisible by {m}")
    out = np.empty((x.shape[0], x.shape[2], x.shape[3]), np.float32)
    with single_blas_thread():
        for s in range(0, x.shape[0], _BATCH_SLICES):
            part = np.ascontiguousarray(x[s : s + _BATCH_SLICES].transpose(0, 2, 3, 1), np.float32)
            out[s : s + _BATCH_SLICES] = _forward(net, part)
    return out


def _sigmoid(z: np.ndarray) -> np.ndarray:
    return (0.5 * (1.0 + np.tanh(0.5 * z))).astype(np.float32)


def unet_probability(net: UNetWeights, images: np.ndarray, *, mirror: bool = False) -> np.ndarray:
    """Sigmoid of :func:`unet_logits`, float32 ``(n, h, w)`` in [0, 1].

    ``mirror``: the mean of the network's probability of the images and of
    their mirror image (the column axis, the left-right flip of the training),
    mirrored back: a test-time augmentation that costs a second pass. The
    answer is then mirror-equivariant, as a left-right flipped head's should
    be (``reports/learned_cv.md``, "Mirrored inference": cross-validated).
    """
    p = _sigmoid(unet_logits(net, images))
    if mirror:
        flipped = np.ascontiguousarray(np.asarray(images)[..., ::-1])
        p = 0.5 * (p + _sigmoid(unet_logits(net, flipped))[..., ::-1])  # float32 stays
    return p


def as_nets(net: Any, *, name: str = "net") -> tuple[UNetWeights, ...]:
    """``net`` (one U-Net or a sequence of them, an ensemble) as a tuple of nets.

    Raises :class:`~tumor3d.errors.InputError` (one line, naming the argument
    ``name``) for anything else, an empty sequence included.

    >>> as_nets([], name="cnn")
    Traceback (most recent call last):
    ...
    tumor3d.errors.InputError: cnn must be a UNetWeights or a non-empty sequence of them, got list
    """
    if isinstance(net, UNetWeights):
        return (net,)
    nets = tuple(net) if isinstance(net, Sequence) and not isinstance(net, str) else ()
    if not nets or not all(isinstance(n, UNetWeights) for n in nets):
        raise InputError(
            f"{name} must be a UNetWeights or a non-empty sequence of them, "
            f"got {type(net).__name__}"
        )
    return nets


def unet_member_probabilities(
    net: UNetWeights | Sequence[UNetWeights],
    image: np.ndarray,
    *,
    mirror: bool = False,
    pixel_mm: tuple[float, float] | None = None,
) -> np.ndarray:
    """Each net's lesion probability of every voxel of ``image`` ``(z, y, x)``, in [0, 1].

    The slices as acquired go in on the grid each net was trained on
    (:func:`tumor3d.learned.cnn_data.case_input` at the file's size, context
    and framing, computed once per grid) and come back bilinearly to the native
    grid (:func:`tumor3d.learned.cnn_data.upsample`), as in the
    cross-validation. ``mirror``: each probability is also the mean with the
    net's mirrored pass (:func:`unet_probability`). Returns ``(n_nets, z, y, x)``
    float32; their spread inside the lesion is a review figure
    (:func:`tumor3d.learned.review.review_features`, ``net_spread``).
    ``pixel_mm``: the slices' (row, column) spacing, which a net framed in
    millimetres needs (:func:`tumor3d.learned.cnn_data.frame_of`).
    """
    from tumor3d.learned.cnn_data import case_input, frame_of, upsample

    nets = as_nets(net)
    img = np.asarray(image)
    if img.ndim != 3 or min(img.shape) < 1:
        raise InputError(f"image must be 3-D (z, y, x), got shape {img.shape}")
    framings = {n.framing for n in nets}
    if "mm" in framings and pixel_mm is None:
        raise InputError("a U-Net framed in millimetres needs the pixel spacing (pixel_mm)")
    frames = {f: frame_of(img, f, pixel_mm) for f in framings}
    inputs: dict[tuple[int, int, str], np.ndarray] = {}
    out = np.empty((len(nets), *img.shape), np.float32)
    for i, n in enumerate(nets):
        grid = (n.size, n.context, n.framing)
        if grid not in inputs:
            inputs[grid] = case_input(img, n.size, n.context, frames[n.framing])
        prob = unet_probability(n, inputs[grid], mirror=mirror)
        out[i] = upsample(prob, img.shape, frames[n.framing])
    return out


def unet_volume_probability(
    net: UNetWeights | Sequence[UNetWeights],
    image: np.ndarray,
    *,
    mirror: bool = False,
    pixel_mm: tuple[float, float] | None = None,
) -> np.ndarray:
    """The network's lesion probability of every voxel of ``image`` ``(z, y, x)``, in [0, 1].

    A sequence of nets (an ensemble: the same network trained with other
    seeds; the pipeline's) gives the mean of their probabilities
    (:func:`unet_member_probabilities`: each net on its training grid, back on
    the native one). ``mirror``: each net's probability is also the mean with
    its mirrored pass (:func:`unet_probability`); the pipeline runs the shipped
    ensemble without it (one pass per net: as accurate by cross-validation,
    half the time; ``reports/learned_cv.md``, "A longer-trained U-Net").
    """
    members = unet_member_probabilities(net, image, mirror=mirror, pixel_mm=pixel_mm)
    return members.mean(axis=0, dtype=np.float32)

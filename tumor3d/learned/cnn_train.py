"""Training the U-Net of :mod:`tumor3d.learned.cnn` with PyTorch (the ``train`` extra).

Arrays in, ``.npz`` bytes out: :func:`unet_slices` turns one labelled patient
into the network's input and target slices (:mod:`tumor3d.learned.cnn_data`,
the grids inference uses), :func:`fit_unet` trains the network on the slices
of many patients, :func:`unet_to_bytes` exports it as
:func:`tumor3d.learned.cnn.unet_from_bytes` reads it (batch normalisation
folded into the convolutions; a ``meta_json`` entry, the UTF-8 bytes of a JSON
object as a uint8 array, says what it was trained on). :func:`train_unet` does
all three.

The training (issue 28; ``reports/learned_cv.md`` cross-validates it by
patient): every epoch every slice with tumour and ``neg_ratio`` times as many
slices without, drawn at random; binary cross-entropy + the batch's soft Dice + the
mean per-slice soft Dice of its slices with tumour (``UNetSettings.slice_dice``); Adam
(weight decay 1e-5) with a one-cycle learning rate (15 % warm-up, cosine
decay); left-right flips, shifts of up to ``shift`` pixels and intensity
jitter (gain 0.9-1.1, offset +-0.1) per batch. Seeded: torch's and numpy's
generators both start from ``seed``, so one seed, one thread count and one
torch version give one network.

PyTorch is imported inside the functions that need it; without it they
raise an :class:`~tumor3d.errors.InputError` naming the extra (inference
needs numpy only). Nothing here touches the file system.
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.learned.cnn import META_KEY, decode_meta

__all__ = [
    "UNetFit",
    "UNetSettings",
    "fit_unet",
    "require_torch",
    "slices_from_bytes",
    "slices_to_bytes",
    "torch_probability",
    "train_unet",
    "unet_meta",
    "unet_slices",
    "unet_to_bytes",
]


@dataclass(frozen=True)
class UNetSettings:
    """The network and its training (defaults: the cross-validated and shipped ones).

    ``size``: slices resampled to ``size`` x ``size``; ``context``: neighbour
    slices each side as channels; ``base``: channels at the top level, doubled
    per level; ``levels``: resolution levels; then the training's epochs,
    batch, peak learning rate, slices without tumour per slice with, the
    largest random shift in pixels, and the random in-plane scaling (a factor
    within ``1 +- scale``) and rotation (within ``+- rotate_deg`` degrees) of
    each slice, both 0 (none) in the shipped training; ``framing``: what of each
    slice the net sees (:data:`tumor3d.learned.cnn_data.FRAMINGS`: the whole
    slice; a square around the head; a square of 240 mm centred on the head, shipped:
    the field of view does not set the scale at which the net sees the head);
    ``slice_dice``: the weight of a per-slice soft Dice term, the mean over the batch's
    slices that hold tumour, added to the loss (binary cross-entropy + the batch's soft
    Dice, in which the large cross-sections outweigh the small ones); 1 in the shipped
    training (chosen by the rule of ``reports/learned_cv.md``, "A per-slice soft Dice in
    the U-Net's loss"; 0 before).
    """

    size: int = 128
    context: int = 1
    base: int = 8
    levels: int = 4
    epochs: int = 20
    batch: int = 16
    lr: float = 3e-3
    neg_ratio: float = 0.5
    shift: int = 8
    scale: float = 0.0
    rotate_deg: float = 0.0
    framing: str = "mm"
    slice_dice: float = 1.0

    def __post_init__(self) -> None:
        # tumor3d.learned.cnn_data.FRAMINGS, spelled here: this module runs where only
        # numpy and torch are installed (the training worker of benchmarks/cnn_cv.py)
        if self.framing not in ("slice", "head", "mm"):
            raise InputError(f"U-Net framing must be 'slice', 'head' or 'mm', got {self.framing!r}")
        if self.size % 2 ** (self.levels - 1):
            raise InputError(
                f"U-Net size {self.size} is not divisible by 2**(levels-1) = "
                f"{2 ** (self.levels - 1)}"
            )
        for name in ("size", "base", "levels", "epochs", "batch"):
            if getattr(self, name) < 1:
                raise InputError(f"U-Net {name} must be at least 1")
        if self.context < 0 or self.shift < 0 or self.lr <= 0 or self.neg_ratio < 0:
            raise InputError("U-Net context, shift and neg_ratio must be >= 0, lr > 0")
        if not self.slice_dice >= 0:  # NaN too
            raise InputError("U-Net slice_dice must be >= 0")
        if not (0.0 <= self.scale < 0.5 and 0.0 <= self.rotate_deg <= 45.0):
            raise InputError("U-Net scale must lie in [0, 0.5) and rotate_deg in [0, 45]")


@dataclass
class UNetFit:
    """A trained torch network and how its training went."""

    model: Any  # torch.nn.Module, in eval mode
    slices_per_epoch: int
    seconds: float
    losses: list[float]  # mean loss of each epoch


def require_torch() -> Any:
    """The ``torch`` module, or an :class:`InputError` naming the ``train`` extra."""
    try:
        import torch
    except ImportError:
        raise InputError(
            "training the U-Net needs PyTorch: pip install 'tumor3d[train]' "
            "(CPU wheels: --extra-index-url https://download.pytorch.org/whl/cpu)"
        ) from None
    return torch


# ---------------------------------------------------------------- the slices of one patient


def unet_slices(
    image: np.ndarray,
    label: np.ndarray,
    settings: UNetSettings = UNetSettings(),
    pixel_mm: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One patient's network input ``(z, 2 context + 1, s, s)`` and target ``(z, s, s)``.

    ``image`` is the scan as acquired ``(z, y, x)`` (the raw intensities: the
    input is normalised here, as at inference); ``label`` the boolean
    reference on the same grid. Both float16. ``pixel_mm``: the (row, column)
    spacing, which the ``"mm"`` framing needs.
    """
    from tumor3d.learned.cnn_data import case_input, case_target, frame_of

    if np.shape(image) != np.shape(label):
        raise InputError(f"image {np.shape(image)} and label {np.shape(label)} differ in shape")
    if settings.framing == "mm" and pixel_mm is None:
        raise InputError("the 'mm' framing needs the slices' pixel spacing (pixel_mm)")
    frame = frame_of(image, settings.framing, pixel_mm)
    return (
        case_input(image, settings.size, settings.context, frame),
        case_target(np.asarray(label, bool), settings.size, frame),
    )


def slices_to_bytes(x: np.ndarray, y: np.ndarray) -> bytes:
    """One patient's slices as ``.npz`` bytes (plain arrays)."""
    buf = io.BytesIO()
    np.savez(buf, x=np.asarray(x, np.float16), y=np.asarray(y, np.float16))
    return buf.getvalue()


def slices_from_bytes(data: bytes, *, source: str = "slices") -> tuple[np.ndarray, np.ndarray]:
    """The ``(x, y)`` of :func:`slices_to_bytes` (never unpickles)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            x, y = z["x"], z["y"]
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"{source}: not U-Net training slices ({exc})") from None
    if x.ndim != 4 or y.shape != (x.shape[0], *x.shape[2:]):
        raise InputError(f"{source}: not U-Net training slices (x {x.shape}, y {y.shape})")
    return x, y


# ---------------------------------------------------------------- the network (torch)


def torch_unet(in_channels: int, base: int, levels: int) -> Any:
    """The torch U-Net :mod:`tumor3d.learned.cnn` runs (its docstring describes it)."""
    torch = require_torch()
    nn = torch.nn
    F = torch.nn.functional

    class Block(nn.Sequential):
        def __init__(self, i: int, o: int) -> None:
            super().__init__(
                nn.Conv2d(i, o, 3, padding=1, bias=False),
                nn.BatchNorm2d(o),
                nn.ReLU(inplace=True),
                nn.Conv2d(o, o, 3, padding=1, bias=False),
                nn.BatchNorm2d(o),
                nn.ReLU(inplace=True),
            )

    class UNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            ch = [base * 2**i for i in range(levels)]
            self.enc = nn.ModuleList()
            c = in_channels
            for o in ch:
                self.enc.append(Block(c, o))
                c = o
            self.dec = nn.ModuleList()
            for o in reversed(ch[:-1]):
                self.dec.append(Block(c + o, o))
                c = o
            self.head = nn.Conv2d(c, 1, 1)

        def forward(self, x: Any) -> Any:
            skips = []
            for i, e in enumerate(self.enc):
                x = e(x)
                if i < len(self.enc) - 1:
                    skips.append(x)
                    x = F.max_pool2d(x, 2)
            for d in self.dec:
                x = F.interpolate(x, scale_factor=2, mode="nearest")
                x = d(torch.cat([x, skips.pop()], 1))
            return self.head(x)[:, 0]

    return UNet()


def _scale_rotate(torch: Any, xb: Any, yb: Any, rng: Any, scale: float, rotate_deg: float):
    """Each slice of a batch scaled and rotated about its centre (bilinear).

    ``xb`` ``(n, c, s, s)``, targets ``yb`` ``(n, s, s)``: a factor within ``1 +- scale``
    and an angle within ``+- rotate_deg``; the image's border value outside it, no tumour
    outside the target.
    """
    F = torch.nn.functional
    n = xb.shape[0]
    zoom = rng.uniform(1.0 - scale, 1.0 + scale, n)
    angle = np.deg2rad(rng.uniform(-rotate_deg, rotate_deg, n))
    c, si = np.cos(angle) / zoom, np.sin(angle) / zoom  # output -> input coordinates
    theta = np.zeros((n, 2, 3), np.float32)
    theta[:, 0, 0], theta[:, 0, 1], theta[:, 1, 0], theta[:, 1, 1] = c, -si, si, c
    grid = F.affine_grid(torch.from_numpy(theta), list(xb.shape), align_corners=False)
    xb = F.grid_sample(xb, grid, mode="bilinear", padding_mode="border", align_corners=False)
    yb = F.grid_sample(
        yb[:, None], grid, mode="bilinear", padding_mode="zeros", align_corners=False
    )
    return xb, yb[:, 0]


def fit_unet(
    x: np.ndarray,
    y: np.ndarray,
    settings: UNetSettings = UNetSettings(),
    *,
    seed: int = 0,
    rows: np.ndarray | None = None,
    threads: int | None = None,
    log: Callable[[str], None] | None = None,
) -> UNetFit:
    """Train a U-Net on slices ``x`` ``(n, c, s, s)`` and targets ``y`` ``(n, s, s)`` in [0, 1].

    ``rows``: the slices to train on (default all); ``threads``: torch's thread
    count (process-wide; default unchanged); ``log`` receives one line per epoch.
    """
    torch = require_torch()
    F = torch.nn.functional
    if x.ndim != 4 or y.shape != (x.shape[0], *x.shape[2:]):
        raise InputError(f"U-Net slices x {x.shape} and targets y {y.shape} do not match")
    tr = np.arange(len(x)) if rows is None else np.asarray(rows)
    if threads is not None:
        torch.set_num_threads(int(threads))
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    pos = tr[y[tr].reshape(len(tr), -1).max(axis=1) > 0]
    if len(pos) == 0:
        raise InputError("no training slice holds tumour: the U-Net needs some")
    neg = np.setdiff1d(tr, pos)
    s = settings
    model = torch_unet(x.shape[1], s.base, s.levels)
    opt = torch.optim.Adam(model.parameters(), lr=s.lr, weight_decay=1e-5)
    n_neg = min(len(neg), int(round(s.neg_ratio * len(pos))))
    steps_per_epoch = int(np.ceil((len(pos) + n_neg) / s.batch))
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=s.lr, total_steps=s.epochs * steps_per_epoch, pct_start=0.15
    )
    losses = []
    t0 = time.perf_counter()
    for ep in range(s.epochs):
        model.train()
        order = rng.permutation(np.concatenate([pos, rng.choice(neg, n_neg, replace=False)]))
        tot = 0.0
        for start in range(0, len(order), s.batch):
            b = np.sort(order[start : start + s.batch])
            xb = torch.from_numpy(x[b].astype(np.float32))
            yb = torch.from_numpy(y[b].astype(np.float32))
            if rng.random() < 0.5:  # left-right flip (the image's column axis)
                xb, yb = xb.flip(-1), yb.flip(-1)
            dy, dx = rng.integers(-s.shift, s.shift + 1, 2)
            xb = torch.roll(xb, (int(dy), int(dx)), (-2, -1))
            yb = torch.roll(yb, (int(dy), int(dx)), (-2, -1))
            g = torch.from_numpy(rng.uniform(0.9, 1.1, (len(b), 1, 1, 1)).astype(np.float32))
            o = torch.from_numpy(rng.uniform(-0.1, 0.1, (len(b), 1, 1, 1)).astype(np.float32))
            xb = xb * g + o
            if s.scale or s.rotate_deg:  # drawn only then: the default stream is unchanged
                xb, yb = _scale_rotate(torch, xb, yb, rng, s.scale, s.rotate_deg)
            logit = model(xb)
            p = torch.sigmoid(logit)
            inter = (p * yb).sum()
            soft_dice = 1 - (2 * inter + 1) / (p.sum() + yb.sum() + 1)
            loss = F.binary_cross_entropy_with_logits(logit, yb) + soft_dice
            if s.slice_dice:
                loss = loss + s.slice_dice * per_slice_soft_dice(p, yb)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            tot += float(loss.detach()) * len(b)
        losses.append(tot / len(order))
        if log is not None:
            log(
                f"epoch {ep + 1}/{s.epochs}: loss {losses[-1]:.4f} "
                f"({time.perf_counter() - t0:.0f} s)"
            )
    model.eval()
    return UNetFit(model, int(len(pos) + n_neg), time.perf_counter() - t0, losses)


def per_slice_soft_dice(p: Any, y: Any) -> Any:
    """The per-slice soft Dice loss of ``p`` against ``y`` (both ``(n, s, s)`` tensors).

    1 - the soft Dice of each slice, the mean over the slices where ``y`` holds tumour
    (0 if none does): each cross-section weighs the same, however small.
    """
    ps, ys = p.flatten(1), y.flatten(1)
    has = ys.sum(1) > 0
    if not bool(has.any()):
        return p.sum() * 0.0
    d = 1 - (2 * (ps * ys).sum(1) + 1) / (ps.sum(1) + ys.sum(1) + 1)
    return d[has].mean()


def torch_probability(model: Any, x: np.ndarray, batch: int = 32) -> np.ndarray:
    """The torch network's probabilities ``(n, s, s)`` float32 of slices ``x`` (eval mode)."""
    torch = require_torch()
    model.eval()
    out = np.empty((len(x), *x.shape[2:]), np.float32)
    with torch.no_grad():
        for s in range(0, len(x), batch):
            xb = torch.from_numpy(np.asarray(x[s : s + batch], np.float32))
            out[s : s + len(xb)] = torch.sigmoid(model(xb)).numpy()
    return out


def unet_to_bytes(model: Any, meta: dict[str, Any] | None = None) -> bytes:
    """The trained network as ``.npz`` bytes :func:`tumor3d.learned.cnn.unet_from_bytes` reads.

    Each convolution's batch normalisation is folded into its weights and bias
    (the network in eval mode computes the same); ``meta`` (JSON-able) goes in
    as ``meta_json``, the UTF-8 bytes of its JSON as a uint8 array.
    """
    out: dict[str, np.ndarray] = {}
    if meta is not None:
        out[META_KEY] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8)

    def fold(block: Any, name: str) -> None:
        convs = [m for m in block if m.__class__.__name__ == "Conv2d"]
        bns = [m for m in block if m.__class__.__name__ == "BatchNorm2d"]
        for j, (c, bn) in enumerate(zip(convs, bns, strict=True)):
            s = (bn.weight / (bn.running_var + bn.eps).sqrt()).detach().numpy()
            w = c.weight.detach().numpy() * s[:, None, None, None]
            b = bn.bias.detach().numpy() - bn.running_mean.detach().numpy() * s
            out[f"{name}_{j}_w"] = w.astype(np.float32)
            out[f"{name}_{j}_b"] = b.astype(np.float32)

    for i, e in enumerate(model.enc):
        fold(e, f"enc{i}")
    for i, d in enumerate(model.dec):
        fold(d, f"dec{i}")
    out["head_w"] = model.head.weight.detach().numpy().astype(np.float32)
    out["head_b"] = model.head.bias.detach().numpy().astype(np.float32)
    buf = io.BytesIO()
    np.savez(buf, **out)
    return buf.getvalue()


def unet_meta(data: bytes) -> dict[str, Any]:
    """The ``meta_json`` of a weight file's bytes ({} when it has none; never unpickles)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if META_KEY not in z.files:
                return {}
            raw = z[META_KEY]
    except (OSError, ValueError) as exc:
        raise InputError(f"not a readable .npz of plain arrays ({exc})") from None
    return dict(decode_meta(raw))


def train_unet(
    x: np.ndarray,
    y: np.ndarray,
    settings: UNetSettings = UNetSettings(),
    *,
    seed: int = 0,
    meta: dict[str, Any] | None = None,
    threads: int | None = None,
    log: Callable[[str], None] | None = None,
) -> tuple[bytes, UNetFit]:
    """:func:`fit_unet` on every slice, then :func:`unet_to_bytes`: (bytes, the fit).

    The settings, seed, torch version, slices and wall time are added to ``meta``.
    """
    torch = require_torch()
    fit = fit_unet(x, y, settings, seed=seed, threads=threads, log=log)
    info = {
        "trainer": f"torch {torch.__version__}",
        "settings": asdict(settings),
        "seed": int(seed),
        "train_slices": int(len(x)),
        "slices_per_epoch": fit.slices_per_epoch,
        "train_wall_s": round(fit.seconds, 1),
        "final_loss": round(fit.losses[-1], 4),
    }
    info.update(meta or {})
    return unet_to_bytes(fit.model, info), fit

"""Annotation after rendering (Pillow): orientation letters, scale bar, turntable GIF."""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import numpy as np

from tumor3d.errors import InputError
from tumor3d.visual.render.camera import Camera
from tumor3d.visual.render.checks import _check_int


def _scale_bar_length_mm(width: int, px_mm: float) -> float:
    """The largest 1-2-5 x 10^k mm length at most a quarter of the image width."""
    target = 0.25 * width / px_mm
    k = math.floor(math.log10(target))
    best = 10.0**k
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10.0**k <= target:
            best = m * 10.0**k
    return float(best)


def _font(size_px: int):  # noqa: ANN202 - a Pillow font object
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size_px)
    except (TypeError, OSError, ImportError):  # Pillow without FreeType
        return ImageFont.load_default()


def _annotate(img: np.ndarray, cam: Camera, background: np.ndarray, bar_mm: float) -> np.ndarray:
    """Draw edge orientation letters and a scale bar (bottom left)."""
    from PIL import Image, ImageDraw

    h, w = img.shape[:2]
    lum = float(background @ np.array([0.2126, 0.7152, 0.0722]))
    ink = (0, 0, 0) if lum > 0.5 else (255, 255, 255)
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    size = max(10, min(h, w) // 24)
    font = _font(size)
    pad = max(3, size // 4)
    labels = cam.edge_labels()
    anchors = {
        "left": ((pad, h / 2), "lm"),
        "right": ((w - 1 - pad, h / 2), "rm"),
        "top": ((w / 2, pad), "mt"),
        "bottom": ((w / 2, h - 1 - pad), "mb"),
    }
    for edge, ((x, y), anchor) in anchors.items():
        if labels[edge]:
            draw.text((x, y), labels[edge], fill=ink, font=font, anchor=anchor)
    bar_px = int(round(bar_mm * cam.pixels_per_mm))
    x0, y1 = pad, h - 1 - pad
    thick = max(2, size // 6)
    draw.rectangle([x0, y1 - thick + 1, x0 + bar_px - 1, y1], fill=ink)
    text = f"{bar_mm:g} mm"
    draw.text(
        (x0, y1 - thick - 2), text, fill=ink, font=_font(max(8, (size * 3) // 4)), anchor="lb"
    )
    return np.asarray(pil, dtype=np.uint8).copy()


def turntable_gif(frames: Sequence[np.ndarray], *, frame_ms: int = 100) -> bytes:
    """Encode turntable frames as a looping animated GIF (Pillow).

    Parameters
    ----------
    frames : sequence of (h, w, 3) uint8 ndarray
        The frames, all the same shape (``RenderResult.turntable``).
    frame_ms : int
        Display time per frame in milliseconds (10-10000).

    Returns
    -------
    bytes
        The GIF file content; the same frames give the same bytes.
    """
    from PIL import Image

    frames = list(frames)
    if not frames:
        raise InputError("turntable_gif needs at least one frame")
    shape = np.asarray(frames[0]).shape
    for k, f in enumerate(frames):
        a = np.asarray(f)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3 or a.shape != shape:
            raise InputError(f"frame {k} must be a uint8 (h, w, 3) array of shape {shape}")
    frame_ms = _check_int(frame_ms, "frame_ms", 10, 10000)
    # one shared palette from the first frame keeps the colours stable and the bytes deterministic
    first = Image.fromarray(np.asarray(frames[0])).quantize(
        colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
    )
    pal = [first] + [
        Image.fromarray(np.asarray(f)).quantize(palette=first, dither=Image.Dither.NONE)
        for f in frames[1:]
    ]
    buf = io.BytesIO()
    pal[0].save(
        buf,
        format="GIF",
        save_all=True,
        append_images=pal[1:],
        duration=frame_ms,
        loop=0,
        optimize=False,
        disposal=1,
    )
    return buf.getvalue()

"""What the cheaper publishing must keep: the PNG encoder's pixels (issue 32 item 3).

:func:`tumor3d.storage.formats.encode_png` writes its own PNG (the "Up" filter,
zlib level 2) instead of Pillow's; these tests decode it with Pillow (an
independent reader) and with a naive reading of the PNG format written here.
"""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from tumor3d.storage import formats


def _images() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:97, 0:131]
    smooth = ((yy * 3 + xx * 2) % 256).astype(np.uint8)
    # an overlay-like tile: dark background, a grey disc, a one-pixel coloured contour;
    # rows that go 255 -> 0 -> 255 make the Up filter wrap modulo 256 both ways
    tile = np.zeros((97, 131, 3), np.uint8)
    disc = (yy - 48) ** 2 + (xx - 65) ** 2 < 40**2
    tile[disc] = 120
    ring = disc & ~((yy - 48) ** 2 + (xx - 65) ** 2 < 39**2)
    tile[ring] = (255, 40, 0)
    tile[::2, :5] = 255
    return {
        "rgb random": rng.integers(0, 256, size=(33, 47, 3), dtype=np.uint8),
        "grey random": rng.integers(0, 256, size=(29, 18), dtype=np.uint8),
        "rgba random": rng.integers(0, 256, size=(5, 9, 4), dtype=np.uint8),
        "grey smooth": smooth,
        "rgb tile": tile,
        "one pixel": np.array([[[1, 2, 3]]], np.uint8),
        "one row": rng.integers(0, 256, size=(1, 64, 3), dtype=np.uint8),
        "one column": rng.integers(0, 256, size=(64, 1), dtype=np.uint8),
        "not contiguous": np.asfortranarray(rng.integers(0, 256, size=(20, 30, 3), dtype=np.uint8)),
    }


IMAGES = _images()


def _pillow_pixels(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as img:
        img.load()
        return np.asarray(img)


def _naive_decode(data: bytes) -> np.ndarray:
    """PNG -> pixels with plain Python loops, for the filter types 0 to 4 (PNG spec, 9.2)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        tag, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])
        assert crc == zlib.crc32(tag + body), tag
        if tag == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat += body
        pos += 12 + n
    assert header is not None
    w, h, depth, colour, _, _, interlace = header
    assert depth == 8 and interlace == 0
    channels = {0: 1, 2: 3, 6: 4}[colour]
    stride = w * channels
    raw = zlib.decompress(idat)
    assert len(raw) == h * (stride + 1)
    out: list[list[int]] = []
    prev = [0] * stride
    for r in range(h):
        kind, line = raw[r * (stride + 1)], raw[r * (stride + 1) + 1 : (r + 1) * (stride + 1)]
        row: list[int] = []
        for i, v in enumerate(line):
            a = row[i - channels] if i >= channels else 0
            b = prev[i]
            c = prev[i - channels] if i >= channels else 0
            if kind == 0:
                pred = 0
            elif kind == 1:
                pred = a
            elif kind == 2:
                pred = b
            elif kind == 3:
                pred = (a + b) // 2
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            row.append((v + pred) % 256)
        out.append(row)
        prev = row
    arr = np.array(out, dtype=np.uint8).reshape(h, w, channels)
    return arr[:, :, 0] if channels == 1 else arr


@pytest.mark.parametrize("name", list(IMAGES))
def test_png_pixels_are_the_arrays(name):
    image = IMAGES[name]
    data = formats.encode_png(image)
    assert formats.encode_png(image) == data  # deterministic: the artifact's digest is its content
    np.testing.assert_array_equal(_pillow_pixels(data), image)
    np.testing.assert_array_equal(_naive_decode(data), image)


@pytest.mark.parametrize("name", ["rgb random", "grey smooth", "rgb tile"])
def test_png_same_pixels_as_pillows_own_encoding(name):
    image = IMAGES[name]
    sink = io.BytesIO()
    Image.fromarray(image).save(sink, format="PNG")
    np.testing.assert_array_equal(
        _pillow_pixels(formats.encode_png(image)), _pillow_pixels(sink.getvalue())
    )
    if image.ndim == 3:  # decode_png (RGB) reads it back too
        np.testing.assert_array_equal(formats.decode_png(formats.encode_png(image)), image)


def test_png_compresses_a_flat_image():
    image = np.zeros((400, 300, 3), np.uint8)
    image[100:300, 50:250] = (90, 90, 90)
    data = formats.encode_png(image)
    assert len(data) < image.nbytes / 100
    np.testing.assert_array_equal(_pillow_pixels(data), image)


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((4, 4, 3), np.float32),
        np.zeros((4, 4, 2), np.uint8),
        np.zeros((4,), np.uint8),
        np.zeros((0, 4, 3), np.uint8),
        np.zeros((4, 0), np.uint8),
    ],
)
def test_png_refuses_what_it_cannot_write(bad):
    with pytest.raises(ValueError, match="PNG needs"):
        formats.encode_png(bad)

"""The numpy U-Net forward pass (``tumor3d.learned.cnn``) against a naive per-pixel reference.

The reference below is written independently: a convolution as an explicit
sum over output pixel, output channel, input channel and kernel tap, max
pooling and upsampling pixel by pixel. A tiny random net (2 and 3 levels)
must give the same logits.
"""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.learned.cnn import (
    UNetWeights,
    conv2d,
    unet_from_bytes,
    unet_logits,
    unet_probability,
    unet_volume_probability,
)


def naive_conv(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x (c, h, w) -> (o, h, w), zero padding, cross-correlation, one pixel at a time."""
    o, c, kh, kw = w.shape
    _, h, wd = x.shape
    out = np.zeros((o, h, wd))
    for oc in range(o):
        for y in range(h):
            for xx in range(wd):
                s = float(b[oc])
                for ic in range(c):
                    for dy in range(kh):
                        for dx in range(kw):
                            yy, xs = y + dy - kh // 2, xx + dx - kw // 2
                            if 0 <= yy < h and 0 <= xs < wd:
                                s += float(w[oc, ic, dy, dx]) * float(x[ic, yy, xs])
                out[oc, y, xx] = s
    return out


def naive_unet(a: dict, levels: int, x: np.ndarray) -> np.ndarray:
    """One image (c, h, w) -> logits (h, w), the architecture spelled out."""

    def block(h, name):
        for j in (0, 1):
            h = np.maximum(naive_conv(h, a[f"{name}_{j}_w"], a[f"{name}_{j}_b"]), 0.0)
        return h

    def pool(h):
        c, hh, ww = h.shape
        out = np.zeros((c, hh // 2, ww // 2))
        for k in range(c):
            for y in range(hh // 2):
                for xx in range(ww // 2):
                    out[k, y, xx] = max(
                        h[k, 2 * y, 2 * xx],
                        h[k, 2 * y + 1, 2 * xx],
                        h[k, 2 * y, 2 * xx + 1],
                        h[k, 2 * y + 1, 2 * xx + 1],
                    )
        return out

    def up(h):
        c, hh, ww = h.shape
        out = np.zeros((c, 2 * hh, 2 * ww))
        for y in range(2 * hh):
            for xx in range(2 * ww):
                out[:, y, xx] = h[:, y // 2, xx // 2]
        return out

    h = x.astype(np.float64)
    skips = []
    for i in range(levels):
        h = block(h, f"enc{i}")
        if i < levels - 1:
            skips.append(h)
            h = pool(h)
    for i in range(levels - 1):
        h = block(np.concatenate([up(h), skips.pop()], axis=0), f"dec{i}")
    return naive_conv(h, a["head_w"], a["head_b"])[0]


def he(rng, o: int, ci: int) -> np.ndarray:
    """3 x 3 weights with He's spread (logits of a few units, no overflow)."""
    return rng.normal(0, np.sqrt(2.0 / (9 * ci)), (o, ci, 3, 3)).astype(np.float32)


def random_unet(rng, cin: int, base: int, levels: int) -> dict:
    a = {}
    ch = [base * 2**i for i in range(levels)]
    c = cin
    for i, o in enumerate(ch):
        for j, ci in enumerate((c, o)):
            a[f"enc{i}_{j}_w"] = he(rng, o, ci)
            a[f"enc{i}_{j}_b"] = rng.normal(0, 0.1, o).astype(np.float32)
        c = o
    for i, o in enumerate(reversed(ch[:-1])):
        for j, ci in enumerate((c + o, o)):
            a[f"dec{i}_{j}_w"] = he(rng, o, ci)
            a[f"dec{i}_{j}_b"] = rng.normal(0, 0.1, o).astype(np.float32)
        c = o
    a["head_w"] = rng.normal(0, 0.5, (1, c, 1, 1)).astype(np.float32)
    a["head_b"] = rng.normal(0, 0.1, 1).astype(np.float32)
    return a


def test_conv2d_matches_naive_convolution():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(3, 7, 9)).astype(np.float32)
    w = rng.normal(size=(4, 3, 3, 3)).astype(np.float32)
    b = rng.normal(size=4).astype(np.float32)
    got = conv2d(np.ascontiguousarray(x.transpose(1, 2, 0)), w, b).transpose(2, 0, 1)
    np.testing.assert_allclose(got, naive_conv(x, w, b), rtol=1e-4, atol=1e-4)
    # an asymmetric kernel catches a flipped (convolution instead of correlation) tap order
    w5 = rng.normal(size=(2, 3, 5, 5)).astype(np.float32)
    got5 = conv2d(np.ascontiguousarray(x.transpose(1, 2, 0)), w5, b[:2]).transpose(2, 0, 1)
    np.testing.assert_allclose(got5, naive_conv(x, w5, b[:2]), rtol=1e-4, atol=1e-4)
    # a wide input (more than 16 channels: one product per tap, no copy), batched (n, h, w, c)
    xw = rng.normal(size=(2, 20, 6, 5)).astype(np.float32)
    got_w = conv2d(np.ascontiguousarray(xw.transpose(0, 2, 3, 1)), w5[:, :1].repeat(20, 1), b[:2])
    for n in range(2):
        want = naive_conv(xw[n], w5[:, :1].repeat(20, 1), b[:2])
        np.testing.assert_allclose(got_w[n].transpose(2, 0, 1), want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("levels", [2, 3])
def test_unet_matches_naive_reference(tmp_path, levels):
    rng = np.random.default_rng(levels)
    a = random_unet(rng, cin=3, base=2, levels=levels)
    path = tmp_path / "net.npz"
    np.savez(path, **a)
    net = unet_from_bytes(path.read_bytes())
    assert net.levels == levels and net.in_channels == 3
    # 3 images: the forward pass batches 2 slices at a time, the last batch holds one
    x = rng.normal(size=(3, 3, 8, 12)).astype(np.float32)
    got = unet_logits(net, x)
    want = np.stack([naive_unet(a, levels, xi) for xi in x])
    assert got.shape == (3, 8, 12)
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-3 * np.abs(want).max())
    p = unet_probability(net, x)
    np.testing.assert_allclose(p, np.exp(-np.logaddexp(0.0, -want)), atol=1e-4)


def test_unet_rejects_bad_input(tmp_path):
    a = random_unet(np.random.default_rng(0), cin=1, base=2, levels=3)
    net = UNetWeights(a, 3)
    with pytest.raises(InputError):
        unet_logits(net, np.zeros((1, 2, 8, 8)))  # wrong channel count
    with pytest.raises(InputError):
        unet_logits(net, np.zeros((1, 1, 6, 8)))  # 6 not divisible by 4
    np.savez(tmp_path / "x.npz", foo=np.zeros(3))
    with pytest.raises(InputError):
        unet_from_bytes((tmp_path / "x.npz").read_bytes())
    np.savez(tmp_path / "o.npz", w=np.array([{"a": 1}], dtype=object))  # a pickled array
    with pytest.raises(InputError):
        unet_from_bytes((tmp_path / "o.npz").read_bytes())


def _npz_bytes(arrays: dict, meta: dict | None = None) -> bytes:
    import io
    import json

    buf = io.BytesIO()
    extra = {}
    if meta is not None:
        extra["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(buf, **arrays, **extra)
    return buf.getvalue()


def test_weight_file_metadata_sets_the_input_grid_and_the_digest():
    import hashlib

    a = random_unet(np.random.default_rng(5), cin=5, base=2, levels=2)
    data = _npz_bytes(a, {"settings": {"size": 16, "context": 2}, "trained_on": "x"})
    net = unet_from_bytes(data, source="w.npz")
    assert (net.size, net.context, net.in_channels) == (16, 2, 5)
    assert net.meta["trained_on"] == "x" and "meta_json" not in net.arrays
    assert net.sha256 == hashlib.sha256(data).hexdigest()
    # without metadata: the grid of the cross-validation (128 x 128, one neighbour each side)
    plain = unet_from_bytes(_npz_bytes(random_unet(np.random.default_rng(5), 3, 2, 2)))
    assert (plain.size, plain.context, plain.meta) == (128, 1, {})
    with pytest.raises(InputError, match="w.npz: 5 input channels but context 1"):
        unet_from_bytes(_npz_bytes(a, {"settings": {"size": 16, "context": 1}}), source="w.npz")
    del a["dec0_1_b"]
    with pytest.raises(InputError, match="missing dec0_1_b"):
        unet_from_bytes(_npz_bytes(a), source="w.npz")


def test_volume_probability_is_the_network_on_its_grid_back_on_the_native_one():
    """Slices (z, y, x) -> case_input at the file's size and context -> the net ->
    upsample to (y, x): the grids of the cross-validation (tumor3d.learned.cnn_data)."""
    from tumor3d.learned.cnn_data import case_input, upsample

    rng = np.random.default_rng(6)
    a = random_unet(rng, cin=3, base=2, levels=2)
    net = unet_from_bytes(_npz_bytes(a, {"settings": {"size": 12, "context": 1}}))
    vol = rng.normal(100.0, 20.0, (5, 30, 26)).astype(np.float32)
    vol[:, :4] = 0.0  # some background
    got = unet_volume_probability(net, vol, mirror=False)
    x = case_input(vol, 12, 1).astype(np.float32)
    small = np.stack([1.0 / (1.0 + np.exp(-naive_unet(a, 2, xi))) for xi in x])
    want = upsample(small.astype(np.float32), vol.shape)
    assert got.shape == vol.shape and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-4)
    np.testing.assert_array_equal(unet_volume_probability(net, vol), got)  # one pass: default
    # mirror: the mean with the mirrored pass, mirrored back, on the net's grid
    small_m = np.stack(
        [1.0 / (1.0 + np.exp(-naive_unet(a, 2, xi[..., ::-1])))[..., ::-1] for xi in x]
    )
    want_m = upsample((0.5 * (small + small_m)).astype(np.float32), vol.shape)
    np.testing.assert_allclose(unet_volume_probability(net, vol, mirror=True), want_m, atol=1e-4)
    with pytest.raises(InputError, match="3-D"):
        unet_volume_probability(net, vol[0])


def test_an_ensembles_volume_probability_is_the_mean_of_its_nets():
    """Nets on one grid (averaged there) and on another (averaged after the upsampling):
    the mean of each net's own volume probability, with the mirrored pass or without
    (the pipeline's)."""
    rng = np.random.default_rng(9)
    vol = rng.normal(100.0, 20.0, (4, 30, 26)).astype(np.float32)
    grids = ((12, 1), (12, 1), (16, 0))
    nets = [
        unet_from_bytes(
            _npz_bytes(random_unet(rng, 2 * c + 1, 2, 2), {"settings": {"size": n, "context": c}})
        )
        for n, c in grids
    ]
    for mirror in (False, True):
        singles = [unet_volume_probability(n, vol, mirror=mirror) for n in nets]
        assert min(float(np.abs(singles[0] - p).max()) for p in singles[1:]) > 0.01  # unlike
        got = unet_volume_probability(nets, vol, mirror=mirror)
        assert got.shape == vol.shape and got.dtype == np.float32
        np.testing.assert_allclose(got, np.mean(singles, axis=0), atol=1e-5)
        np.testing.assert_array_equal(unet_volume_probability(nets[:1], vol, mirror=mirror),
                                      singles[0])  # fmt: skip
    for bad in ((), (nets[0], "net")):
        with pytest.raises(InputError, match="non-empty sequence"):
            unet_volume_probability(bad, vol)


def test_mirrored_probability_is_mirror_equivariant_and_the_plain_one_is_not():
    """A left-right flipped slice gets the flipped answer with ``mirror=True`` (exactly,
    up to float rounding); a random network alone is not symmetric, so without it the
    two differ: the property is the augmentation's, not the network's."""
    rng = np.random.default_rng(11)
    net = unet_from_bytes(_npz_bytes(random_unet(rng, cin=3, base=3, levels=3)))
    x = rng.normal(0.0, 1.0, (4, 3, 16, 24)).astype(np.float32)
    xf = np.ascontiguousarray(x[..., ::-1])
    m, mf = unet_probability(net, x, mirror=True), unet_probability(net, xf, mirror=True)
    assert m.shape == (4, 16, 24) and m.dtype == np.float32
    np.testing.assert_allclose(mf, m[..., ::-1], atol=1e-6)
    p, pf = unet_probability(net, x), unet_probability(net, xf)
    assert np.abs(pf - p[..., ::-1]).max() > 1e-3
    np.testing.assert_allclose(m, 0.5 * (p + pf[..., ::-1]), atol=1e-6)


def _head(shape=(4, 40, 36)) -> np.ndarray:
    """A textured ellipse of tissue (rows 6-30, columns 10-30) in zero air, ``(z, y, x)``:
    round, as a head is, so the box around it holds air in its corners."""
    yy, xx = np.mgrid[: shape[1], : shape[2]]
    inside = ((yy - 18) / 12.5) ** 2 + ((xx - 20) / 10.5) ** 2 <= 1
    rng = np.random.default_rng(11)
    return np.where(inside, rng.normal(100.0, 15.0, shape), 0.0).astype(np.float32)


@pytest.mark.parametrize("framing", ["head", "mm"])
def test_a_framed_net_sees_the_same_pixels_whatever_air_surrounds_the_head(framing):
    """``head``: the square around the tissue (its extent plus the margin each side);
    ``mm``: FRAME_MM millimetres each way, centred on the tissue. Either way the same head
    padded with air, cropped to it, or off centre in a wider slice goes in as the same
    pixels and its probability comes back on the same voxels; the whole slice
    (``framing: slice``, the shipped nets) sees the field of view."""
    from tumor3d.learned.cnn_data import FRAME_MM, HEAD_MARGIN, case_input, frame_of, upsample

    vol = _head()
    pixel_mm = (8.0, 6.0)
    y0, x0, rows, cols = frame_of(vol, framing, pixel_mm)
    if framing == "head":  # rows 6-30: 25 px, the longer extent
        assert rows == cols == int(np.ceil(25 * (1 + 2 * HEAD_MARGIN)))
    else:
        assert (rows, cols) == (round(FRAME_MM / 8.0), round(FRAME_MM / 6.0))
    assert abs((y0 + rows / 2) - 18.5) <= 0.5 and abs((x0 + cols / 2) - 20.5) <= 0.5
    variants = {  # (volume, where the original's pixel (0, 0) lies in it)
        "padded": (np.pad(vol, ((0, 0), (7, 30), (21, 4))), (7, 21)),
        "cropped": (vol[:, 5:32, 9:32], (-5, -9)),
    }
    want = case_input(vol, 16, 1, frame_of(vol, framing, pixel_mm))
    small = np.random.default_rng(3).random((4, 16, 16)).astype(np.float32)
    back = upsample(small, vol.shape, frame_of(vol, framing, pixel_mm))
    assert back[:, 6:31, 10:31].min() > 0
    if framing == "head":
        assert back[:, :, :3].max() == 0  # 0 beyond the frame
    for name, (v, (dy, dx)) in variants.items():
        frame = frame_of(v, framing, pixel_mm)
        assert frame == (y0 + dy, x0 + dx, rows, cols), name
        np.testing.assert_array_equal(case_input(v, 16, 1, frame), want, err_msg=name)
        got = upsample(small, v.shape, frame)
        # the pixels both hold, in the original's rows r0:r1 and columns c0:c1
        r0, r1 = max(0, -dy), min(vol.shape[1], v.shape[1] - dy)
        c0, c1 = max(0, -dx), min(vol.shape[2], v.shape[2] - dx)
        np.testing.assert_array_equal(
            got[:, r0 + dy : r1 + dy, c0 + dx : c1 + dx], back[:, r0:r1, c0:c1], err_msg=name
        )
    whole = case_input(variants["padded"][0], 16, 1, frame_of(vol, "slice"))
    assert not np.array_equal(whole, want)  # the whole slice: the air moves the scale


def test_a_weight_files_framing_is_read_from_its_settings_and_checked():
    """A net trained head-framed is run head-framed (one pass per framing, each back on
    the native grid); a file naming a framing the code does not know is refused."""
    from tumor3d.learned.cnn import unet_member_probabilities
    from tumor3d.learned.cnn_data import case_input, frame_of, upsample

    rng = np.random.default_rng(12)
    a = random_unet(rng, cin=3, base=2, levels=2)
    head = unet_from_bytes(_npz_bytes(a, {"settings": {"size": 12, "framing": "head"}}))
    whole = unet_from_bytes(_npz_bytes(a, {"settings": {"size": 12}}))
    assert (head.framing, whole.framing) == ("head", "slice")
    vol = _head()
    got = unet_member_probabilities([head, whole], vol)
    for i, framing in enumerate(("head", "slice")):
        frame = frame_of(vol, framing)
        x = case_input(vol, 12, 1, frame).astype(np.float32)
        small = np.stack([1.0 / (1.0 + np.exp(-naive_unet(a, 2, xi))) for xi in x])
        np.testing.assert_allclose(
            got[i], upsample(small.astype(np.float32), vol.shape, frame), atol=1e-4
        )
    assert float(np.abs(got[0] - got[1]).max()) > 0.01
    with pytest.raises(InputError, match="w.npz: framing 'brain' unknown"):
        unet_from_bytes(_npz_bytes(a, {"settings": {"framing": "brain"}}), source="w.npz")
    mm = unet_from_bytes(_npz_bytes(a, {"settings": {"size": 12, "framing": "mm"}}))
    with pytest.raises(InputError, match="framed in millimetres needs the pixel spacing"):
        unet_member_probabilities([mm], vol)
    assert unet_member_probabilities([mm], vol, pixel_mm=(8.0, 8.0)).shape == (1, *vol.shape)

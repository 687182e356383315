"""Training the U-Net (``tumor3d.learned.cnn_train``, issue 28).

Without torch (CI): the missing extra is named in one line, the per-patient
slices round-trip as plain arrays and planted pickles are refused, bad
settings are refused. With torch (``pytest.importorskip``; run with the
``train`` extra installed): a tiny U-Net (base 2, 2 levels, 2 epochs)
trained on phantoms, exported with batch norm folded, gives through the
numpy forward pass (:mod:`tumor3d.learned.cnn`, the independent
implementation inference uses) the torch network's own probabilities; the
same seed gives the same bytes; the metadata reads back.
"""

from __future__ import annotations

import io
import sys

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.learned.cnn_train import (
    UNetSettings,
    fit_unet,
    slices_from_bytes,
    slices_to_bytes,
    unet_meta,
    unet_slices,
)
from tumor3d.phantom import make_phantom_patient

TINY = UNetSettings(size=32, context=1, base=2, levels=2, epochs=2, batch=8)


@pytest.fixture(scope="module")
def phantom_slices():
    xs, ys = [], []
    for seed in (11, 12):
        p = make_phantom_patient(seed, modality="flair", n_slices=12)
        x, y = unet_slices(  # the shipped framing: 240 mm centred on the head
            p.scan.image, np.asarray(p.slice_masks) > 0.5, TINY, p.scan.pixel_spacing_mm
        )
        xs.append(x)
        ys.append(y)
    return np.concatenate(xs), np.concatenate(ys)


def test_without_torch_the_error_names_the_extra(monkeypatch, phantom_slices):
    monkeypatch.setitem(sys.modules, "torch", None)  # "import torch" raises ImportError
    x, y = phantom_slices
    with pytest.raises(InputError, match=r"PyTorch: pip install 'tumor3d\[train\]'") as info:
        fit_unet(x, y, TINY)
    assert "\n" not in str(info.value)


def test_patient_slices_are_the_inference_grid_and_round_trip(phantom_slices):
    x, y = phantom_slices
    assert x.shape == (24, 3, 32, 32) and y.shape == (24, 32, 32)
    assert x.dtype == y.dtype == np.float16
    # the target is the reference's area fraction: in [0, 1], tumour on some slices only
    per_slice = y.reshape(24, -1).max(axis=1)
    assert 0 < np.sum(per_slice > 0) < 24 and float(y.min()) >= 0 and float(y.max()) <= 1
    # 2.5-D: the middle channel of slice i is the first channel of slice i + 1
    assert np.array_equal(x[1:11, 1], x[2:12, 0])
    x2, y2 = slices_from_bytes(slices_to_bytes(x, y))
    assert np.array_equal(x2, x) and np.array_equal(y2, y)


def test_planted_pickles_and_bad_shapes_are_refused():
    buf = io.BytesIO()
    np.savez(buf, x=np.array([object()], dtype=object), y=np.zeros(1))
    with pytest.raises(InputError, match="not U-Net training slices"):
        slices_from_bytes(buf.getvalue(), source="planted")
    with pytest.raises(InputError, match="not U-Net training slices"):
        slices_from_bytes(slices_to_bytes(np.zeros((2, 3, 8, 8)), np.zeros((2, 4, 4))))
    with pytest.raises(InputError, match="differ in shape"):
        unet_slices(np.zeros((3, 16, 16)), np.zeros((3, 16, 8), bool), TINY)


def test_settings_the_network_cannot_take_are_refused():
    with pytest.raises(InputError, match="not divisible"):
        UNetSettings(size=36, levels=4)
    with pytest.raises(InputError, match="at least 1"):
        UNetSettings(epochs=0)
    with pytest.raises(InputError, match="scale must lie in"):
        UNetSettings(scale=0.5)
    with pytest.raises(InputError, match="rotate_deg in"):
        UNetSettings(rotate_deg=-1.0)
    with pytest.raises(InputError, match="framing must be 'slice', 'head' or 'mm'"):
        UNetSettings(framing="brain")
    with pytest.raises(InputError, match="slice_dice must be >= 0"):
        UNetSettings(slice_dice=-0.5)


def test_the_per_slice_dice_weighs_each_cross_section_the_same():
    """A missed one-pixel cross-section costs 1 - 1/2 (the +1 smoothing) on one of the four
    slices with tumour, an eighth of the term (each slice weighs the same), against a few
    hundredths of the batch's soft Dice; slices without tumour take no part; a perfect
    prediction costs nothing."""
    torch = pytest.importorskip("torch")
    from tumor3d.learned.cnn_train import per_slice_soft_dice

    y = torch.zeros(5, 16, 16)
    y[0, :8, :8] = y[1, 2:10, 2:10] = y[2, 4:12, 4:12] = 1.0
    y[3, 7, 7] = 1.0  # the one-pixel cross-section; slice 4 holds no tumour
    assert float(per_slice_soft_dice(y.clone(), y)) == pytest.approx(0.0, abs=1e-6)
    p = y.clone()
    p[3] = 0.0
    p[4, :4, :4] = 1.0  # false tumour on the empty slice: not the term's business
    by_slice = 1 - (2 * (p * y).sum((1, 2)) + 1) / (p.sum((1, 2)) + y.sum((1, 2)) + 1)
    assert float(per_slice_soft_dice(p, y)) == pytest.approx(float(by_slice[:4].mean()))
    assert float(per_slice_soft_dice(p, y)) == pytest.approx(0.125, abs=0.005)
    batch = 1 - (2 * (p * y).sum() + 1) / (p.sum() + y.sum() + 1)
    assert float(batch) < 0.1
    assert float(per_slice_soft_dice(p, torch.zeros_like(y))) == 0.0


def test_the_settings_framings_are_the_inference_grids():
    """The training worker spells the framings (numpy + torch only); they are cnn_data's,
    and a head-framed patient's slices are the inference's input and target in its frame."""
    from tumor3d.learned.cnn_data import FRAMINGS, case_input, case_target, frame_of

    for framing in FRAMINGS:
        UNetSettings(framing=framing)
    p = make_phantom_patient(11, modality="flair", n_slices=12)
    label = np.asarray(p.slice_masks) > 0.5
    head = UNetSettings(size=32, context=1, base=2, levels=2, framing="head")
    x, y = unet_slices(p.scan.image, label, head)
    frame = frame_of(p.scan.image, "head")
    assert frame is not None and frame[2] < p.scan.image.shape[1]  # the head, not the slice
    mm = UNetSettings(size=32, context=1, base=2, levels=2, framing="mm")
    pixel_mm = p.scan.pixel_spacing_mm
    with pytest.raises(InputError, match="'mm' framing needs the slices' pixel spacing"):
        unet_slices(p.scan.image, label, mm)
    xm, _ = unet_slices(p.scan.image, label, mm, pixel_mm)
    np.testing.assert_array_equal(
        xm, case_input(p.scan.image, 32, 1, frame_of(p.scan.image, "mm", pixel_mm))
    )
    np.testing.assert_array_equal(x, case_input(p.scan.image, 32, 1, frame))
    np.testing.assert_array_equal(y, case_target(label, 32, frame))


def test_scaling_and_rotation_move_image_and_target_together():
    """The training's scale / rotation augmentation against exact expectations: no change
    at 0, ``torch.rot90`` at 90 degrees, a square's area times the zoom squared, and the
    target moved with the image (a target that is the image's own mask stays its mask)."""
    torch = pytest.importorskip("torch")
    from tumor3d.learned.cnn_train import _scale_rotate

    class Fixed:  # the draws: the largest value of each range, in order
        def __init__(self, *values):
            self.values = list(values)

        def uniform(self, lo, hi, n):
            return np.full(n, self.values.pop(0))

    gen = torch.Generator().manual_seed(0)
    x = torch.rand(3, 3, 16, 16, generator=gen)
    y = (x[:, 1] > 0.5).float()
    same_x, same_y = _scale_rotate(torch, x, y, Fixed(1.0, 0.0), 0.0, 0.0)
    assert float((same_x - x).abs().max()) < 1e-5 and float((same_y - y).abs().max()) < 1e-5
    rx, ry = _scale_rotate(torch, x, y, Fixed(1.0, 90.0), 0.0, 90.0)
    assert float((rx - torch.rot90(x, 1, (-2, -1))).abs().max()) < 1e-5
    assert torch.equal((rx[:, 1] > 0.5).float(), (ry > 0.5).float())
    square = torch.zeros(1, 32, 32)
    square[0, 8:24, 8:24] = 1.0
    _, zoomed = _scale_rotate(torch, torch.zeros(1, 1, 32, 32), square, Fixed(1.2, 0.0), 0.2, 0)
    assert abs(float(zoomed.sum() / square.sum()) - 1.2**2) < 0.02


def test_a_file_without_metadata_has_none():
    buf = io.BytesIO()
    np.savez(buf, head_w=np.zeros((1, 2, 1, 1), np.float32))
    assert unet_meta(buf.getvalue()) == {}


def test_numpy_forward_pass_reproduces_the_trained_torch_net(phantom_slices):
    pytest.importorskip("torch")
    from tumor3d.learned.cnn import unet_from_bytes, unet_probability
    from tumor3d.learned.cnn_train import torch_probability, train_unet

    x, y = phantom_slices
    data, fit = train_unet(x, y, TINY, seed=3, threads=1, meta={"trained_on": "phantoms 11, 12"})
    assert len(fit.losses) == 2 and all(np.isfinite(fit.losses))
    # the batch norms learned something: folding them is not the identity
    bn = fit.model.enc[0][1]
    assert float(bn.running_mean.abs().sum()) > 0
    p_torch = torch_probability(fit.model, x)
    net = unet_from_bytes(data, source="tiny")
    assert net.levels == 2 and net.in_channels == 3
    p_numpy = unet_probability(net, x)
    assert p_numpy.shape == p_torch.shape == (24, 32, 32)
    assert float(np.abs(p_numpy - p_torch).max()) < 1e-5
    assert 0.0 < float(p_torch.std())  # not a constant map
    meta = unet_meta(data)
    assert meta["trained_on"] == "phantoms 11, 12" and meta["seed"] == 3
    assert meta["settings"]["base"] == 2 and meta["trainer"].startswith("torch ")
    assert meta["slices_per_epoch"] == fit.slices_per_epoch
    again, _ = train_unet(x, y, TINY, seed=3, threads=1, meta={"trained_on": "phantoms 11, 12"})
    strip = {"train_wall_s"}  # the one field that is not a function of the inputs

    def arrays(b):
        with np.load(io.BytesIO(b), allow_pickle=False) as z:
            return {k: z[k] for k in z.files if k != "meta_json"}

    a1, a2 = arrays(data), arrays(again)
    assert a1.keys() == a2.keys() and all(np.array_equal(a1[k], a2[k]) for k in a1)
    m2 = unet_meta(again)
    assert {k: v for k, v in meta.items() if k not in strip} == {
        k: v for k, v in m2.items() if k not in strip
    }

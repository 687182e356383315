"""The shared validators: TypeError for wrong types, InputError for bad values."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.validation import (
    check_affine,
    check_binary_mask,
    check_int,
    check_positive,
    short_repr,
)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_check_positive_refuses_bad_values(bad):
    with pytest.raises(InputError, match="radius_mm must be a positive number of mm"):
        check_positive(bad, "radius_mm", unit="mm")


def test_check_positive_types_and_zero():
    assert check_positive(0, "gap", allow_zero=True) == 0.0
    assert check_positive(np.float32(2.5), "x") == 2.5
    for wrong in ("2", True, None, [1.0]):
        with pytest.raises(TypeError, match="x must be a positive number"):
            check_positive(wrong, "x")
    # a value read from a file is user input: InputError naming the file
    with pytest.raises(InputError, match=r"^stack\.yaml: x must be a positive number"):
        check_positive("2", "x", where="stack.yaml")


def test_check_int():
    assert check_int(np.int64(3), "n", minimum=1) == 3
    with pytest.raises(InputError, match="n must be an integer >= 1, got 0"):
        check_int(0, "n", minimum=1)
    with pytest.raises(TypeError):
        check_int(2.0, "n", minimum=1)


def test_check_affine():
    aff = np.diag([1.0, 2.0, 5.0, 1.0])
    out = check_affine(aff)
    out[0, 0] = 9.0
    assert aff[0, 0] == 1.0  # a copy, the input untouched
    with pytest.raises(InputError, match="4x4"):
        check_affine(np.eye(3))
    with pytest.raises(InputError, match="singular"):
        check_affine(np.diag([1.0, 1.0, 0.0, 1.0]))
    with pytest.raises(InputError, match="last row"):
        check_affine(np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]))
    with pytest.raises(InputError, match="finite"):
        check_affine(np.full((4, 4), np.nan))
    with pytest.raises(TypeError):
        check_affine([["a"] * 4] * 4)


def test_check_binary_mask():
    m = check_binary_mask(np.array([[0, 1], [1, 0]], dtype=np.uint8), ndim=2)
    assert m.dtype == bool and m.sum() == 2
    with pytest.raises(InputError, match="only 0 and 1"):
        check_binary_mask(np.array([0, 2]))
    with pytest.raises(InputError, match="must be 3-D"):
        check_binary_mask(np.zeros((2, 2)), ndim=3)
    with pytest.raises(TypeError):
        check_binary_mask(np.array(["a"]))


def test_short_repr_bounds_huge_and_nested_values():
    nested: list = [0] * 10
    for _ in range(8):
        nested = [nested] * 10  # 10**9 leaves if expanded
    text = short_repr(nested)
    assert len(text) <= 80
    assert "..." in short_repr("x" * 1000) and len(short_repr("x" * 1000)) <= 80

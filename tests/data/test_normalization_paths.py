"""``normalize_per_cube_max`` given what a notebook user easily has: a cube holding NaN or Inf, one with no positive
value, a torch tensor. Each is one InputError saying what is wrong (before: NaN and negative cubes were told "all
zeros", an Inf cube came back as NaN and 0 values with peak inf, a tensor raised a TypeError from numpy's max).
Found by a review that used hsicam from Python. Reference: the exact line a user sees, the count of non-finite
values by a loop, and a finite cube divided by its maximum in float64."""

import numpy as np
import pytest
import torch

from hsicam.data import normalize_per_cube_max
from hsicam.errors import InputError


def _cube():
    return np.random.default_rng(0).uniform(0.1, 3.0, (3, 8, 9)).astype(np.float32)


@pytest.mark.parametrize("bad", [[np.nan], [np.inf], [np.nan, -np.inf, np.inf]])
def test_a_cube_holding_nan_or_inf_is_told_so_with_its_count(bad):
    cube = _cube()
    for i, v in enumerate(bad):
        cube[i, i, i] = v
    n = sum(1 for v in cube.ravel() if not np.isfinite(v))
    with pytest.raises(InputError) as e:
        normalize_per_cube_max(cube, "s.h5")
    assert str(e.value) == f"s.h5: the cube contains {n} NaN or Inf value(s) of {cube.size}; cannot normalise by its maximum"


def test_a_cube_without_a_positive_value_is_not_called_all_zeros():
    cube = -_cube()
    with pytest.raises(InputError) as e:
        normalize_per_cube_max(cube, "s.h5")
    assert str(e.value) == (f"s.h5: the cube has no positive value (its maximum is {float(cube.max()):.4g}); cannot "
                            "normalise by its maximum")
    with pytest.raises(InputError, match="^s.h5: the cube is all zeros; cannot normalise by its maximum$"):
        normalize_per_cube_max(np.zeros((3, 4, 4), np.float32), "s.h5")


def test_a_tensor_is_told_to_become_an_array():
    cube = _cube()
    with pytest.raises(InputError) as e:
        normalize_per_cube_max(torch.from_numpy(cube))
    assert str(e.value) == ("cube: normalize_per_cube_max takes a NumPy array (C, H, W), got Tensor: cube.numpy(), or "
                            "divide the tensor by cube.max()")
    out, peak = normalize_per_cube_max(torch.from_numpy(cube).numpy())
    ref = cube.astype(np.float64) / cube.astype(np.float64).max()
    assert peak == float(cube.max())
    np.testing.assert_allclose(out, ref, rtol=1e-6)

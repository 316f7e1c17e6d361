"""A cube a notebook user easily gives ``srgb_preview`` / ``cube_to_srgb``: a torch tensor, a cube stored bands last
(H, W, C), a cube of another band count. One InputError in the user's own shape naming the fix, not a TypeError
from ``torch.from_numpy`` or a message about an internally transposed shape. Found by a review that used hsicam
from Python. Reference: the exact line a user sees, and a white cube, whose preview is 255 everywhere (sRGB of a
perfect white reflector under D65 is (1, 1, 1)), once given as the message says."""

import numpy as np
import pytest
import torch

from hsicam.color import cube_to_srgb, srgb_preview
from hsicam.errors import InputError
from hsicam.spectral import Bands

BANDS = Bands.paper()
GRID = "Bands(31 bands, 420..720 nm)"


def test_srgb_preview_of_a_cube_stored_bands_last_names_the_move():
    hwc = np.ones((12, 20, 31), dtype=np.float32)
    with pytest.raises(InputError) as e:
        srgb_preview(hwc, BANDS)
    assert str(e.value) == (f"srgb_preview: the cube must be (C, H, W) with the 31 bands of {GRID} on axis 0, got shape "
                            "(12, 20, 31); its last axis has the bands: a cube stored bands last is np.moveaxis(cube, -1, 0)")
    assert (srgb_preview(np.moveaxis(hwc, -1, 0), BANDS) == 255).all()


def test_srgb_preview_of_a_tensor_names_the_conversion():
    cube = torch.ones((31, 12, 20), dtype=torch.float32)
    with pytest.raises(InputError) as e:
        srgb_preview(cube, BANDS)
    assert str(e.value) == "srgb_preview: the cube must be a NumPy array (C, H, W), got Tensor: cube.detach().cpu().numpy()"
    assert (srgb_preview(cube.detach().cpu().numpy(), BANDS) == 255).all()


@pytest.mark.parametrize("shape", [(3, 12, 20), (12, 20)])
def test_srgb_preview_of_another_band_count_or_a_2d_image(shape):
    with pytest.raises(InputError) as e:
        srgb_preview(np.ones(shape, dtype=np.float32), BANDS)
    expected = (f"srgb_preview: the cube must be (C, H, W) with the 31 bands of {GRID} on axis 0, got shape {shape}"
                if len(shape) == 3 else f"srgb_preview: the cube must be (C, H, W), got shape {shape}")
    assert str(e.value) == expected


def test_cube_to_srgb_of_a_batch_stored_bands_last_names_the_move_in_its_own_shape():
    bhwc = torch.ones((2, 12, 20, 31))
    with pytest.raises(InputError) as e:
        cube_to_srgb(bhwc, BANDS)
    assert str(e.value) == (f"cube_to_srgb: the cube must be (B, C, H, W) with the 31 bands of {GRID} on axis 1, got "
                            "shape (2, 12, 20, 31); its last axis has the bands: a cube stored bands last is "
                            "cube.movedim(-1, 1)")
    torch.testing.assert_close(cube_to_srgb(bhwc.movedim(-1, 1), BANDS), torch.ones((2, 3, 12, 20)))


def test_srgb_preview_draws_nan_pixels_black_without_numpy_s_cast_warning():
    """A cube with NaN pixels (a notebook's masked cube): those pixels black (0), the others as in the preview of the
    cube without them (a white reflector: 255), and no 'invalid value encountered in cast' RuntimeWarning (casting
    NaN to uint8 is undefined in NumPy); an all-NaN cube is black."""
    import warnings

    cube = np.ones((31, 4, 5), dtype=np.float32)
    cube[7, 1, 2] = np.nan  # one band of one pixel: its colour is undefined
    cube[:, 3, :] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rgb = srgb_preview(cube, BANDS)
        black = srgb_preview(np.full((31, 2, 3), np.nan, dtype=np.float32), BANDS)
    nan_px = np.isnan(cube).any(axis=0)
    assert (rgb[nan_px] == 0).all() and (rgb[~nan_px] == 255).all()
    assert black.dtype == np.uint8 and (black == 0).all()

"""Inputs a notebook user easily gives ``hsicam.metrics``: NumPy arrays, a single band as a 2-D image, cubes of two
shapes. Each is one InputError (an HsicamError, still a ValueError) with the line a user sees, not an
AttributeError or IndexError from inside the metric. Found by a review that used hsicam from Python. Reference:
the exact message, and scikit-image's PSNR of the same data once given as the message says."""

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio

from hsicam import metrics
from hsicam.errors import HsicamError, InputError

FUNCTIONS = [metrics.all_metrics, metrics.psnr_per_band, metrics.ssim, metrics.sam_degrees, metrics.ergas]


def _pair():
    g = torch.Generator().manual_seed(0)
    truth = torch.rand((4, 16, 18), generator=g, dtype=torch.float64)
    return (truth + 0.05 * torch.rand(truth.shape, generator=g, dtype=torch.float64)).clamp(0, 1), truth


@pytest.mark.parametrize("fn", FUNCTIONS)
def test_numpy_arrays_are_one_input_error_naming_the_fix(fn):
    est, truth = _pair()
    with pytest.raises(InputError) as e:
        fn(est.numpy(), truth.numpy())
    assert str(e.value) == ("estimate must be a torch.Tensor (B, C, H, W) or (C, H, W), got ndarray: "
                            "torch.from_numpy(a)")
    with pytest.raises(InputError, match="^truth must be a torch.Tensor"):
        fn(est, truth.numpy())


@pytest.mark.parametrize("fn", FUNCTIONS)
def test_a_2d_image_and_two_shapes_are_one_input_error(fn):
    est, truth = _pair()
    with pytest.raises(InputError) as e:
        fn(est[0], truth[0])
    assert str(e.value) == "expected (B, C, H, W) or (C, H, W), got (16, 18)"
    with pytest.raises(HsicamError, match=r"^shapes differ: \(4, 16, 18\) vs \(4, 16, 17\)$"):
        fn(est, truth[..., :17])


def test_the_fix_the_message_names_gives_scikit_images_score():
    est, truth = _pair()
    e, t = est.numpy(), truth.numpy()
    sk = np.mean([peak_signal_noise_ratio(t[b], e[b], data_range=1) for b in range(4)])
    assert metrics.all_metrics(torch.from_numpy(e), torch.from_numpy(t))["psnr"][0] == pytest.approx(sk, rel=1e-12)

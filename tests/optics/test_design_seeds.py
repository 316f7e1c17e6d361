"""Designs drawn from a seed (the DOE's heights, a CFA, the CASSI coded aperture) built without a config: their draws
keep only a seed's low 32 bits (``torch.Generator.manual_seed``, the aperture's 32-bit hash), so ``ColorFilterArray(
seed=2**32)`` was the CFA of seed 0 and ``seed=-1`` that of 2^32 - 1, silently (measured: equal weights). The config's
seed keys were bounded to [0, 2^32 - 1] already; the classes now refuse the same seeds, and every seed inside keeps
its design byte for byte (the shipped weights and the documented figures use seed 0 and small seeds)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsicam.cameras.cassi import CodedAperture, hashed_bits, random_aperture
from hsicam.errors import ConfigError
from hsicam.optics.doe import DOE
from hsicam.sensor import ColorFilterArray, bandpass_weights
from hsicam.spectral import get_material

OUTSIDE = [(2**32, "4294967296"), (-1, "-1"), (2**40 + 3, str(2**40 + 3)), (-(2**64), str(-(2**64)))]
CENTRES = torch.tensor([450.0, 500.0, 550.0, 600.0, 650.0], dtype=torch.float64)


def _builds():
    fused = get_material("fused_silica")
    return {
        "DOE seed": lambda s: DOE(5, fused, seed=s),
        "CFA seed": lambda s: ColorFilterArray(3, 2, seed=s),
        "CFA seed ": lambda s: bandpass_weights(CENTRES, 2, 40.0, s),
        "coded-aperture seed": lambda s: CodedAperture(seed=s),
        "coded-aperture seed ": lambda s: hashed_bits(4, 4, s),
    }


@pytest.mark.parametrize("what", list(_builds()))
@pytest.mark.parametrize("seed,shown", OUTSIDE)
def test_a_seed_outside_32_bits_is_refused_naming_it(what, seed, shown):
    with pytest.raises(ConfigError) as err:
        _builds()[what](seed)
    assert str(err.value) == f"{what.strip()} must be an integer in [0, 2^32 - 1], got {shown}"


@pytest.mark.parametrize("seed", [0, 1, 7, 2**31, 2**32 - 1])
def test_seeds_inside_keep_their_designs_byte_for_byte(seed):
    """The reference: torch's generator seeded with the same int, drawn as the classes draw (uniform heights times
    the 2π height, a uniform CFA, a random permutation of the band-pass filters)."""
    fused = get_material("fused_silica")
    doe = DOE(5, fused, seed=seed)
    g = torch.Generator().manual_seed(seed)
    want = (torch.rand(5, 5, generator=g, dtype=torch.float64) * doe.h2pi_m).float()
    assert torch.equal(doe.height_m.detach(), want)
    g = torch.Generator().manual_seed(seed)
    assert torch.equal(ColorFilterArray(3, 2, seed=seed).weights.detach(), torch.rand(3, 2, 2, generator=g))
    order = torch.randperm(4, generator=torch.Generator().manual_seed(seed))
    w = bandpass_weights(CENTRES, 2, 40.0, seed)
    peaks = w.reshape(5, 4).argmax(dim=0)  # the filter at tile cell k peaks at the band nearest its centre
    centres = torch.linspace(450.0, 650.0, 4, dtype=torch.float64)[order]
    assert peaks.tolist() == [int((CENTRES - c).abs().argmin()) for c in centres]


def test_numpy_integers_are_seeds_and_distinct_seeds_give_distinct_designs():
    a = ColorFilterArray(3, 2, seed=np.int64(5)).weights
    assert torch.equal(a, ColorFilterArray(3, 2, seed=5).weights)
    assert not torch.equal(a, ColorFilterArray(3, 2, seed=6).weights)
    assert torch.equal(random_aperture(8, 8, np.uint32(2**32 - 1)), random_aperture(8, 8, 2**32 - 1))
    assert not torch.equal(hashed_bits(8, 8, 2**32 - 1), hashed_bits(8, 8, 0))

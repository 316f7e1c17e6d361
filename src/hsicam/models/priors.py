"""Learned priors over hyperspectral cubes (used by the solvers, trained by :mod:`hsicam.engine.prior`)."""

from __future__ import annotations

import torch
from torch import nn

from hsicam.config import ChoiConfig
from hsicam.models.registry import check_parameter_memory

#: The keys of ``baselines.choi`` that size the autoencoder (with the band count).
PRIOR_SIZE_KEYS = ("features", "latent")
#: 3×3 convolutions in each of the autoencoder's encoder and decoder (not a config key).
PRIOR_LAYERS = 6


class SpectralAutoencoder(nn.Module):
    """Convolutional autoencoder prior R(x) = x + D(E(x)): cube (B, C, H, W) → code (B, L, H, W) →
    cube, the layer stack of Choi et al. 2017 (KAIST-VCLAB/deepcassi) with a skip.

    Encoder E: ``layers`` 3×3 convolutions (C → F → … → F → L), ReLU after each but the last (the
    code is linear); decoder D: ``layers`` 3×3 convolutions (L → F → … → F → C), ReLU after each but
    the last; reflect padding. The code keeps full resolution and, with L ≥ C (the published 64
    features and 64-channel code for 31 bands), has no spectral bottleneck. Unlike the published
    autoencoder, D returns a correction to its input (:meth:`decode` is that correction) and starts
    at zero, so R starts as the identity and clean cubes stay (near) its fixed points: trained as a
    denoising autoencoder it learns to remove corruption rather than to rebuild every spectrum.
    Without the skip the 6 + 6 stack did not train within the CPU scales' budgets (session 25: its
    loss stayed above the identity's after 800 steps), and the earlier 3 + 3 autoencoder with a
    12-channel code rebuilt clean cubes at a mean SAM of ~23°. Spatial context (4·``layers`` + 1) px.
    """

    def __init__(self, bands: int, features: int = 64, latent: int = 64, layers: int = PRIOR_LAYERS) -> None:
        super().__init__()
        if min(bands, features, latent) < 1 or layers < 2:
            raise ValueError("autoencoder sizes must be >= 1 and layers >= 2")
        self.encoder = _stack(bands, features, latent, layers)
        self.decoder = _stack(latent, features, bands, layers)
        nn.init.zeros_(self.decoder[-1].weight)  # R = identity at the start: clean cubes are its fixed points

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoder(x)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(z)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.decoder(self.encoder(x))


def autoencoder_parameter_count(bands: int, features: int = 64, latent: int = 64, layers: int = PRIOR_LAYERS) -> int:
    """The parameter count of ``SpectralAutoencoder(bands, features, latent, layers)``, in closed form
    (tests hold it equal to the built one's): each 3×3 convolution a → b has 9ab weights and b biases."""
    c, f, lat, k = bands, features, latent, layers
    inner = (k - 2) * (9 * f * f + f)  # the F → F convolutions of one stack
    encoder = 9 * c * f + f + inner + 9 * f * lat + lat
    decoder = 9 * lat * f + f + inner + 9 * f * c + c
    return encoder + decoder


def build_prior(settings: ChoiConfig, bands: int, training: bool = False) -> SpectralAutoencoder:
    """The autoencoder ``settings`` (``baselines.choi``) describe for ``bands`` bands; one whose weights
    (``training``: whose training) do not fit the memory budget is a ConfigError naming the
    ``baselines.choi`` sizes before anything is built (:func:`hsicam.models.registry.check_parameter_memory`,
    the check of every network)."""
    n = autoencoder_parameter_count(bands, settings.features, settings.latent)
    check_parameter_memory(n, "baselines.choi", settings, PRIOR_SIZE_KEYS, bands, training)
    return SpectralAutoencoder(bands, settings.features, settings.latent)


def _stack(cin: int, features: int, cout: int, layers: int) -> nn.Sequential:
    """``layers`` 3×3 convolutions cin → features → … → features → cout, ReLU between them."""
    mods: list[nn.Module] = []
    for i in range(layers):
        a = cin if i == 0 else features
        b = cout if i == layers - 1 else features
        conv = nn.Conv2d(a, b, 3, padding=1, padding_mode="reflect")
        # He initialisation (ReLU gain; the last, linear, layer gain 1): a plain 12-layer stack with
        # PyTorch's default init shrinks the signal layer by layer and trains several times slower
        nn.init.kaiming_normal_(conv.weight, nonlinearity="relu" if i < layers - 1 else "linear")
        nn.init.zeros_(conv.bias)
        mods.append(conv)
        if i < layers - 1:
            mods.append(nn.ReLU())
    return nn.Sequential(*mods)

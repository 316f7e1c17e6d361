"""Learned priors over hyperspectral cubes (used by the solvers, trained by :mod:`hsicam.engine.prior`)."""

from __future__ import annotations

import torch
from torch import nn


class SpectralAutoencoder(nn.Module):
    """Convolutional autoencoder: cube (B, C, H, W) → latent (B, L, H, W) → cube.

    Encoder 3×3 (C→F), 1×1 (F→F), 1×1 (F→L); decoder 1×1 (L→F), 3×3 (F→F), 1×1 (F→C); leaky ReLU
    between layers, reflect padding. Spatial context 5×5; the latent keeps full resolution (the
    spectral dimension is what is compressed, C → L).
    """

    def __init__(self, bands: int, features: int = 48, latent: int = 12) -> None:
        super().__init__()
        if min(bands, features, latent) < 1:
            raise ValueError("autoencoder sizes must be >= 1")
        act = lambda: nn.LeakyReLU(0.1)  # noqa: E731
        self.encoder = nn.Sequential(
            nn.Conv2d(bands, features, 3, padding=1, padding_mode="reflect"), act(),
            nn.Conv2d(features, features, 1), act(),
            nn.Conv2d(features, latent, 1),
        )
        self.decoder = nn.Sequential(
            nn.Conv2d(latent, features, 1), act(),
            nn.Conv2d(features, features, 3, padding=1, padding_mode="reflect"), act(),
            nn.Conv2d(features, bands, 1),
        )

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoder(x)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(z)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder(x))

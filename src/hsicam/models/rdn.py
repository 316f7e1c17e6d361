"""The paper's reconstruction network: tentative 1×1 reconstruction + residual dense network.

    t = Conv1×1(g)                              sensor (B, 1, H, W) → tentative cube (B, C, H, W)
    F₋₁ = Conv3×3(t), F₀ = Conv3×3(F₋₁)          shallow features (G0 channels)
    F_d = RDB_d(F_{d−1}), d = 1..D               residual dense blocks
    F_GF = Conv3×3(Conv1×1([F_1, …, F_D])) + F₋₁  global fusion, global residual
    f̂ = Conv3×3(F_GF) + t                        output, plus the tentative reconstruction

Each RDB has ``layers`` (paper: C = 4) densely connected Conv3×3+ReLU layers of ``growth`` (G)
channels, a 1×1 local fusion back to G0 channels and a local residual. The paper gives no D, G0,
G; our defaults (D = 8, G0 = 64, G = 32) follow Zhang et al.'s RDN at a size that trains at paper
scale on one GPU; the CPU preset uses D = 3, G0 = 32, G = 16. Fully convolutional: any band count,
any image size.

Initialisation (the paper gives none): the tentative 1×1 conv starts as t_c = g (the sensor image
copied into every band; other input channels weigh 0) and the output conv starts at zero, so an
untrained network already returns the grey image t instead of noise and training starts from a
sensible reconstruction. Every other layer has PyTorch's default initialisation.
"""

from __future__ import annotations

import torch
from torch import nn

from hsicam.errors import ConfigError
from hsicam.models.context import conv_receptive_radius
from hsicam.models.demosaic import backprojection, camera_demosaic, camera_operator, demosaic_window
from hsicam.models.registry import register_network


class ResidualDenseBlock(nn.Module):
    """``layers`` densely connected 3×3 conv + ReLU layers, 1×1 local fusion, local residual."""

    def __init__(self, features: int, growth: int, layers: int = 4) -> None:
        super().__init__()
        self.convs = nn.ModuleList(
            nn.Sequential(nn.Conv2d(features + i * growth, growth, 3, padding=1), nn.ReLU(inplace=True))
            for i in range(layers)
        )
        self.fusion = nn.Conv2d(features + layers * growth, features, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        feats = [x]
        for conv in self.convs:
            feats.append(conv(torch.cat(feats, dim=1)))
        return x + self.fusion(torch.cat(feats, dim=1))


class RDN(nn.Module):
    """Sensor image (B, in_channels, H, W) → cube (B, bands, H, W)."""

    def __init__(self, bands: int, in_channels: int = 1, blocks: int = 8, features: int = 64, growth: int = 32,
                 layers_per_block: int = 4) -> None:
        super().__init__()
        if min(bands, in_channels, blocks, features, growth, layers_per_block) < 1:
            raise ValueError("RDN sizes must all be >= 1")
        self.tentative = nn.Conv2d(in_channels, bands, 1)
        self.sfe1 = nn.Conv2d(bands, features, 3, padding=1)
        self.sfe2 = nn.Conv2d(features, features, 3, padding=1)
        self.blocks = nn.ModuleList(ResidualDenseBlock(features, growth, layers_per_block) for _ in range(blocks))
        self.global_fusion = nn.Sequential(nn.Conv2d(blocks * features, features, 1), nn.Conv2d(features, features, 3, padding=1))
        self.output = nn.Conv2d(features, bands, 3, padding=1)
        with torch.no_grad():
            self.tentative.weight.zero_()
            self.tentative.weight[:, 0] = 1.0
            self.tentative.bias.zero_()
            self.output.weight.zero_()
            self.output.bias.zero_()

    def start_from_input(self, channels: list[int]) -> None:
        """Initialise the tentative conv to copy input channel ``channels[c]`` into band c."""
        if len(channels) != self.tentative.out_channels:
            raise ValueError(f"need one input channel per band ({self.tentative.out_channels}), got {len(channels)}")
        with torch.no_grad():
            self.tentative.weight.zero_()
            self.tentative.bias.zero_()
            for band, ch in enumerate(channels):
                self.tentative.weight[band, ch] = 1.0

    def forward(self, g: torch.Tensor) -> torch.Tensor:
        t = self.tentative(g)
        f_1 = self.sfe1(t)
        f = self.sfe2(f_1)
        outs = []
        for block in self.blocks:
            f = block(f)
            outs.append(f)
        f = self.global_fusion(torch.cat(outs, dim=1)) + f_1
        return self.output(f) + t


class RDNReconstructor(RDN):
    """The RDN as a camera network (``model.kind: rdn``). It reads one of:

    - the sensor image g (the paper);
    - with ``demosaic_input`` (beyond the paper, CFA cameras): ``[g, x̃_1, …, x̃_C]``, where x̃ is
      the per-band demosaic of g over one CFA period (:mod:`hsicam.models.demosaic`);
    - with ``backprojection_input`` (beyond the paper, any camera; CASSI): the back-projection
      Aᵀy ⊘ AᵀA𝟙 (C channels), which tells the network the code at each pixel.

    With the demosaic the tentative reconstruction starts as x̃; with the back-projection as its
    mean over bands in every band (a flat spectrum).

    Args:
        bands: C.
        demosaic_input: also read the demosaic (cameras with a per-band sensor code only).
        window: odd demosaic box width (px), the camera's CFA period.
        blocks, features, growth, layers_per_block: D, G0, G, C of the RDN.
        backprojection_input: read the back-projection instead of g.
        op_reach_px: how far the back-projection spreads a pixel (the operator's AᵀA reach, px).
    """

    def __init__(self, bands: int, demosaic_input: bool = False, window: int = 1, blocks: int = 8, features: int = 64,
                 growth: int = 32, layers_per_block: int = 4, backprojection_input: bool = False,
                 op_reach_px: int = 0) -> None:
        if demosaic_input and backprojection_input:
            raise ValueError("demosaic_input and backprojection_input are alternatives")
        in_channels = rdn_input_channels(bands, demosaic_input, backprojection_input)
        super().__init__(bands, in_channels, blocks, features, growth, layers_per_block)
        self.demosaic_input, self.window = bool(demosaic_input), int(window)
        self.backprojection_input, self.op_reach_px = bool(backprojection_input), int(op_reach_px)
        if self.demosaic_input:
            self.start_from_input(list(range(1, 1 + bands)))
        elif self.backprojection_input:
            # a flat spectrum at the back-projection's band mean: the spiky back-projection itself (each
            # band 0 where the code is closed) was a worse start at quick scale (docs/networks.md)
            with torch.no_grad():
                self.tentative.weight.fill_(1.0 / bands)
                self.tentative.bias.zero_()

    @property
    def context_px(self) -> int:
        """Receptive radius of the convolutions plus the reach of the input estimate (px per side)."""
        first = self.window // 2 if self.demosaic_input else self.op_reach_px if self.backprojection_input else 0
        return conv_receptive_radius(self) + first

    def network_input(self, sensor: torch.Tensor, camera, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """(B, 1, H, W) sensor → what the RDN reads: g, [g, x̃] (B, 1 + C, H, W) or Aᵀy ⊘ AᵀA𝟙 (B, C, H', W')."""
        if self.demosaic_input:
            return torch.cat([sensor, camera_demosaic(camera, sensor, origin)], dim=1)
        if self.backprojection_input:
            return backprojection(camera_operator(camera), sensor, origin)
        return sensor

    def forward(self, sensor: torch.Tensor, camera=None, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:  # type: ignore[override]
        """Sensor (B, 1, H, W) → cube (B, C, H', W'); ``camera`` (or its snapshot) is needed with
        either input estimate. Any floating input dtype; the output has the weights' dtype. The sensor is
        taken to the weights' dtype first, as the other networks do, so the input estimate is computed in it
        (a float16 image's back-projection through the DOE camera's FFTs failed on the CPU, its demosaic lost
        precision)."""
        sensor = sensor.to(self.tentative.weight.dtype)  # float32 unless the network was converted
        return super().forward(self.network_input(sensor, camera, origin))


def rdn_parameters(bands: int, in_channels: int = 1, blocks: int = 8, features: int = 64, growth: int = 32,
                   layers_per_block: int = 4) -> int:
    """The parameters (weights and biases) of ``RDN(bands, in_channels, blocks, features, growth,
    layers_per_block)``, in closed form (no loop over blocks or layers: any size is O(1))."""
    c, i, d, f, g, n = bands, in_channels, blocks, features, growth, layers_per_block
    # layer k of a block: 3×3 conv (f + k·g → g); summed over k = 0..n−1; then the 1×1 fusion (f + n·g → f)
    block = 9 * g * (n * f + g * n * (n - 1) // 2) + n * g + (f + n * g) * f + f
    return ((i * c + c) + (9 * c * f + f) + (9 * f * f + f)  # tentative 1×1, shallow features
            + d * block + (d * f * f + f) + (9 * f * f + f)  # blocks, global fusion 1×1 + 3×3
            + (9 * f * c + c))  # output 3×3


def rdn_input_channels(bands: int, demosaic_input: bool = False, backprojection_input: bool = False) -> int:
    """Channels of what :class:`RDNReconstructor` reads: g (1), [g, x̃] (1 + C) or Aᵀy ⊘ AᵀA𝟙 (C)."""
    return 1 + bands if demosaic_input else bands if backprojection_input else 1


def rdn_parameter_count(cfg, camera) -> int:
    """The parameters :func:`build_rdn` makes for ``cfg`` and ``camera`` (its band count)."""
    m, bands = cfg.model.rdn, len(camera.bands)
    in_channels = rdn_input_channels(bands, m.demosaic_input, m.backprojection_input)
    return rdn_parameters(bands, in_channels, m.blocks, m.features, m.growth, m.layers_per_block)


@register_network("rdn", parameters=rdn_parameter_count, sizes=("blocks", "features", "growth", "layers_per_block"))
def build_rdn(cfg, camera) -> RDNReconstructor:
    """The RDN of ``cfg.model.rdn`` for ``camera``."""
    m = cfg.model.rdn
    if m.demosaic_input:
        try:
            camera.sensor_code(1, 1)
        except NotImplementedError as exc:
            raise ConfigError(f"model.rdn.demosaic_input needs a camera with a per-band sensor code (the DOE camera's "
                              f"CFA): {exc}; set model.rdn.demosaic_input=false") from None
    probe = (64, 64)
    scene_hw = tuple(camera.scene_size(probe))
    if not m.backprojection_input and any(s < p for s, p in zip(scene_hw, probe)):
        # (SD-CASSI: the dispersion widens the sensor) the RDN reading g returns a cube of the sensor's size
        raise ConfigError(f"model.kind=rdn reading the sensor image returns a cube of the sensor's size, but "
                          f"{type(camera).__name__}'s sensor is larger than its scene (a {probe[0]}×{probe[1]} px "
                          f"sensor image holds a {scene_hw[0]}×{scene_hw[1]} px scene); set model.rdn.backprojection_input=true (the network reads Aᵀy on the scene's grid), or use "
                          "model.kind=unrolled with model.unrolled.init=backprojection")
    reach = 0
    if m.backprojection_input:
        with torch.no_grad():
            op = camera_operator(camera)
        reach = max(op.reach_px)  # how far AᵀA spreads a pixel
    return RDNReconstructor(len(camera.bands), m.demosaic_input, demosaic_window(camera), m.blocks, m.features,
                            m.growth, m.layers_per_block, m.backprojection_input, reach)

"""How far a plain convolutional network looks: the tiling halo of conv-only networks."""

from __future__ import annotations

from torch import nn

# Modules that do not widen the receptive field (pointwise or containers).
_POINTWISE = (nn.ReLU, nn.LeakyReLU, nn.GELU, nn.SiLU, nn.Sigmoid, nn.Tanh, nn.Identity, nn.Sequential,
              nn.ModuleList, nn.ModuleDict, nn.PReLU, nn.Softplus)


def conv_receptive_radius(net: nn.Module) -> int:
    """Upper bound of the receptive radius (px) of a stride-1 conv network: Σ dilation·(k−1)/2.

    Raises ``ValueError`` for a module it cannot reason about (pooling, strides, upsampling,
    attention, normalisation over space): such a network must declare its own ``context_px``.
    """
    r = 0
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            if m.stride != (1, 1):
                raise ValueError(f"{type(net).__name__}: strided {m}; declare context_px for this network")
            r += m.dilation[0] * (m.kernel_size[0] - 1) // 2
        elif m is not net and not isinstance(m, _POINTWISE) and next(m.children(), None) is None:
            raise ValueError(f"{type(net).__name__}: cannot bound the reach of {type(m).__name__}; "
                             f"declare context_px for this network")
    return r

"""How far a plain convolutional network looks: the tiling halo of conv-only networks."""

from __future__ import annotations

from torch import nn

# Modules that do not widen the receptive field (pointwise or containers).
_POINTWISE = (nn.ReLU, nn.LeakyReLU, nn.GELU, nn.SiLU, nn.Sigmoid, nn.Tanh, nn.Identity, nn.Sequential,
              nn.ModuleList, nn.ModuleDict, nn.PReLU, nn.Softplus)


def conv_receptive_radius(net: nn.Module) -> int:
    """Upper bound of the receptive radius (px) of a stride-1 conv network: the sum over its convs of
    each one's reach (:func:`conv_reach`; dilation·(k−1)/2 for an odd kernel padded to keep the size).

    Raises ``ValueError`` for a module it cannot reason about (pooling, strides, upsampling,
    attention, normalisation over space): such a network must declare its own ``context_px``.
    """
    r = 0
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            if m.stride != (1, 1):
                raise ValueError(f"{type(net).__name__}: strided {m}; declare context_px for this network")
            r += conv_reach(m)
        elif m is not net and not isinstance(m, _POINTWISE) and next(m.children(), None) is None:
            raise ValueError(f"{type(net).__name__}: cannot bound the reach of {type(m).__name__}; "
                             f"declare context_px for this network")
    return r


def conv_reach(conv: nn.Conv2d) -> int:
    """How far (px) one output pixel of a stride-1 ``conv`` looks on either side, over both axes:
    a window of span dilation·(k−1) starts ``padding`` before the pixel. Both axes and both sides
    count, so a 1×k kernel, an even kernel or an asymmetric padding is not undercounted (before
    session 55 only the first axis's dilation·(k−1)//2 was taken: 0 for a 1×5 kernel's 2 px)."""
    reach = 0
    for axis in range(2):
        span = conv.dilation[axis] * (conv.kernel_size[axis] - 1)
        if conv.padding == "same":
            before = span // 2  # torch puts the odd pixel of an even span after
        elif conv.padding == "valid":
            before = 0
        else:
            before = conv.padding[axis]
        reach = max(reach, before, span - before)
    return reach

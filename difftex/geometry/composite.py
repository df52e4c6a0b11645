"""Front-to-back alpha compositing of layers (the seed's alpha buffer).

The z-buffer keeps one surface per pixel, which cannot blend transparent
surfaces: ``a C_front + (1 - a) C_back`` depends on the order. The alpha
buffer keeps the layers of a pixel sorted by depth and blends them front to
back, stopping at the first opaque one. With layer ``i`` of colour ``c_i``
and coverage / opacity ``a_i`` (nearest first) the result is

    out = sum_i a_i T_i c_i,   T_0 = 1,   T_{i+1} = T_i (1 - a_i),

and the accumulated alpha is ``1 - T_L``. ``T_i`` is the light that reaches
layer ``i`` through the layers in front of it; once a layer with ``a = 1``
is met it is exactly 0, and every later layer of that pixel is not read
(selected away, not multiplied by 0: a NaN there stays out), contributes
nothing and gets a zero gradient.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .._checks import check_float, describe

__all__ = ["composite"]


def composite(colors: Tensor, alphas: Tensor) -> tuple[Tensor, Tensor]:
    """Blend layers front to back with their alphas (the alpha buffer).

    Args:
        colors: [L, B, C, H, W] colour of each layer, nearest layer first
            (e.g. one :func:`difftex.sample` result per depth layer).
        alphas: [L, B, 1, H, W] opacity of each layer in [0, 1] (texture
            alpha times coverage; 0 where the layer has no surface). B and
            the channel may also be 1 in either argument and broadcast.

    Returns:
        ``(color, alpha)``: [B, C, H, W] the premultiplied blend
        ``sum_i a_i prod_{j<i}(1 - a_j) c_i`` and [B, 1, H, W] the
        accumulated alpha ``1 - prod_i (1 - a_i)``. Put the blend over a
        background ``bg`` with ``color + (1 - alpha) * bg``.

    Differentiable with respect to ``colors`` and ``alphas``. Where the
    accumulated alpha reaches 1 (an opaque layer) the layers behind are not
    read: they get exactly zero weight and zero gradient, so a NaN or inf
    colour or alpha there changes neither the pixel nor any gradient; layers
    behind an opaque layer in every pixel are not evaluated at all. As they
    are not read, the gradient to an alpha of exactly 1 is ``T_i c_i`` alone
    (``T_i = prod_{j<i}(1 - a_j)``; the same whether the opaque layer covers
    one pixel or every pixel), not the ``T_i (c_i - behind)`` that reading
    the layers behind would add.
    A NaN in a layer that is read (not occluded) makes its own pixel NaN,
    value and gradients, and no other pixel. Alphas outside [0, 1] are not
    checked (a check would cost a device sync) and extrapolate the formula.
    Raises TypeError on non-float input, ValueError naming the argument on
    bad shapes, mismatched layer counts or devices.
    """
    check_float("colors", colors, 5, shape_doc="[L, B, C, H, W]")
    check_float("alphas", alphas, 5, shape_doc="[L, B, 1, H, W]")
    if alphas.shape[2] != 1:
        raise ValueError(f"alphas: expected one channel [L, B, 1, H, W], got {describe(alphas)}")
    if colors.shape[0] != alphas.shape[0]:
        raise ValueError(f"alphas: expected {colors.shape[0]} layers like colors, got {describe(alphas)}")
    if colors.shape[-2:] != alphas.shape[-2:]:
        raise ValueError(f"alphas: expected the image size {tuple(colors.shape[-2:])} of colors, "
                         f"got {describe(alphas)}")
    if colors.device != alphas.device:
        raise ValueError(f"alphas: expected device {colors.device} like colors, got {describe(alphas)}")
    try:
        shape = torch.broadcast_shapes(colors.shape[1:], alphas.shape[1:])
    except RuntimeError:
        raise ValueError(f"colors ({describe(colors)}) and alphas ({describe(alphas)}) must broadcast "
                         "(batch equal or 1)") from None
    dtype = torch.promote_types(colors.dtype, alphas.dtype)
    B, C, H, W = shape
    out = torch.zeros((B, C, H, W), dtype=dtype, device=colors.device)
    trans = torch.ones((B, 1, H, W), dtype=dtype, device=colors.device)
    for i in range(colors.shape[0]):
        # A pixel whose transmittance is exactly 0 (an opaque layer in front) does not read this layer:
        # torch.where selects 0 there instead of multiplying the layer by the zero transmittance, which
        # would keep a NaN / inf colour or alpha (0 * NaN = NaN) in the value and, through the product's
        # backward (0 * NaN again), in every gradient of the pixel. where's backward routes exact zeros
        # to the unselected input, so the layer gets a zero gradient there, not 0 * grad; and the zeroed
        # alpha keeps the transmittance at 0 (0 * (1 - NaN) would be NaN) for the layers further back.
        seen = (trans != 0).detach()
        a = torch.where(seen, alphas[i].to(dtype), 0.0)
        c = torch.where(seen, colors[i].to(dtype), 0.0)
        out = out + (a * trans) * c
        trans = trans * (1 - a)
        # The alpha buffer's early stop: every pixel is opaque, nothing
        # behind can show. One sync per layer, for L small.
        if i + 1 < colors.shape[0] and not bool((trans != 0).any()):
            break
    return out, 1 - trans

"""``sample()``: one entry point for every texture filter and wrap mode."""
from __future__ import annotations

from typing import Union

import torch
from torch import Tensor

from ._checks import broadcast_batch, check_float, check_same
from .filters.basic import separable_sample
from .wrap import Wrap, parse_wrap

# Filters that read one texture level; the value is the per-axis kernel.
SEPARABLE = {"nearest": "nearest", "bilinear": "linear", "bicubic": "cubic"}
FILTERS = tuple(SEPARABLE)


def sample(
    texture: Tensor,
    uv: Tensor,
    *,
    filter: str = "bilinear",
    wrap: Wrap = "repeat",
    border_value: float = 0.0,
) -> Tensor:
    """Sample a texture at uv coordinates.

    Args:
        texture: [B, C, H, W] float tensor; B = 1 broadcasts over the uv batch.
        uv: [B, Ho, Wo, 2]; (0, 0) is the top-left corner of texel (0, 0),
            (1, 1) the bottom-right corner of the last texel; u runs along the
            width, v along the rows (DESIGN.md). ``grid_sample`` with
            ``grid = 2 * uv - 1`` and ``align_corners=False`` samples the same
            point. B = 1 broadcasts over the texture batch.
        filter: "nearest" (round half to even, like grid_sample), "bilinear",
            or "bicubic" (Keys cubic, a = -0.75, like grid_sample).
        wrap: "repeat" | "clamp" | "mirror" | "border", one for both axes or a
            pair (wrap_u, wrap_v).
        border_value: the constant that "border" reads outside the texture.

    Returns:
        [B, C, Ho, Wo], same dtype and device as the inputs.

    Gradients flow to texture and uv (nearest: texture only; its uv gradient
    is zero almost everywhere). The backward pass is itself differentiable
    (double backward). A pixel with a NaN or infinite uv comes out NaN and
    passes no gradient to the texture; other pixels are unaffected.

    Raises ValueError naming the argument on bad shapes, batch mismatch,
    different devices or an unknown filter / wrap; TypeError on non-float
    tensors or mixed dtypes.
    """
    check_float("texture", texture, 4, shape_doc="[B, C, H, W]")
    check_float("uv", uv, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_same("uv", uv, "texture", texture)
    if texture.shape[-1] < 1 or texture.shape[-2] < 1 or texture.shape[1] < 1:
        raise ValueError(f"texture: expected C, H, W >= 1, got shape {tuple(texture.shape)}")
    wrap_u, wrap_v = parse_wrap(wrap)
    if not isinstance(filter, str) or filter not in FILTERS:
        raise ValueError(f"filter: unknown filter {filter!r}; expected one of {FILTERS}")
    B = broadcast_batch(("texture", "uv"), (texture.shape[0], uv.shape[0]))
    Bt, C = texture.shape[:2]
    _, Ho, Wo, _ = uv.shape
    if Bt == 1:
        # One texture for every view: all sample points in one flat row.
        flat_uv = uv.reshape(1, -1, 2)
    else:
        flat_uv = uv.expand(B, -1, -1, -1).reshape(B, -1, 2)
    out = separable_sample(texture, flat_uv, SEPARABLE[filter], wrap_u, wrap_v, border_value)
    if Bt == 1 and B > 1:
        return out.view(C, B, Ho, Wo).transpose(0, 1)
    return out.view(B, C, Ho, Wo)

"""Nearest, bilinear and bicubic sampling of one texture level.

All three are separable: along each axis a pixel reads a few texels
(1, 2 or 4) with weights that depend on the fractional texel coordinate.
One autograd Function serves all three, so gather, wrap handling, the
texture gradient (a scatter of the same weights) and the uv gradient (the
weights' derivatives) are written once.

The backward pass recomputes indices and weights from ``uv`` instead of
saving the gathered texels: it keeps memory at the size of the inputs, and
because it is written in differentiable torch ops it can itself be
differentiated (double backward), which grid_sample cannot.

Flat layout used here: texture ``[Bt, C, H, W]``, uv ``[Bt, M, 2]`` (one
row of M sample points per texture), output ``[Bt, C, M]``;
``difftex.sample`` does the reshaping and broadcasting around it.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..wrap import wrap_index

KINDS = ("nearest", "linear", "cubic")

# grid_sample's bicubic uses the Keys cubic convolution with a = -0.75.
_CUBIC_A = -0.75


def _cubic_near(t: Tensor) -> tuple[Tensor, Tensor]:
    """Keys kernel and its derivative for |t| <= 1."""
    a = _CUBIC_A
    return ((a + 2) * t - (a + 3)) * t * t + 1, (3 * (a + 2) * t - 2 * (a + 3)) * t


def _cubic_far(t: Tensor) -> tuple[Tensor, Tensor]:
    """Keys kernel and its derivative for 1 < |t| < 2."""
    a = _CUBIC_A
    return ((a * t - 5 * a) * t + 8 * a) * t - 4 * a, (3 * a * t - 10 * a) * t + 8 * a


def axis_taps(x: Tensor, n: int, kind: str, mode: str):
    """Texels and weights along one axis.

    Args:
        x: continuous texel coordinate, texel ``j`` has its centre at ``j``
            (``x = u * n - 0.5``).
        n: texels along the axis.
        kind: ``"nearest"``, ``"linear"`` or ``"cubic"``.
        mode: wrap mode of this axis.

    Returns:
        list of ``(index, valid, weight, dweight)`` per tap, where ``dweight``
        is d(weight)/dx (``None`` for nearest, whose weight is constant 1).
    """
    if kind == "nearest":
        # torch.round rounds half to even, like grid_sample's nearbyint.
        idx, valid = wrap_index(torch.round(x), n, mode)
        # 1 where x is finite, NaN where it is not: a bad uv shows in its pixel.
        return [(idx, valid, 1 + 0 * x, None)]
    base = torch.floor(x)
    t = x - base
    if kind == "linear":
        i0, v0 = wrap_index(base, n, mode)
        i1, v1 = wrap_index(base + 1, n, mode)
        one = torch.ones_like(t)
        return [(i0, v0, 1 - t, -one), (i1, v1, t, one)]
    if kind == "cubic":
        taps = []
        w0, d0 = _cubic_far(t + 1)
        w1, d1 = _cubic_near(t)
        w2, d2 = _cubic_near(1 - t)
        w3, d3 = _cubic_far(2 - t)
        for off, w, d in ((-1, w0, d0), (0, w1, d1), (1, w2, -d2), (2, w3, -d3)):
            i, v = wrap_index(base + off, n, mode)
            taps.append((i, v, w, d))
        return taps
    raise ValueError(f"filter: unknown separable kind {kind!r}; expected one of {KINDS}")


def _tap_grid(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str):
    """Yield (flat index, valid mask, weight, dweight/dx, dweight/dy) per 2D tap."""
    H, W = texture.shape[-2:]
    x = uv[..., 0] * W - 0.5
    y = uv[..., 1] * H - 0.5
    tx = axis_taps(x, W, kind, wrap_u)
    ty = axis_taps(y, H, kind, wrap_v)
    for iy, vy, wy, dy in ty:
        row = iy * W
        for ix, vx, wx, dx in tx:
            valid = vx if vy is None else (vy if vx is None else vx & vy)
            if dx is None:
                yield row + ix, valid, wx * wy, None, None
            else:
                yield row + ix, valid, wx * wy, dx * wy, wx * dy


def _gather(flat: Tensor, idx: Tensor) -> Tensor:
    """flat [Bt, C, HW], idx [Bt, M] -> [Bt, C, M]."""
    return torch.gather(flat, 2, idx.unsqueeze(1).expand(-1, flat.shape[1], -1))


def _read(flat: Tensor, idx: Tensor, valid: Tensor | None, border: float) -> Tensor:
    vals = _gather(flat, idx)
    if valid is not None:
        vals = torch.where(valid.unsqueeze(1), vals, vals.new_tensor(border))
    return vals


def separable_forward(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """Filtered values, flat layout (see module docstring)."""
    Bt, C, H, W = texture.shape
    flat = texture.reshape(Bt, C, H * W)
    out = None
    for idx, valid, w, _, _ in _tap_grid(texture, uv, kind, wrap_u, wrap_v):
        term = _read(flat, idx, valid, border) * w.unsqueeze(1)
        out = term if out is None else out + term
    return out


def separable_backward(texture: Tensor, uv: Tensor, grad_out: Tensor, kind: str, wrap_u: str, wrap_v: str,
                       border: float, need_tex: bool, need_uv: bool) -> tuple[Tensor | None, Tensor | None]:
    """Gradients w.r.t. texture and uv, in differentiable ops (double backward)."""
    Bt, C, H, W = texture.shape
    flat = texture.reshape(Bt, C, H * W)
    # A pixel whose uv is NaN / inf has NaN weights; it must not spread NaN
    # into the texels it happens to index, so it gives the texture nothing.
    finite = torch.isfinite(uv).all(-1) if need_tex else None
    grad_flat = torch.zeros_like(flat) if need_tex else None
    gx = gy = None
    need_uv = need_uv and kind != "nearest"
    for idx, valid, w, dwx, dwy in _tap_grid(texture, uv, kind, wrap_u, wrap_v):
        if need_tex:
            wt = torch.where(finite if valid is None else finite & valid, w, 0.0)
            src = grad_out * wt.unsqueeze(1)
            grad_flat = grad_flat.scatter_add(2, idx.unsqueeze(1).expand(-1, C, -1), src)
        if need_uv:
            gv = (grad_out * _read(flat, idx, valid, border)).sum(1)
            gx = gv * dwx if gx is None else gx + gv * dwx
            gy = gv * dwy if gy is None else gy + gv * dwy
    grad_tex = grad_flat.view(Bt, C, H, W) if need_tex else None
    grad_uv = torch.stack((gx * W, gy * H), -1) if need_uv else None
    return grad_tex, grad_uv


class SeparableSample(torch.autograd.Function):
    """Autograd wrapper: texture [Bt,C,H,W], uv [Bt,M,2] -> [Bt,C,M]."""

    @staticmethod
    def forward(ctx, texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float) -> Tensor:
        ctx.save_for_backward(texture, uv)
        ctx.args = (kind, wrap_u, wrap_v, border)
        return separable_forward(texture, uv, kind, wrap_u, wrap_v, border)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        texture, uv = ctx.saved_tensors
        kind, wrap_u, wrap_v, border = ctx.args
        grad_tex, grad_uv = separable_backward(
            texture, uv, grad_out, kind, wrap_u, wrap_v, border,
            ctx.needs_input_grad[0], ctx.needs_input_grad[1])
        return grad_tex, grad_uv, None, None, None, None


def separable_sample(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float = 0.0) -> Tensor:
    """Sample one level in the flat layout: texture [Bt,C,H,W], uv [Bt,M,2] -> [Bt,C,M].

    No input checks: callers (``difftex.sample`` and the mip filters) have
    validated shapes, dtypes and modes already.
    """
    return SeparableSample.apply(texture, uv, kind, wrap_u, wrap_v, float(border))

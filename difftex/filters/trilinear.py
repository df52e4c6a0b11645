"""Trilinear (and nearest-mip) filtering: the bilinear tap of two adjacent mip levels, blended.

This is the *trilinear tap* that the anisotropic filter calls once per
probe, and ``mip_blend``, its level grouping and blend, is shared with the
EWA filter. Work is proportional to the points a level serves: points are
sorted by level once, each level is read (with ``separable_sample``, the one
bilinear of the package) only at the points that use it, and the results
are put back in order with one ``index_copy``. A point whose level is an
exact integer, or clamped to the ends of the pyramid, costs one bilinear
tap, not two.

Flat layout: one texture's levels ``[1, C, H_k, W_k]``, points ``[M, ...]``,
result ``[C, M]``; ``difftex.sample`` does batching and checks.
"""
from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import Tensor

from .basic import separable_sample


def mip_blend(D: Tensor, levels: int, inputs: Sequence[Tensor], read: Callable[[int, list[Tensor]], Tensor], *,
              nearest: bool = False) -> Tensor:
    """Blend per-level results at ``floor(D)`` and ``floor(D) + 1``, each level read once for its points.

    Args:
        D: [M] level per point, already clamped to ``[0, levels - 1]``
            (``difftex.lod.level``); may carry a gradient.
        levels: number of levels.
        inputs: per-point tensors ``[M, ...]`` that ``read`` needs (uv, ...).
        read: ``read(k, [x[sel] for x in inputs])`` -> [C, m], the level-k
            value at a selection of points (a contiguous slice of them).
        nearest: read only the nearest level ``round(D)``, weight 1.

    Returns:
        [C, M]: ``(1 - frac(D)) read(floor D) + frac(D) read(floor D + 1)``,
        differentiable in D through the weights.

    Points are sorted once by (level, needs the upper level) so that each
    level's points are one contiguous slice: a level is read at exactly the
    points below and above it, no masks over all points per level. The upper
    level is skipped where its weight is 0 (exact integer level, clamped at
    either end) unless D needs a gradient inside the pyramid (d/dD = upper -
    lower).
    """
    M = D.shape[0]
    Dd = D.detach()
    if nearest:
        k0 = torch.floor(Dd + 0.5).clamp_(0, levels - 1)
        upper = torch.zeros_like(k0, dtype=torch.bool)
    else:
        k0 = torch.floor(Dd).clamp_(0, levels - 1)
        upper = (k0 < levels - 1) & ((Dd > k0) | (D.requires_grad & (Dd > 0)))
    key = k0.long() * 2 + upper.long()
    counts = torch.bincount(key, minlength=2 * levels).tolist()
    bounds = [0]
    for c in counts:
        bounds.append(bounds[-1] + c)
    used = [i for i, c in enumerate(counts) if c]
    if len(used) == 1:
        perm = None
        xs, Ds = list(inputs), D
    else:
        # Small keys sort several times faster as uint8 (levels <= 64).
        perm = torch.argsort(key.to(torch.uint8) if levels <= 64 else key)
        xs = [x.index_select(0, perm) for x in inputs]
        Ds = D.index_select(0, perm)
    lower, upper_parts = [], []
    for k in range(levels):
        # Keys 2k-1 (level k-1 blending up), 2k, 2k+1 (level k, below):
        # consecutive, hence one slice of the sorted points.
        lo, mid, hi = bounds[max(2 * k - 1, 0)], bounds[2 * k], bounds[2 * k + 2]
        if hi == lo:
            continue
        vals = read(k, [x[lo:hi] for x in xs])
        if mid > lo:
            upper_parts.append((2 * k - 1, vals[:, :mid - lo] * (Ds[lo:mid] - (k - 1))))
        if hi > mid:
            v = vals[:, mid - lo:]
            lower.append(v if nearest else v * (1 - (Ds[mid:hi] - k)))
    out = torch.cat(lower, 1) if len(lower) > 1 else lower[0]
    if upper_parts:
        # Upper terms belong to the odd-key slices; zeros pad the even ones.
        pieces, done = [], 0
        for key_odd, part in upper_parts:
            if bounds[key_odd] > done:
                pieces.append(out.new_zeros((out.shape[0], bounds[key_odd] - done)))
            pieces.append(part)
            done = bounds[key_odd + 1]
        if done < M:
            pieces.append(out.new_zeros((out.shape[0], M - done)))
        out = out + torch.cat(pieces, 1)
    if perm is None:
        return out
    return out.new_zeros(out.shape).index_copy(1, perm, out)


def trilinear_points(levels: Sequence[Tensor], uv: Tensor, D: Tensor, wrap_u: str, wrap_v: str,
                     border: float, *, nearest_mip: bool = False) -> Tensor:
    """Trilinear taps of one texture.

    Args:
        levels: the pyramid of one texture, ``[1, C, H_k, W_k]`` each.
        uv: [M, 2] sample points (DESIGN.md convention).
        D: [M] clamped level per point.
        wrap_u, wrap_v, border: as in ``separable_sample``.
        nearest_mip: bilinear at the nearest level instead of blending two.

    Returns:
        [C, M]. Differentiable in every level, uv and D (D: trilinear only).
    """
    def read(k: int, xs: list[Tensor]) -> Tensor:
        return separable_sample(levels[k], xs[0].unsqueeze(0), "linear", wrap_u, wrap_v, border)[0]

    return mip_blend(D, len(levels), [uv], read, nearest=nearest_mip)

"""Trilinear (and nearest-mip) filtering: the bilinear tap of two adjacent mip levels, blended.

This is the *trilinear tap* that the anisotropic filter calls once per
probe, and ``mip_blend``, its level grouping and blend, is shared with the
EWA filter. Work is proportional to the points a level serves: points are
sorted by level once, each level is read (with ``separable_sample``, the one
bilinear of the package) only at the points that use it, and the results
are put back in order with one ``index_add``. A point whose level is an
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
            value at a selection of points.
        nearest: read only the nearest level ``round(D)``, weight 1.

    Returns:
        [C, M]: ``(1 - frac(D)) read(floor D) + frac(D) read(floor D + 1)``,
        differentiable in D through the weights.

    Every (point, level) pair to read is one *entry*: each point's lower
    level, plus its upper level where that has a weight. Entries are sorted
    by level once, so each level's entries are one contiguous block: one
    gather of the inputs, one split, a read per level, one concatenation and
    one ``index_add`` back to the points, whatever the number of levels (the
    backward is as short). The upper level is skipped where its weight is 0
    (exact integer level, clamped at either end) unless D needs a gradient
    inside the pyramid (d/dD = upper - lower).
    """
    M = D.shape[0]
    Dd = D.detach()
    if nearest:
        k0 = torch.floor(Dd + 0.5).clamp_(0, levels - 1)
        upper = None
    else:
        k0 = torch.floor(Dd).clamp_(0, levels - 1)
        upper = (k0 < levels - 1) & ((Dd > k0) | (D.requires_grad & (Dd > 0)))
        if not bool(upper.any()):
            upper = None
    lev = k0.to(torch.uint8) if levels <= 256 else k0.long()
    point = None
    if upper is not None:
        up = upper.nonzero().squeeze(1)
        point = torch.cat((torch.arange(M, device=D.device), up))
        lev = torch.cat((lev, lev.index_select(0, up) + 1))
    counts = torch.bincount(lev, minlength=levels).tolist()
    used = [k for k, c in enumerate(counts) if c]
    if len(used) > 1:
        # Small keys sort several times faster as uint8 (measured on CPU).
        perm = torch.sort(lev, stable=True).indices
        point = perm if point is None else point.index_select(0, perm)
        lev = lev.index_select(0, perm)
    if point is None:  # every point reads one level, in order
        xs, De = list(inputs), D
    else:
        xs = [x.index_select(0, point) for x in inputs]
        De = D.index_select(0, point)
    sizes = [counts[k] for k in used]
    parts = [read(k, list(chunk)) for k, chunk in zip(used, zip(*(x.split(sizes) for x in xs)))]
    vals = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
    if not nearest:
        # Tent weight 1 - |D - k|, written per side so that d/dD is -1 for
        # the lower level and +1 for the upper one even where D = k exactly.
        k = lev.to(D.dtype)
        below = De >= k
        vals = vals * torch.where(below, 1 - (De - k), 1 + (De - k))
    if point is None:
        return vals
    return vals.new_zeros((vals.shape[0], M)).index_add(1, point, vals)


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

"""Trilinear (and nearest-mip) filtering: the bilinear tap of two adjacent mip levels, blended.

This is the *trilinear tap* that the anisotropic filter calls once per
probe and whose level grouping the EWA filter shares. Work is proportional
to the pixels a level serves: points are grouped by level, each level is
read (with ``separable_sample``, the one bilinear of the package) only at
the points that use it, and the weighted values are summed back with one
``index_add``. A point whose level is an exact integer, or clamped to the
ends of the pyramid, costs one bilinear tap, not two.

Flat layout: one texture's levels ``[1, C, H_k, W_k]``, points ``[M, ...]``,
result ``[C, M]``; ``difftex.sample`` does batching and checks.
"""
from __future__ import annotations

from typing import Iterator, Sequence

import torch
from torch import Tensor

from .basic import separable_sample


def level_groups(D: Tensor, levels: int, *, nearest: bool = False) -> Iterator[tuple[int, Tensor, Tensor | None]]:
    """Split points by the mip levels they read, with their blend weights.

    Args:
        D: [M] level per point, already clamped to ``[0, levels - 1]``
            (``difftex.lod.level``); may carry a gradient.
        levels: number of levels.
        nearest: read only the nearest level (``round(D)``), weight 1.

    Yields:
        ``(k, index, weight)``: level k, the int64 indices of the points that
        read it, and their weights (``1 - frac(D)`` from below, ``frac(D)``
        from above; ``None`` means all ones). Weights sum to 1 per point and
        carry d/dD.
    """
    Dd = D.detach()
    if nearest:
        k = torch.floor(Dd + 0.5).clamp_(0, levels - 1).long()
        for lev in torch.bincount(k, minlength=levels).nonzero().flatten().tolist():
            yield lev, (k == lev).nonzero().flatten(), None
        return
    k0 = torch.floor(Dd).clamp_(0, levels - 1)
    frac = D - k0
    # The upper level is skipped where its weight is 0 (exact integer level,
    # clamped at either end), except that a D that needs a gradient inside
    # the pyramid still reads it: d/dD = upper - lower.
    upper = (k0 < levels - 1) & ((Dd > k0) | (D.requires_grad & (Dd > 0)))
    k0 = k0.long()
    k1 = torch.where(upper, k0 + 1, k0)
    # One bincount finds the levels in use, so unused levels cost nothing.
    used = torch.bincount(torch.cat((k0, k1[upper])), minlength=levels).nonzero().flatten().tolist()
    for lev in used:
        lo = k0 == lev
        hi = upper & (k1 == lev)
        if not bool(hi.any()):
            idx = lo.nonzero().flatten()
            # frac is 0 wherever there is no upper partner (D == k0), so the
            # weight is 1 unless some of these points blend upwards or D
            # needs its gradient.
            blend = D.requires_grad or bool((upper & lo).any())
            yield lev, idx, (1 - frac[idx]) if blend else None
            continue
        idx = (lo | hi).nonzero().flatten()
        f = frac[idx]
        yield lev, idx, torch.where(lo[idx], 1 - f, f)


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
    M = uv.shape[0]
    C = levels[0].shape[1]
    idxs, vals = [], []
    for k, idx, w in level_groups(D, len(levels), nearest=nearest_mip):
        pts = uv if idx.numel() == M else uv.index_select(0, idx)
        v = separable_sample(levels[k], pts.unsqueeze(0), "linear", wrap_u, wrap_v, border)[0]
        idxs.append(idx)
        vals.append(v if w is None else v * w)
    if len(vals) == 1 and idxs[0].numel() == M:
        return vals[0]
    out = uv.new_zeros((C, M))
    return out.index_add(1, torch.cat(idxs), torch.cat(vals, 1))

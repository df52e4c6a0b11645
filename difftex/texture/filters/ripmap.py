"""The "ripmap" filter: bilinear taps on the ripmap level that fits the footprint's axis-aligned box.

Per point the footprint's bounding box is ``w_u x w_v`` level-0 texels
(``lod.log2_extents``); each axis gets its own level with the level formula
of the mip filters, ``D_u = clamp(log2 w_u + lod_bias, 0, n_u - 1)`` and
likewise ``D_v``, and the point blends the bilinear reads of the four
levels ``(floor D_u + a, floor D_v + b)``, a, b in {0, 1}, with the weights
``(1 - f_u or f_u) (1 - f_v or f_v)`` (f the fractional parts): trilinear
with one more axis. The blend is ``mip_blend`` nested once (over D_v, then
over D_u inside each row of levels), so each axis' level gradient follows
DESIGN.md's rule (the derivative from below at integer levels and at the
clamps) exactly as trilinear's does, and each level is read once for the
points that use it.

A box matches the footprint where the footprint is axis-aligned (a
grazing view along u or v): there a ripmap level is 2^D_u x 2^D_v texels,
the footprint's own shape, where trilinear blurs both axes to the longer
one. A diagonal footprint's box is larger than the footprint (a 45-degree
line of length L has an L / sqrt 2 square box): the blur reaches across
the footprint, the seed notes' "diagonal footprints still a problem".
"""
from __future__ import annotations

from typing import Union

import torch
from torch import Tensor

from ..lod import footprint, level, log2_extents
from ..pyramid.ripmap import Ripmap, build_ripmap, ripmap_counts
from ..taps import levels_read
from .separable import separable_sample
from .trilinear import mip_blend, per_level


def ripmap_levels(uv_dx: Tensor, uv_dy: Tensor, lod_bias: Union[float, Tensor], height: int, width: int,
                  counts: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Per point ``(D_u, D_v)``: each axis' level, ``clamp(log2 extent + lod_bias, 0, n - 1)``; [M] each.

    uv_dx, uv_dy: [M, 2]; lod_bias a number, 0-dim or [M]; counts (n_u, n_v).
    Differentiable in the derivatives and the bias (DESIGN.md's level rule).
    """
    ext = log2_extents(footprint(uv_dx, uv_dy, height, width))
    return level(ext[..., 0], lod_bias, counts[0]), level(ext[..., 1], lod_bias, counts[1])


def ripmap_points(source: Union[Tensor, Ripmap], uv: Tensor, uv_dx: Tensor, uv_dy: Tensor,
                  lod_bias: Union[float, Tensor], wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """The ripmap filter at flat points of one texture.

    Args:
        source: the texture [1, C, H, W] (its ripmap is built here, only as
            far as the points read) or its Ripmap.
        uv, uv_dx, uv_dy: [M, 2] (DESIGN.md conventions).
        lod_bias: a number, a 0-dim tensor or [M].
        wrap_u, wrap_v, border: as in ``separable_sample``.

    Returns:
        [C, M]; NaN where uv is not finite (those points pass no gradient).
        Differentiable in the texture (through the ripmap's adjoint) or the
        Ripmap's levels, uv, the derivatives and the bias.
    """
    base = source.base if isinstance(source, Ripmap) else source
    H, W = base.shape[-2:]
    counts = source.counts if isinstance(source, Ripmap) else ripmap_counts(H, W)
    D_u, D_v = ripmap_levels(uv_dx, uv_dy, lod_bias, H, W, counts)
    if isinstance(source, Ripmap):
        rip = source
    else:
        counts = (levels_read(D_u, counts[0], False), levels_read(D_v, counts[1], False))
        rip = Ripmap(build_ripmap(base, *counts))
    # A non-finite uv reads a safe point and gets NaN put back (trilinear_points does the same): a NaN value
    # would meet mip_blend's d/dD and send NaN to the derivatives even where the loss masks the point out.
    ok = torch.isfinite(uv).all(-1)
    safe = torch.where(ok.unsqueeze(-1), uv, 0.0)

    def read_row(j: int, xs: list[Tensor]) -> Tensor:
        def read_level(i: int, ys: list[Tensor]) -> Tensor:
            return separable_sample(rip[i, j], ys[0].unsqueeze(0), "linear", wrap_u, wrap_v, border)[0]
        return mip_blend(xs[1], counts[0], [xs[0]], per_level(read_level))

    out = mip_blend(D_v, counts[1], [safe, D_u], per_level(read_row))
    return torch.where(ok, out, float("nan"))

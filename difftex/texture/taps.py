"""The footprint front end of the mip filters: per point the level and the taps, and how many levels they read."""
from __future__ import annotations

import math
from typing import Optional, Sequence, Union

import torch
from torch import Tensor

from .._checks import broadcast_batch, check_float, check_same
from .. import _native as native
from .filters.anisotropic import anisotropic_taps, tap_count
from .filters.auto import auto_tap_count
from .lod import check_lod_bias, ellipse, footprint, level, log2_length, size_and_levels
from .options import BOX_FILTERS, DEFAULT_TOLERANCE, MAX_ANISO, MIP_FILTERS, check_filter, check_number
from .pyramid.mipmap import level_count


def levels_read(D: Tensor, levels: int, nearest: bool) -> int:
    """How many of ``levels`` pyramid levels the bilinear-tap filters read at the levels D (clamped to them).

    The coarsest is round(D) for nearest-mip, else ceil(D): ``mip_blend``
    reads the levels ``ceil(D) - 1`` and ``ceil(D)`` (the lower one only for
    the derivative where D is an integer).
    """
    if D.numel() == 0:
        return 1
    with torch.no_grad():
        top = torch.floor(D + 0.5) if nearest else torch.ceil(D)
        return min(int(top.max().item()) + 1, levels)


def taps(filter: str, dx: Tensor, dy: Tensor, bias: Union[float, Tensor], height: int, width: int, levels: int,
          max_aniso: float, tolerance: float) -> tuple[Tensor, Optional[Tensor], Optional[Tensor]]:
    """The footprint front end of the bilinear-tap mip filters: per point the level and the taps.

    dx, dy: [M, 2]; bias: a number, a 0-dim tensor or [M]. Returns (D [M]
    clamped to ``[0, levels - 1]``, axis [M, 2], count [M] int64), axis and
    count None for trilinear / nearest-mip (one tap a point), and None where
    every point takes one tap on the torch path. Where no gradient reaches
    dx, dy or the bias, the native kernel computes it in one pass on the CPU
    (``native/csrc/front.cpp``: the same values to rounding, 5-14x faster
    than these torch ops at 512^2 points, which are its reference).
    """
    kind = {"trilinear": 0, "nearest-mip": 0, "anisotropic": 1, "auto": 2}[filter]
    grad = torch.is_grad_enabled() and (dx.requires_grad or dy.requires_grad or
                                        (isinstance(bias, Tensor) and bias.requires_grad))
    kernel = None if grad else native.kernel(dx)
    if kernel is not None:
        per_point = isinstance(bias, Tensor) and bias.dim() == 1
        D, axis, count = kernel.front(dx, dy,
                                      bias.detach().contiguous() if per_point else dx.new_empty(0),
                                      bias0=0.0 if per_point else float(bias), height=height, width=width,
                                      levels=levels, kind=kind, max_aniso=max_aniso, tolerance=tolerance)
        return (D, axis, count) if kind else (D, None, None)
    if kind == 0:
        return level(log2_length(dx, dy, height, width), bias, levels), None, None
    fp = footprint(dx, dy, height, width)
    ell = ellipse(fp)
    n = (auto_tap_count(ell, fp, bias, max_aniso, tolerance) if filter == "auto"
         else tap_count(ell, fp, max_aniso))
    return anisotropic_taps(fp, ell, n, bias, levels, height, width)


def levels_needed(uv_dx: Tensor, uv_dy: Tensor, texture_size: Sequence[int] | Tensor | object, *,
                  lod_bias: Tensor | float = 0.0, max_aniso: float = 16, filter: str = "trilinear",
                  tolerance: float | None = None) -> int:
    """How many mip levels ``sample(filter=...)`` reads for these footprints: ``mipmap(..., max_levels=...)``.

    Args:
        uv_dx, uv_dy: [B, Ho, Wo, 2] uv per pixel column / row (DESIGN.md);
            B = 1 broadcasts.
        texture_size: (H, W) of level 0, or the texture [..., H, W], or a
            Mipmap (then at most its level count).
        lod_bias: as in ``sample``: a number or [B, Ho, Wo].
        max_aniso, tolerance: as in ``sample`` (tolerance: "auto" only;
            default sample's).
        filter: any filter of ``sample``; the single-level ones, "ripmap"
            and "sat" need 1 (they read a Mipmap's level 0).

    Returns:
        int in ``[1, full chain]``: 1 + the coarsest level any pixel reads
        (``ceil(D)`` of the filter's level D; ``round(D)`` for nearest-mip;
        one more for "ewa", whose coarsest level is filtered differently,
        unless that is the full chain). A pyramid of that depth gives the
        same values as the full one.

    Not differentiable (a count). Zero / NaN derivatives count as level 0,
    infinite ones as the coarsest level. Raises ValueError / TypeError
    naming the argument on bad shapes, dtypes, an unknown filter,
    ``max_aniso`` outside [1, 1024] or ``tolerance < 0``.
    """
    check_float("uv_dx", uv_dx, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_float("uv_dy", uv_dy, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_same("uv_dy", uv_dy, "uv_dx", uv_dx)
    if uv_dx.shape[1:] != uv_dy.shape[1:]:
        raise ValueError(f"uv_dy: expected the shape of uv_dx {tuple(uv_dx.shape)} (B = 1 broadcasts), "
                         f"got {tuple(uv_dy.shape)}")
    check_filter(filter)
    max_aniso = check_number("max_aniso", max_aniso, 1, MAX_ANISO)
    tolerance = check_number("tolerance", DEFAULT_TOLERANCE if tolerance is None else tolerance, 0)
    H, W, full = size_and_levels(texture_size)
    if full is None:
        full = level_count(H, W)
    check_lod_bias(lod_bias, uv_dx)
    sizes = [uv_dx.shape[0], uv_dy.shape[0]] + ([lod_bias.shape[0]] if isinstance(lod_bias, Tensor) and
                                                lod_bias.dim() == 3 else [])
    broadcast_batch(["uv_dx", "uv_dy", "lod_bias"][:len(sizes)], sizes)
    if filter not in MIP_FILTERS or filter in BOX_FILTERS or full == 1:
        return 1  # the box filters read a Mipmap's level 0 (and build their own ripmap / table)
    with torch.no_grad():
        bias = lod_bias.detach() if isinstance(lod_bias, Tensor) else float(lod_bias)
        B = max(uv_dx.shape[0], uv_dy.shape[0], bias.shape[0] if isinstance(bias, Tensor) and bias.dim() else 1)
        dx = uv_dx.detach().expand(B, -1, -1, -1)
        dy = uv_dy.detach().expand(B, -1, -1, -1)
        if isinstance(bias, Tensor) and bias.dim() == 3:
            bias = bias.expand(B, -1, -1)
        if dx.numel() == 0:
            return 1
        if filter == "ewa":  # the level of EWA's minor axis, grown to major / max_aniso
            fp = footprint(dx, dy, H, W)
            ell = ellipse(fp)
            D = level(torch.maximum(ell.log2_minor, ell.log2_major - math.log2(max_aniso)), bias, full)
            # one more: never let a truncated top stand in for the real coarsest level
            return min(levels_read(D, full, False) + 1, full)
        if isinstance(bias, Tensor) and bias.dim() == 3:
            bias = bias.reshape(-1)
        D = taps(filter, dx.reshape(-1, 2), dy.reshape(-1, 2), bias, H, W, full, max_aniso, tolerance)[0]
        return levels_read(D, full, filter == "nearest-mip")

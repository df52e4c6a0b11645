"""References the filters are scored against: supersampled renders and the checker's closed form.

The supersampled reference is the box average of ss x ss bilinear
level-0 samples a pixel; the closed form is the exact mean of an ideal
checker over a pixel's footprint on the grazing plane of
:func:`difftex.testing.grazing_plane` (no sampling at all).
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from .scenes import grazing_plane


def supersampled(texture: Tensor, uv_ss: Tensor, ss: int, wrap: str | Sequence[str] = "repeat",
                 chunk_rows: int = 16) -> Tensor:
    """Box average of ss x ss bilinear level-0 samples a pixel: the reference of a minified render.

    Args:
        texture: [1 or B, C, H, W].
        uv_ss: [B, Ho * ss, Wo * ss, 2], the uv at the ss x ss sub-pixel
            centres of every pixel (e.g. ``grazing_plane(res, ss=ss)[0]``).
        ss: sub-samples a pixel along each axis.
        wrap: passed to :func:`difftex.sample`.
        chunk_rows: output rows rendered at a time (bounds the memory of the
            ss^2-times larger lookup).

    Returns:
        [B, C, Ho, Wo], computed under no_grad (a fixture).

    Raises:
        ValueError: ``ss`` or ``chunk_rows`` < 1, or uv_ss's size not a multiple of ss.
    """
    import difftex

    if ss < 1 or chunk_rows < 1 or uv_ss.dim() != 4 or uv_ss.shape[1] % ss or uv_ss.shape[2] % ss:
        raise ValueError(f"supersampled: expected ss >= 1, chunk_rows >= 1 and uv_ss [B, Ho * ss, Wo * ss, 2], got "
                         f"ss={ss}, chunk_rows={chunk_rows}, uv_ss of shape {tuple(uv_ss.shape)}")
    with torch.no_grad():
        rows = [F.avg_pool2d(difftex.sample(texture, chunk, filter="bilinear", wrap=wrap), ss)
                for chunk in torch.split(uv_ss, chunk_rows * ss, dim=1)]
        return torch.cat(rows, 2)


def _tri(x: Tensor) -> Tensor:
    """T(x) = integral_0^x s, s(t) = (-1)^floor(t): a triangle wave of period 2 between 0 and 1."""
    r = torch.remainder(x, 2.0)
    return torch.where(r < 1, r, 2 - r)


def _tri2(x: Tensor) -> Tensor:
    """integral_0^x T: one per period of 2, plus the in-period part (piecewise quadratic)."""
    r = torch.remainder(x, 2.0)
    part = torch.where(r < 1, 0.5 * r * r, 0.5 + 2 * (r - 1) - 0.5 * (r * r - 1))
    return torch.floor(x / 2.0) + part


def checker_footprint_mean(uv: Tensor, uv_dx: Tensor, uv_dy: Tensor, checks: int,
                           lo: float = 0.1, hi: float = 0.9) -> Tensor:
    """Exact mean of the ideal checker over each pixel's parallelogram footprint.

    The checker is ``c(u, v) = lo + (hi - lo) (1 - s(n u) s(n v)) / 2`` with
    ``s(t) = (-1)^floor(t)`` and n = checks per uv unit; the footprint is
    ``uv + a uv_dx + b uv_dy``, a, b uniform in [-1/2, 1/2] (the affine
    approximation of the pixel's preimage that the filters also use).  It
    requires ``uv_dx`` along u only (``uv_dx[..., 1] == 0``), which holds
    exactly for :func:`grazing_plane` (its camera only pitches).  In check
    units, with ``A = n du/dx``, ``B = n du/dy``, ``C = n dv/dy``:

        mean(s s) = int_b s(v0 + b C) Q(b) db,
        Q(b) = int_a s(u0 + b B + a A) da = [T(u0 + bB + A/2) - T(u0 + bB - A/2)] / A,

    with T the triangle wave (antiderivative of s).  s(v0 + bC) is constant
    between the b where v0 + bC is an integer, and on each such piece the
    integral of Q is closed form with T2 = int T:
    ``[T2(u0 + bB + A/2) - T2(u0 + bB - A/2)] / (A B)`` between its ends.
    Where |A| or |B| is tiny the limits (point sample in a, midpoint in b)
    are used, whose error is O(A^2), O(B^2).  Computed in float64.

    Args:
        uv, uv_dx, uv_dy: [B, H, W, 2] as returned by grazing_plane.
        checks: checker squares per uv unit (per texture repeat).

    Returns:
        [B, 1, H, W] float64 mean value (one channel; the checker is grey).
    """
    if float(uv_dx[..., 1].abs().max()) > 1e-9 * max(1.0, float(uv_dx.abs().max())):
        raise ValueError("checker_footprint_mean: uv_dx must run along u only (uv_dx[..., 1] == 0)")
    n = float(checks)
    u0, v0 = (uv[..., 0].double() * n), (uv[..., 1].double() * n)
    A = uv_dx[..., 0].double() * n
    Bq = uv_dy[..., 0].double() * n
    C = uv_dy[..., 1].double() * n
    # Break points of s(v0 + b C) in b: integers k strictly inside v0 +- |C|/2.
    kmin = torch.floor(v0 - C.abs() / 2) + 1
    K = int(torch.ceil(C.abs().max()).item()) + 2
    k = kmin.unsqueeze(-1) + torch.arange(K, dtype=torch.float64)
    Csafe = torch.where(C.abs() > 1e-12, C, torch.ones_like(C))
    bk = ((k - v0.unsqueeze(-1)) / Csafe.unsqueeze(-1)).clamp(-0.5, 0.5)
    bk = torch.where(C.abs().unsqueeze(-1) > 1e-12, bk, torch.full_like(bk, 0.5))
    ends = torch.cat([torch.full_like(bk[..., :1], -0.5), bk, torch.full_like(bk[..., :1], 0.5)], -1)
    ends, _ = torch.sort(ends, -1)
    b0, b1 = ends[..., :-1], ends[..., 1:]
    mid = 0.5 * (b0 + b1)
    sign = 1.0 - 2.0 * torch.remainder(torch.floor(v0.unsqueeze(-1) + mid * C.unsqueeze(-1)), 2.0)
    A_, B_, u_ = A.unsqueeze(-1), Bq.unsqueeze(-1), u0.unsqueeze(-1)
    smallA = A_.abs() < 1e-7
    Asafe = torch.where(smallA, torch.ones_like(A_), A_)

    def Q(b: Tensor) -> Tensor:
        x = u_ + b * B_
        sq = 1.0 - 2.0 * torch.remainder(torch.floor(x), 2.0)
        return torch.where(smallA, sq, (_tri(x + A_ / 2) - _tri(x - A_ / 2)) / Asafe)

    smallB = (B_ * (b1 - b0)).abs() < 1e-6
    Bsafe = torch.where(B_.abs() < 1e-300, torch.ones_like(B_), B_)

    def T2diff(b: Tensor) -> Tensor:
        x = u_ + b * B_
        return (_tri2(x + A_ / 2) - _tri2(x - A_ / 2)) / Asafe

    exact = (T2diff(b1) - T2diff(b0)) / Bsafe
    piece = torch.where(smallB | smallA, Q(mid) * (b1 - b0), exact)
    ss = (sign * piece).sum(-1)
    return (lo + (hi - lo) * (1 - ss) / 2).unsqueeze(1)


def checker_pixel_box_mean(res: int, pitch: float, fov_deg: float, checks: int, lo: float = 0.1,
                           hi: float = 0.9, strips: int = 16) -> Tensor:
    """Mean of the ideal checker over each pixel's true (screen-space box) footprint on the grazing plane.

    The camera of :func:`grazing_plane` only pitches, so along an image row
    v is constant and u affine in the column: a pixel's preimage is a
    trapezoid, and a horizontal strip of it ``1 / strips`` pixels tall is,
    up to the perspective curvature inside the strip (O(strips^-2)), the
    parallelogram at the strip's centre with the full pixel width.  Each
    strip is integrated exactly by :func:`checker_footprint_mean` and the
    strips averaged: exact along the row, no aliasing across check edges,
    only the smooth perspective term approximated.

    Returns:
        [1, 1, res, res] float64.
    """
    uv, dx, dy = grazing_plane(res, pitch, 1.0, fov_deg=fov_deg, ss=strips, dtype=torch.float64)
    n = strips
    # Strip centres at the pixel's centre column: the mean of the two middle
    # sub-columns (u is affine along a row); the strip's width is the whole
    # pixel (n sub-columns), its height one sub-row.
    mid = uv.view(1, res * n, res, n, 2)[:, :, :, n // 2 - 1:n // 2 + 1].mean(3)
    dxs = dx.view(1, res * n, res, n, 2)[:, :, :, 0] * n
    dys = dy.view(1, res * n, res, n, 2)[:, :, :, 0]
    m = checker_footprint_mean(mid, dxs, dys, checks, lo, hi)  # [1, 1, res * n, res]
    return m.view(1, 1, res, n, res).mean(3)


# --------------------------------------------------------------------------

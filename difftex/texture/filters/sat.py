"""The "sat" filter: the exact box average over the footprint's axis-aligned box, from a summed-area table.

Crow's summed-area table (SIGGRAPH 1984). Texel ``(r, c)`` covers the unit
square ``[c, c + 1) x [r, r + 1)`` of texel space (``x = u W``, ``y = v H``)
and the texture is read as constant on it. Its antiderivative
``I(x, y) = int_0^x int_0^y f`` is, at integer corners, the table
``S[b, a] = sum_{r < b, c < a} f[r, c]`` ([H + 1, W + 1], a zero first row
and column), and in between exactly the bilinear interpolation of S (f is
constant on each cell, so I is bilinear there). A box's integral is then
``I(x1, y1) - I(x0, y1) - I(x1, y0) + I(x0, y0)``: fractional edges cost
nothing extra, a texel partly inside weighs by its covered fraction.

Wrap modes extend I per axis (u shown; v alike), with ``G(x) = I(x, .)``:

* repeat: ``G(x) = q G(W) + G(r)`` for ``x = q W + r``, ``0 <= r < W``;
* mirror (period 2W): ``G(x) = 2q G(W) + G(r)`` for ``r <= W``, else
  ``(2q + 2) G(W) - G(2W - r)``;
* clamp: the edge texel continues, i.e. G extends linearly past 0 and W
  with the slope of the end cells: the bilinear interpolation of S
  extrapolated (the interpolation's fraction is left unclamped);
* border: ``I_ext(x, y) = I(cx, cy) + b (x y - cx cy)`` with ``cx, cy`` the
  coordinates clamped to the texture along the border axes (the border
  constant b fills the rest of the box).

So a box sum is ``sum_k sum_l cu_k cv_l S~(pu_k, pv_l)``, S~ the bilinear
(extrapolating) interpolation of S, with 2 terms per axis for clamp /
border and 3 for repeat / mirror (both corners and the whole periods
between them): 16 to 36 table reads per channel, whatever the box's size.

The box is centred at uv with sides ``2^D_u x 2^D_v`` texels, ``D = clamp(
log2 extent + lod_bias, 0, log2 period)`` per axis (the extents of
``lod.log2_extents``; the period is W, 2W for mirror). The floor of one
texel makes a magnified lookup bilinear interpolation (the box average of
one texel width over constant texels is the tent filter between texel
centres), the cap of one period makes an infinite footprint the texture's
mean under repeat and mirror.

Precision: the table is float64 (a float32 table of 4096^2 values near 1
would hold sums of 1.6e7 to 0.5 ulp = 1, useless for a one-texel box), the
coefficients and positions too; the result is cast back to the texture's
dtype. Memory: the table is 8 bytes a texel and channel, made anew on each
call; the backward keeps only the texture and the [M, K] positions and
coefficients (``_BoxSums``), and its texture gradient is the adjoint of the
prefix sums, a suffix sum of the scattered weights.
"""
from __future__ import annotations

import math
from typing import Union

import torch
from torch import Tensor

from ..lod import footprint, level, log2_extents
from ..wrap import drop_periods, floor_index

# Points per chunk of the table reads (and their backward): bounds the
# gathered [chunk, 36, C] float64 values to a few tens of MB.
_CHUNK_VALUES = 1 << 22


def summed_area_table(texture: Tensor) -> Tensor:
    """The table of one texture [1, C, H, W]: [(H + 1) * (W + 1), C] float64, row-major, channels last.

    Differentiable where autograd records (out-of-place ops); under no_grad
    built in place in one buffer.
    """
    _, C, H, W = texture.shape
    t = texture[0].permute(1, 2, 0)
    if torch.is_grad_enabled() and texture.requires_grad:
        S = torch.nn.functional.pad(t.double().cumsum(0).cumsum(1), (0, 0, 1, 0, 1, 0))
    else:
        S = texture.new_zeros((H + 1, W + 1, C), dtype=torch.float64)
        S[1:, 1:] = t
        S.cumsum_(0).cumsum_(1)
    return S.reshape((H + 1) * (W + 1), C)


def _axis_weights(p: Tensor, c: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Per term the two table entries of the (extrapolating) linear interpolation along an axis of n cells.

    p, c: [m, K] positions (0..n, outside for clamp) and coefficients.
    Returns weights [m, 2K] (``c (1 - s)``, ``c s``) and entry indices [m, 2K].
    """
    i = floor_index(p.detach()).clamp_(0, n - 1)
    s = p - i.to(p.dtype)
    return torch.stack((c * (1 - s), c * s), -1).flatten(1), torch.stack((i, i + 1), -1).flatten(1)


def _weights(pu: Tensor, cu: Tensor, pv: Tensor, cv: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Weights [m, J] and flat table indices [m, J] of the box sums (J = 4 Ku Kv)."""
    wu, iu = _axis_weights(pu, cu, width)
    wv, iv = _axis_weights(pv, cv, height)
    w = (wv.unsqueeze(2) * wu.unsqueeze(1)).flatten(1)
    idx = (iv.unsqueeze(2) * (width + 1) + iu.unsqueeze(1)).flatten(1)
    return w, idx


def _read(table: Tensor, w: Tensor, idx: Tensor) -> Tensor:
    """sum_j w[m, j] table[idx[m, j]]: [m, C]."""
    vals = table.index_select(0, idx.reshape(-1)).view(*idx.shape, table.shape[1])
    return torch.bmm(w.unsqueeze(1), vals).squeeze(1)


def box_sums_reference(texture: Tensor, pu: Tensor, cu: Tensor, pv: Tensor, cv: Tensor) -> Tensor:
    """``_BoxSums`` in autograd-tracked torch ops (its double backward, and the tests' reference)."""
    H, W = texture.shape[-2:]
    w, idx = _weights(pu, cu, pv, cv, H, W)
    return _read(summed_area_table(texture), w, idx)


def _chunks(m: int, terms: int, channels: int) -> list[slice]:
    step = max(1, _CHUNK_VALUES // max(1, terms * channels))
    return [slice(a, min(a + step, m)) for a in range(0, m, step)]


class _BoxSums(torch.autograd.Function):
    """Box sums ``sum_k sum_l cu_k cv_l S~(pu_k, pv_l)`` of one texture [1, C, H, W] -> [M, C] float64.

    pu, cu: [M, Ku]; pv, cv: [M, Kv] float64 (positions in texel units,
    coefficients). The backward recomputes the table only for the position
    and coefficient gradients, and gives the texture the adjoint of the
    prefix sums: the weights scattered into a [H + 1, W + 1] buffer, then
    suffix-summed along both axes.
    """

    @staticmethod
    def forward(ctx, texture: Tensor, pu: Tensor, cu: Tensor, pv: Tensor, cv: Tensor) -> Tensor:
        ctx.save_for_backward(texture, pu, cu, pv, cv)
        H, W = texture.shape[-2:]
        table = summed_area_table(texture)
        out = pu.new_empty((pu.shape[0], table.shape[1]))
        for sl in _chunks(pu.shape[0], 4 * pu.shape[1] * pv.shape[1], table.shape[1]):
            out[sl] = _read(table, *_weights(pu[sl], cu[sl], pv[sl], cv[sl], H, W))
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        texture, pu, cu, pv, cv = ctx.saved_tensors
        need = ctx.needs_input_grad
        if torch.is_grad_enabled():
            # Double backward (create_graph=True): differentiate the torch reference.
            inputs = [x for x, n in zip((texture, pu, cu, pv, cv), need) if n]
            with torch.enable_grad():
                out = box_sums_reference(texture, pu, cu, pv, cv)
                got = iter(torch.autograd.grad(out, inputs, grad, create_graph=True, allow_unused=True))
            return tuple(next(got) if n else None for n in need)
        _, C, H, W = texture.shape
        need_geom = any(need[1:])
        table = summed_area_table(texture.detach()) if need_geom else None
        g_table = grad.new_zeros(((H + 1) * (W + 1), C)) if need[0] else None
        g_geom: list[list[Tensor]] = [[] for _ in range(4)]
        for sl in _chunks(pu.shape[0], 4 * pu.shape[1] * pv.shape[1], C):
            g = grad[sl]
            # The weights again, as a small local graph: its gradient carries the positions' and coefficients'.
            geom = [x[sl].detach().requires_grad_(n) for x, n in zip((pu, cu, pv, cv), need[1:])]
            with torch.enable_grad():
                w, idx = _weights(*geom, H, W)
            if g_table is not None:
                g_table.index_add_(0, idx.reshape(-1), (w.detach().unsqueeze(-1) * g.unsqueeze(1)).reshape(-1, C))
            if need_geom:
                vals = table.index_select(0, idx.reshape(-1)).view(*idx.shape, C)
                g_w = torch.bmm(vals, g.unsqueeze(-1)).squeeze(-1)
                leaves = [x for x in geom if x.requires_grad]
                parts = iter(torch.autograd.grad(w, leaves, g_w, allow_unused=True))
                for k, x in enumerate(geom):
                    if x.requires_grad:
                        part = next(parts)
                        g_geom[k].append(torch.zeros_like(x) if part is None else part)
        grad_tex = None
        if g_table is not None:
            # Adjoint of S[b, a] = sum_{r < b, c < a} f[r, c]: grad f[r, c] = sum_{b > r, a > c} grad S[b, a].
            g = g_table.view(H + 1, W + 1, C).flip(0, 1).cumsum_(0).cumsum_(1).flip(0, 1)
            grad_tex = g[1:, 1:].permute(2, 0, 1).unsqueeze(0).to(texture.dtype)
        return (grad_tex, *(torch.cat(parts) if n else None for parts, n in zip(g_geom, need[1:])))


def _axis_terms(x0: Tensor, x1: Tensor, n: int, mode: str) -> tuple[Tensor, Tensor]:
    """Positions and coefficients [M, K] of ``G_ext(x1) - G_ext(x0)`` along one axis (module docstring)."""
    if mode in ("clamp", "border"):
        if mode == "border":
            x0, x1 = x0.clamp(0, n), x1.clamp(0, n)
        one = torch.ones_like(x0)
        return torch.stack((x1, x0), -1), torch.stack((one, -one), -1)
    period = 2 * n if mode == "mirror" else n
    ends = torch.stack((x0, x1), -1)
    q = torch.floor(ends.detach() / period)
    r = ends - q * period
    if mode == "repeat":
        whole, p, sign = q, r, torch.ones_like(q)
    else:
        flip = (r.detach() > n).to(r.dtype)
        whole, p, sign = 2 * q + 2 * flip, r + flip * (2 * n - 2 * r), 1 - 2 * flip
    full = torch.full_like(x0, float(n))
    pos = torch.stack((full, p[..., 1], p[..., 0]), -1)
    coef = torch.stack((whole[..., 1] - whole[..., 0], sign[..., 1], -sign[..., 0]), -1)
    return pos, coef


def _box_edges(u: Tensor, log2_ext: Tensor, lod_bias: Union[float, Tensor], n: int, mode: str
               ) -> tuple[Tensor, Tensor]:
    """The box's ends along one axis in texel units, float64: [M] each (module docstring)."""
    period = 2 * n if mode == "mirror" else n
    D = level(log2_ext, lod_bias, 1 + math.log2(period))  # level() clamps to [0, levels - 1]
    half = 0.5 * torch.exp2(D).double()
    if mode in ("repeat", "mirror"):
        c = drop_periods(u, mode).double() * n
    else:
        # A box wholly outside the texture sees only the edge texels (clamp) or the border: moving it
        # further changes nothing, so its centre stops there (and its derivative is 0) rather than
        # forming huge coordinates.
        c = torch.minimum(torch.maximum(u.double() * n, -half), n + half)
    return c - half, c + half


def sat_points(texture: Tensor, uv: Tensor, uv_dx: Tensor, uv_dy: Tensor, lod_bias: Union[float, Tensor],
               wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """The summed-area-table filter at flat points of one texture.

    Args:
        texture: [1, C, H, W].
        uv, uv_dx, uv_dy: [M, 2] (DESIGN.md conventions).
        lod_bias: a number, a 0-dim tensor or [M]: scales the box by
            ``2^lod_bias`` (before its floor of one texel and cap of one period).
        wrap_u, wrap_v, border: as in ``separable_sample``.

    Returns:
        [C, M] in the texture's dtype; NaN where uv is not finite (those
        points pass no gradient). Differentiable in the texture, uv, the
        derivatives and the bias.
    """
    H, W = texture.shape[-2:]
    ok = torch.isfinite(uv).all(-1)
    safe = torch.where(ok.unsqueeze(-1), uv, 0.0)
    ext = log2_extents(footprint(uv_dx, uv_dy, H, W))
    x0, x1 = _box_edges(safe[:, 0], ext[:, 0], lod_bias, W, wrap_u)
    y0, y1 = _box_edges(safe[:, 1], ext[:, 1], lod_bias, H, wrap_v)
    pu, cu = _axis_terms(x0, x1, W, wrap_u)
    pv, cv = _axis_terms(y0, y1, H, wrap_v)
    sums = _BoxSums.apply(texture, pu, cu, pv, cv)
    area = (x1 - x0) * (y1 - y0)
    if "border" in (wrap_u, wrap_v):
        inner = ((x1.clamp(0, W) - x0.clamp(0, W)) if wrap_u == "border" else x1 - x0) * \
                ((y1.clamp(0, H) - y0.clamp(0, H)) if wrap_v == "border" else y1 - y0)
        sums = sums + (border * (area - inner)).unsqueeze(-1)
    out = (sums / area.unsqueeze(-1)).to(texture.dtype).t()
    return torch.where(ok, out, float("nan"))

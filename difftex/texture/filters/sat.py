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
* clamp: the edge texel continues, so G extends linearly past 0 and W with
  the slope of the end cells: ``G(x) = G(c) + (x - c) (G(e) - G(e - 1))``,
  ``c`` the coordinate clamped to [0, W], e = W past the far end, 1 before
  0 (a box at most W wide overshoots at one end only);
* border: ``I_ext(x, y) = I(cx, cy) + b (x y - cx cy)`` with ``cx, cy`` the
  coordinates clamped to the texture along the border axes (the border
  constant b fills the rest of the box).

So a box sum is ``sum_k sum_l cu_k cv_l S~(pu_k, pv_l)``, S~ the bilinear
interpolation of S at positions inside the table, with 2 terms per axis
for border, 3 for repeat / mirror (both ends and the whole periods between
them) and 4 for clamp: 4 to 16 bilinear reads of the table per point,
whatever the box's size, all in one ``grid_sample`` call on the float64
table (``align_corners=True`` puts its entries at integer positions).

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

On the CPU the box sums run on the native kernel (``_NativeBoxSums``,
``native/csrc/sat.cpp``: the table built in one threaded pass, the reads,
and the adjoint as one scatter and one suffix-sum pass, where torch needs
two cumsums, grid_sample and its backward on a texture-sized float64
buffer); ``_BoxSums`` (torch ops) serves CUDA and ``difftex.backend(
"reference")``, and ``box_sums_reference`` double backward. The wrap terms
above stay torch ops on [M, K] tensors in every case.
"""
from __future__ import annotations

import math
from typing import Union

import torch
import torch.nn.functional as F
from torch import Tensor

from ... import _native as native
from ..lod import footprint, level, log2_extents
from ..wrap import drop_periods, floor_index

# Values per chunk of the table reads (and their backward): bounds the
# [C, chunk, K] float64 reads and their gradients to a few tens of MB.
_CHUNK_VALUES = 1 << 22


def summed_area_table(texture: Tensor) -> Tensor:
    """The table of one texture [1, C, H, W]: [1, C, H + 1, W + 1] float64, ``S[b, a] = sum_{r < b, c < a} f``.

    Differentiable where autograd records (out-of-place ops); under no_grad
    built in place in one buffer.
    """
    _, C, H, W = texture.shape
    if torch.is_grad_enabled() and texture.requires_grad:
        return F.pad(texture.double().cumsum(-2).cumsum(-1), (1, 0, 1, 0))
    S = texture.new_zeros((1, C, H + 1, W + 1), dtype=torch.float64)
    S[..., 1:, 1:] = texture
    return S.cumsum_(-2).cumsum_(-1)


def _suffix_sums(g: Tensor) -> Tensor:
    """``out[r, c] = sum_{b > r, a > c} g[b, a]`` of a contiguous [..., H + 1, W + 1] buffer (consumed) -> [..., H, W].

    Per axis the sum past index i is the total minus the prefix up to i: one
    in-place cumsum and one subtraction, on contiguous rows (no reversed
    copies; float64 keeps the difference exact enough).
    """
    p = g.cumsum_(-1)
    after = p[..., -1:] - p[..., :-1]  # [..., H + 1, W]: the sums past each column
    q = after.cumsum_(-2)
    return q[..., -1:, :] - q[..., :-1, :]


def _grid(pu: Tensor, pv: Tensor, height: int, width: int) -> Tensor:
    """grid_sample's grid [1, M, Kv * Ku, 2] of every (pu_k, pv_l) pair: align_corners=True puts -1 and 1 on the
    table's first and last entries, i.e. texel-space positions 0 and W (H)."""
    M, Ku, Kv = pu.shape[0], pu.shape[1], pv.shape[1]
    gx = (pu * (2.0 / width) - 1).unsqueeze(1).expand(M, Kv, Ku)
    gy = (pv * (2.0 / height) - 1).unsqueeze(2).expand(M, Kv, Ku)
    return torch.stack((gx, gy), -1).reshape(1, M, Kv * Ku, 2)


def _coefs(cu: Tensor, cv: Tensor) -> Tensor:
    """[M, Kv * Ku] products ``cv_l cu_k`` in the order of ``_grid``."""
    return (cv.unsqueeze(2) * cu.unsqueeze(1)).flatten(1)


def _read(table: Tensor, grid: Tensor) -> Tensor:
    """The table's bilinear interpolation at the grid: [C, M, K]."""
    return F.grid_sample(table, grid, mode="bilinear", padding_mode="border", align_corners=True)[0]


def box_sums_reference(texture: Tensor, pu: Tensor, cu: Tensor, pv: Tensor, cv: Tensor) -> Tensor:
    """``_BoxSums`` in autograd-tracked torch ops, differentiable to any order (double backward, tests).

    The bilinear interpolation of the table written as gathers (grid_sample's
    backward is not differentiable): the cell ``i = clamp(floor(p), 0, n - 1)``
    and the fraction ``p - i`` per axis.
    """
    _, C, H, W = texture.shape
    table = summed_area_table(texture)[0].flatten(1)  # [C, (H + 1) (W + 1)]

    def axis(p: Tensor, c: Tensor, n: int) -> tuple[Tensor, Tensor]:
        i = floor_index(p.detach()).clamp_(0, n - 1)
        s = p - i.to(p.dtype)
        return torch.stack((c * (1 - s), c * s), -1).flatten(1), torch.stack((i, i + 1), -1).flatten(1)

    wu, iu = axis(pu, cu, W)
    wv, iv = axis(pv, cv, H)
    w = (wv.unsqueeze(2) * wu.unsqueeze(1)).flatten(1)
    idx = (iv.unsqueeze(2) * (W + 1) + iu.unsqueeze(1)).flatten(1)
    vals = table.index_select(1, idx.reshape(-1)).view(C, *idx.shape)
    return (vals * w).sum(-1)


def _chunks(m: int, terms: int, channels: int) -> list[slice]:
    step = max(1, _CHUNK_VALUES // max(1, terms * channels))
    return [slice(a, min(a + step, m)) for a in range(0, m, step)]


class _BoxSums(torch.autograd.Function):
    """Box sums ``sum_k sum_l cu_k cv_l S~(pu_k, pv_l)`` of one texture [1, C, H, W] -> [C, M] float64.

    pu, cu: [M, Ku]; pv, cv: [M, Kv] float64 (positions in texel units, in
    [0, W] and [0, H], and coefficients). S~ is read with grid_sample on the
    float64 table. Only the texture and these [M, K] tensors are kept for
    the backward, which rebuilds the table, takes grid_sample's backward
    (the table's gradient: the weights scattered; the positions') and gives
    the texture the adjoint of the prefix sums, a suffix sum along both axes.
    """

    @staticmethod
    def forward(ctx, texture: Tensor, pu: Tensor, cu: Tensor, pv: Tensor, cv: Tensor) -> Tensor:
        ctx.save_for_backward(texture, pu, cu, pv, cv)
        H, W = texture.shape[-2:]
        table = summed_area_table(texture)
        out = pu.new_empty((table.shape[1], pu.shape[0]))
        for sl in _chunks(pu.shape[0], pu.shape[1] * pv.shape[1], table.shape[1]):
            out[:, sl] = (_read(table, _grid(pu[sl], pv[sl], H, W)) * _coefs(cu[sl], cv[sl])).sum(-1)
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
        M, Ku, Kv = pu.shape[0], pu.shape[1], pv.shape[1]
        if any(need[1:]) or texture.device.type != "cpu":
            table = summed_area_table(texture.detach())
        else:
            # The texture's gradient alone (fitting a texture): the CPU grid_sample backward scatters the weights
            # without reading the table (tested), so it gets a stand-in of its shape instead of a rebuilt one.
            table = texture.new_zeros((), dtype=torch.float64).expand(1, C, H + 1, W + 1)
        g_table = None
        parts: dict[int, list[Tensor]] = {k: [] for k in range(1, 5) if need[k]}
        for sl in _chunks(M, Ku * Kv, C):
            grid = _grid(pu[sl], pv[sl], H, W)
            coef = _coefs(cu[sl], cv[sl])
            g = grad[:, sl].unsqueeze(-1)  # [C, m, 1]
            if need[0] or need[1] or need[3]:
                gt, gg = torch.ops.aten.grid_sampler_2d_backward(
                    (g * coef).unsqueeze(0), table, grid, 0, 1, True, [need[0], need[1] or need[3]])
                if need[0]:
                    g_table = gt if g_table is None else g_table.add_(gt)
                if need[1]:
                    parts[1].append(gg[0, ..., 0].view(-1, Kv, Ku).sum(1) * (2.0 / W))
                if need[3]:
                    parts[3].append(gg[0, ..., 1].view(-1, Kv, Ku).sum(2) * (2.0 / H))
            if need[2] or need[4]:
                g_coef = (_read(table, grid) * g).sum(0).view(-1, Kv, Ku)  # d out / d (cv_l cu_k)
                if need[2]:
                    parts[2].append((g_coef * cv[sl].unsqueeze(2)).sum(1))
                if need[4]:
                    parts[4].append((g_coef * cu[sl].unsqueeze(1)).sum(2))
        grad_tex = None
        if g_table is not None:
            # Adjoint of S[b, a] = sum_{r < b, c < a} f[r, c]: grad f[r, c] = sum_{b > r, a > c} grad S[b, a].
            grad_tex = _suffix_sums(g_table).to(texture.dtype)
        return (grad_tex, *(torch.cat(parts[k]) if need[k] else None for k in range(1, 5)))


class _NativeBoxSums(torch.autograd.Function):
    """``_BoxSums`` on the native CPU kernel (``native/csrc/sat.cpp``): the same inputs and output.

    The forward builds the float64 table, reads it and, where a position or
    coefficient needs a gradient, returns the per-point Jacobians ([C, M, K]
    each): the backward then needs no table, only the texture's adjoint (a
    scatter and a suffix sum in the kernel) and four small contractions.
    What is saved: the texture (by reference), the [M, K] inputs and the
    Jacobians, never a texture-sized buffer.
    """

    @staticmethod
    def forward(ctx, texture: Tensor, pu: Tensor, cu: Tensor, pv: Tensor, cv: Tensor) -> Tensor:
        need = ctx.needs_input_grad
        # The coefficients need a gradient only under clamp (the overshoot terms); without it the kernel skips
        # terms with a zero coefficient (a repeat / mirror box that does not wrap reads 4 corners, not 9).
        res = native.load().sat_forward(texture[0].contiguous(), pu.contiguous(), cu.contiguous(), pv.contiguous(),
                                        cv.contiguous(), jacobians=any(need[1:]), coef_grads=need[2] or need[4])
        ctx.save_for_backward(texture, pu, cu, pv, cv, *res[1:])
        return res[0]

    @staticmethod
    def backward(ctx, grad: Tensor):
        texture, pu, cu, pv, cv, *jac = ctx.saved_tensors
        need = ctx.needs_input_grad
        if torch.is_grad_enabled():
            # Double backward (create_graph=True): the differentiable torch reference.
            return native.double_backward(lambda: box_sums_reference(texture, pu, cu, pv, cv),
                                          (texture, pu, cu, pv, cv), need, grad)
        grad_tex = None
        if need[0]:
            grad_tex = native.load().sat_backward(texture[0].contiguous(), pu.contiguous(), cu.contiguous(),
                                                  pv.contiguous(), cv.contiguous(), grad).unsqueeze(0)
        g = grad.unsqueeze(-1)
        rest = [(g * j).sum(0) if n else None for j, n in zip(jac, need[1:])] if jac else [None] * 4
        return (grad_tex, *rest)


def _axis_terms(x0: Tensor, x1: Tensor, n: int, mode: str) -> tuple[Tensor, Tensor]:
    """Positions (in [0, n]) and coefficients [M, K] of ``G_ext(x1) - G_ext(x0)`` along one axis (module docstring)."""
    if mode == "border":
        one = torch.ones_like(x0)
        return torch.stack((x1.clamp(0, n), x0.clamp(0, n)), -1), torch.stack((one, -one), -1)
    if mode == "clamp":
        # G(c) plus the overshoot times the end cell's slope G(e) - G(e - 1). A box is at most n wide, so only
        # one end can overshoot: one slope term, at e = n (past the far end) or e = 1 (before 0).
        c0, c1 = x0.clamp(0, n), x1.clamp(0, n)
        over = (x1 - c1) - (x0 - c0)
        e = torch.where(x1.detach() > n, float(n), 1.0).to(x0.dtype)
        one = torch.ones_like(x0)
        return torch.stack((c1, c0, e, e - 1), -1), torch.stack((one, -one, over, -over), -1)
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
    box = _NativeBoxSums if native.kernel(texture) is not None else _BoxSums
    sums = box.apply(texture, pu, cu, pv, cv)
    area = (x1 - x0) * (y1 - y0)
    if "border" in (wrap_u, wrap_v):
        inner = ((x1.clamp(0, W) - x0.clamp(0, W)) if wrap_u == "border" else x1 - x0) * \
                ((y1.clamp(0, H) - y0.clamp(0, H)) if wrap_v == "border" else y1 - y0)
        sums = sums + border * (area - inner)
    return torch.where(ok, (sums / area).to(texture.dtype), float("nan"))

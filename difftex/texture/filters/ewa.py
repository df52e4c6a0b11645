"""EWA: Heckbert's elliptical weighted average with a Gaussian, as pbrt-v4 does it.

Per point, the footprint ellipse (``difftex.lod.ellipse``: axes the singular
values of the texel Jacobian) has its minor axis grown to at least
``major / max_aniso``; the level comes from that minor axis,
``D = log2(minor) + lod_bias``, and the results at ``floor(D)`` and
``floor(D) + 1`` are blended (the same level grouping as trilinear). On
level k the ellipse, in level-k texels, gets pbrt's unit-texel padding,
``Sigma = J J^T + I``, and every texel centre x inside ``r^2 = x^T Sigma^-1
x < 1`` (relative to the sample point) is read with weight
``exp(-2 r^2) - exp(-2)``; the sum is divided by the sum of the weights.

Vectorised, no loop over pixels: per point the ellipse is cut into texel
rows, each row into the run of texels inside it, and the (point, texel)
pairs are flattened with ``repeat_interleave`` — work is proportional to
the texels inside the ellipses, at most about ``pi (2 max_aniso + 1) 3``
per point and level. Pairs are processed in chunks of bounded size; with
gradients and more than one chunk, each chunk is checkpointed (recomputed in
the backward pass) so memory stays bounded too. Texels are read through ``difftex.wrap.wrap_index``.
On the CPU the same computation runs in the native kernel
(``difftex._native``: point by point, forward and first-order backward);
these torch ops are its reference and serve CUDA and double backward.

Where the level is clamped at the coarsest level and the ellipse is still
larger than a couple of texels there, it is shrunk (shape kept) to a minor
axis of 2 texels: the texture is already averaged to a few texels, and this
bounds the work. A negative ``lod_bias`` enlarges the ellipse in texels of
the chosen level, and the work with it, by ``4^-lod_bias``; on every other
level the minor axis is capped at the level's larger side (an ellipse wider
than the whole level already averages all of it), so a huge footprint read
at a low level (bias -inf or NaN, which reads level 0) costs bounded work
instead of overflowing.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from ... import _native as native
from ..lod import Ellipse, Footprint, level
from ..wrap import WRAP_CODES, drop_periods, wrap_index
from .trilinear import mip_blend, per_level

ALPHA = 2.0                       # pbrt-v4's Gaussian falloff
_CHUNK = 1 << 20                  # (point, texel) pairs per chunk
MAX_MINOR = 2.0                   # level-k texels, see the module docstring
FAR_UV = 2.0 ** 60                # clamp / border: uv capped here (_far_clamped)


def covariance(fp: Footprint, ell: Ellipse, max_aniso: float) -> tuple[Tensor, Tensor, Tensor]:
    """Scaled ellipse ``J J^T`` with the minor axis grown to ``major / max_aniso``, and its log2 minor axis.

    Returns ``(sigma [M, 3] as (xx, xy, yy) divided by scale^2, minor [M] scaled, log2_minor [M])``.
    """
    minor = torch.maximum(ell.minor, ell.major / max_aniso)
    log2_minor = torch.maximum(ell.log2_minor, ell.log2_major - math.log2(max_aniso))
    grow = (minor * minor - ell.minor * ell.minor).clamp(min=0)
    ex, ey = ell.direction[..., 0], ell.direction[..., 1]
    # Growing the minor axis adds grow * e_perp e_perp^T, e_perp = (-ey, ex).
    a, b, c = ell.jjt.unbind(-1)
    sigma = torch.stack((a + grow * ey * ey, b - grow * ex * ey, c + grow * ex * ex), -1)
    return sigma, minor, log2_minor


def _pairs(sx: Tensor, sy: Tensor, sxx: Tensor, sxy: Tensor, syy: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Texels inside each ellipse: (point index, local column, local row), all int64 / float.

    sx, sy: fractional sample position in [0, 1) relative to an integer texel
    origin; s**: the padded covariance. Detached inputs; pure integer logic.
    """
    hy = torch.sqrt(syy)
    r0 = torch.ceil(sy - hy)
    rows = (torch.floor(sy + hy) - r0 + 1).clamp_(min=0).long()
    point = torch.repeat_interleave(torch.arange(sx.shape[0], device=sx.device), rows)
    start = torch.cumsum(rows, 0) - rows
    ry = (torch.arange(point.numel(), device=sx.device) - start[point]).to(sx.dtype) + r0[point]
    # Row chord of x^T Sigma^-1 x < 1: centre sxy / syy * dy, half-width
    # sqrt(det / syy * (1 - dy^2 / syy)).
    dy = ry - sy[point]
    s_yy = syy[point]
    det = sxx[point] * s_yy - sxy[point] ** 2
    centre = sx[point] + sxy[point] / s_yy * dy
    half = torch.sqrt((det / s_yy * (1 - dy * dy / s_yy)).clamp(min=0))
    c0 = torch.ceil(centre - half)
    cols = (torch.floor(centre + half) - c0 + 1).clamp_(min=0).long()
    row = torch.repeat_interleave(torch.arange(point.numel(), device=sx.device), cols)
    start = torch.cumsum(cols, 0) - cols
    rx = (torch.arange(row.numel(), device=sx.device) - start[row]).to(sx.dtype) + c0[row]
    return point[row], rx, ry[row]


def gaussian(ss: Tensor, tt: Tensor, sxx: Tensor, sxy: Tensor, syy: Tensor, det: Tensor) -> Tensor:
    """EWA weight ``exp(-ALPHA r^2) - exp(-ALPHA)`` (0 outside) of texel offsets (ss, tt) from the sample point.

    All per (point, texel) pair: ``r^2 = (syy ss^2 - 2 sxy ss tt + sxx tt^2) / det``, the padded covariance
    ``Sigma = (sxx, sxy, syy)`` with ``det = |Sigma|``. The stochastic filter draws texels by these weights.
    """
    r2 = (syy * ss * ss - 2 * sxy * ss * tt + sxx * tt * tt) / det
    return (torch.exp(-ALPHA * r2) - math.exp(-ALPHA)).clamp(min=0)


def texels(flat: Tensor, H: int, W: int, col: Tensor, row: Tensor, wrap_u: str, wrap_v: str,
           border: float) -> Tensor:
    """Texels of one level ``flat`` [C, H * W] at integer-valued float columns / rows [n], wrapped: [C, n]."""
    ix, vx = wrap_index(col, W, wrap_u)
    iy, vy = wrap_index(row, H, wrap_v)
    vals = flat.index_select(1, iy * W + ix)
    valid = vx if vy is None else (vy if vx is None else vx & vy)
    if valid is not None:
        vals = torch.where(valid, vals, vals.new_tensor(border))
    return vals


def _ewa_chunk(flat: Tensor, H: int, W: int, ox: Tensor, oy: Tensor, sx: Tensor, sy: Tensor,
               sxx: Tensor, sxy: Tensor, syy: Tensor, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """EWA of one level at a chunk of points: [C + 1, m] (weighted sums, then the weight sum)."""
    with torch.no_grad():
        point, rx, ry = _pairs(sx.detach(), sy.detach(), sxx.detach(), sxy.detach(), syy.detach())
    # index_select, not advanced indexing (sx[point]): a point owns many pairs, so the backward sums many
    # terms into each point's entry, and the CPU backward of advanced indexing (index_put with accumulate)
    # adds them with atomics from several threads, in an order that changes from run to run; index_select's
    # backward (index_add along dim 0 of a 1-D tensor) adds them one by one in pair order (DESIGN.md,
    # "determinism").
    per_pair = lambda x: x.index_select(0, point)  # noqa: E731
    det = sxx * syy - sxy * sxy
    w = gaussian(rx - per_pair(sx), ry - per_pair(sy), per_pair(sxx), per_pair(sxy), per_pair(syy), per_pair(det))
    vals = texels(flat, H, W, per_pair(ox) + rx, per_pair(oy) + ry, wrap_u, wrap_v, border)
    m = sx.shape[0]
    num = flat.new_zeros((flat.shape[0], m)).index_add(1, point, vals * w)
    den = flat.new_zeros((m,)).index_add(0, point, w)
    return torch.cat((num, den.unsqueeze(0)), 0)


def level_ellipse(H: int, W: int, uv: Tensor, sigma: Tensor, minor: Tensor, scale: Tensor, full_h: int,
                  full_w: int, coarsest: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The padded ellipse of points uv [m, 2] on an H x W level, in its texels: (sxx, sxy, syy, origin, frac).

    ``sigma``, ``minor``, ``scale`` as from ``covariance`` (level-0, scaled); ``origin`` [m, 2] is the
    integer part of the texel position ``uv * (W, H) - 1/2`` (detached), ``frac`` the rest (differentiable).
    """
    kx, ky = W / full_w, H / full_h
    # Beyond the coarsest level the ellipse is shrunk to a minor axis of
    # MAX_MINOR texels; on other levels to the level's larger side (module
    # docstring), which only a bias far below the footprint's level reaches.
    cap = MAX_MINOR if coarsest else max(MAX_MINOR, float(max(H, W)))
    minor_k = minor * max(kx, ky)
    pos = minor_k > 0
    shrunk = cap / torch.where(pos, minor_k, torch.ones_like(minor_k))
    # Strictly below scale, as in the kernel: at a tie the footprint's own size holds, whose derivative is the
    # one from below (torch.minimum would split the gradient between the two).
    s = torch.where(pos & (shrunk < scale), shrunk, scale)
    # Ellipse in level-k texels (the footprint was divided by its scale).
    s2 = s * s
    sxx = sigma[:, 0] * (s2 * kx * kx) + 1
    sxy = sigma[:, 1] * (s2 * kx * ky)
    syy = sigma[:, 2] * (s2 * ky * ky) + 1
    pos = uv * uv.new_tensor([float(W), float(H)]) - 0.5
    # Integer origin + fraction keeps r^2 accurate at large uv (repeat).
    origin = torch.floor(pos.detach())
    frac = pos - origin
    return sxx, sxy, syy, origin, frac


def _ewa_level(lev: Tensor, uv: Tensor, sigma: Tensor, minor: Tensor, scale: Tensor, full_h: int, full_w: int,
               coarsest: bool, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """EWA on one level [1, C, Hk, Wk] at points uv [m, 2] with level-0 ellipses; [C, m]."""
    _, C, H, W = lev.shape
    sxx, sxy, syy, origin, frac = level_ellipse(H, W, uv, sigma, minor, scale, full_h, full_w, coarsest)
    flat = lev[0].reshape(C, H * W)
    M = uv.shape[0]
    with torch.no_grad():
        # Bounding-box size per point bounds its pairs; it sizes the chunks.
        cost = (2 * torch.sqrt(syy) + 1) * (2 * torch.sqrt(sxx) + 1)
        ends = torch.cumsum(cost, 0)
        n_chunks = int(math.ceil(float(ends[-1]) / _CHUNK)) if M else 0
        cuts = torch.searchsorted(ends, torch.arange(1, max(n_chunks, 1), device=ends.device,
                                                     dtype=ends.dtype) * _CHUNK).tolist()
    # Checkpointing trades a second forward pass for memory: only worth it
    # when the pairs do not fit in one chunk.
    grad = (n_chunks > 1 and torch.is_grad_enabled()
            and (flat.requires_grad or frac.requires_grad or sxx.requires_grad))
    outs = []
    lo = 0
    for hi in cuts + [M]:
        if hi <= lo:
            continue
        args = (flat, H, W, origin[lo:hi, 0], origin[lo:hi, 1], frac[lo:hi, 0], frac[lo:hi, 1],
                sxx[lo:hi], sxy[lo:hi], syy[lo:hi], wrap_u, wrap_v, border)
        outs.append(checkpoint(_ewa_chunk, *args, use_reentrant=False) if grad else _ewa_chunk(*args))
        lo = hi
    acc = torch.cat(outs, 1) if len(outs) > 1 else outs[0]
    return acc[:C] / acc[C]


def ewa_points(levels: Sequence[Tensor], uv: Tensor, fp: Footprint, ell: Ellipse, lod_bias: Tensor | float,
               max_aniso: float, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """EWA filtering of one texture.

    Args:
        levels: the pyramid of one texture, ``[1, C, H_k, W_k]`` each.
        uv: [M, 2] sample points.
        fp, ell: footprint and its ellipse per point (``difftex.lod``).
        lod_bias: scalar or [M].
        max_aniso: largest major / minor ratio kept (>= 1).
        wrap_u, wrap_v, border: as in ``separable_sample``.

    Returns:
        [C, M]; NaN where uv is not finite. Differentiable in the levels, uv,
        the footprint (ellipse shape, level) and lod_bias.
    """
    H, W = levels[0].shape[-2:]
    ok = torch.isfinite(uv).all(-1)
    uv_safe = torch.where(ok.unsqueeze(-1), uv, torch.zeros_like(uv))
    # Take whole periods out before the texel position uv * W is formed: at
    # |uv| ~ 1e6 that product rounds to 4 texels in float32 (64-texel
    # texture), which the integer origin in _ewa_level cannot undo; the
    # difference of uv and its floor is exact. (repeat: period 1, mirror: 2.)
    uv_safe = torch.stack([_far_clamped(drop_periods(uv_safe[:, 0], wrap_u), wrap_u),
                           _far_clamped(drop_periods(uv_safe[:, 1], wrap_v), wrap_v)], -1)
    sigma, minor, log2_minor = covariance(fp, ell, max_aniso)
    D = level(log2_minor, lod_bias, len(levels))
    scale = torch.exp2(fp.log2_scale)
    if native.kernel(uv) is not None:
        out = _NativeEWA.apply(uv_safe, sigma, minor, scale, D, (H, W, wrap_u, wrap_v, float(border)), *levels)
    else:
        out = _ewa_torch(levels, uv_safe, sigma, minor, scale, D, H, W, wrap_u, wrap_v, border)
    return torch.where(ok, out, torch.full_like(out, float("nan")))


def _far_clamped(u: Tensor, mode: str) -> Tensor:
    """clamp / border: u capped at +-``FAR_UV`` (the same read), gradient 1; other modes (periods dropped) as is.

    Past ``FAR_UV`` = 2^60 the texel position ``u * W`` would overflow float32 (3e38 * 8 = inf, whose
    fraction ``inf - floor(inf)`` is NaN: the torch path then failed on a negative row count), yet
    nothing changes there: every texel of any ellipse (at most ``MAX_ANISO`` times a level's side)
    is past the edge, so it reads the edge texel (the border constant), and ``u * W - 0.5`` has no
    fraction left at 2^60 as at any larger u, so the Gaussian weights, which depend on that
    fraction, are the same too. The gradient passes straight through, as it does unclamped.
    """
    if mode not in ("clamp", "border") or torch.finfo(u.dtype).max <= FAR_UV:  # float16's floats are all below
        return u
    return u.detach().clamp(-FAR_UV, FAR_UV) + (u - u.detach())  # u - u.detach(): an exact 0, gradient 1


def _ewa_torch(levels: Sequence[Tensor], uv: Tensor, sigma: Tensor, minor: Tensor, scale: Tensor, D: Tensor,
               H: int, W: int, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """EWA in torch ops (the reference, and the path on CUDA and for double backward): [C, M]."""
    n = len(levels)

    def read(k: int, xs: list[Tensor]) -> Tensor:
        return _ewa_level(levels[k], *xs, H, W, k == n - 1, wrap_u, wrap_v, border)

    return mip_blend(D, n, [uv, sigma, minor, scale], per_level(read))


class _NativeEWA(torch.autograd.Function):
    """EWA on the native CPU kernel (``difftex._native``), forward and first-order backward.

    uv [M, 2] (periods dropped, finite), sigma [M, 3], minor [M], scale [M],
    D [M], levels ``[1, C, H_k, W_k]`` -> [C, M]; the same values and
    gradients as ``_ewa_torch`` (its reference).
    """

    @staticmethod
    def forward(ctx, uv: Tensor, sigma: Tensor, minor: Tensor, scale: Tensor, D: Tensor, opts: tuple,
                *levels: Tensor) -> Tensor:
        H, W, wrap_u, wrap_v, border = opts
        ctx.opts = opts
        ctx.d_grad = ctx.needs_input_grad[4]  # an integer D = k > 0 then reads level k - 1 too, as mip_blend
        ctx.save_for_backward(uv, sigma, minor, scale, D, *levels)
        kernel = native.load()
        ctx.read = kernel.ReadOptions(wrap_u=WRAP_CODES[wrap_u], wrap_v=WRAP_CODES[wrap_v], border=border,
                                      d_grad=ctx.d_grad)
        return kernel.ewa(*_ewa_args(levels, uv, sigma, minor, scale, D), H, W, ctx.read)

    @staticmethod
    def backward(ctx, grad: Tensor):
        uv, sigma, minor, scale, D, *levels = ctx.saved_tensors
        H, W, wrap_u, wrap_v, border = ctx.opts
        need = ctx.needs_input_grad
        if torch.is_grad_enabled():
            # Double backward (create_graph=True): the differentiable torch path.
            return native.double_backward(
                lambda: _ewa_torch(levels, uv, sigma, minor, scale, D, H, W, wrap_u, wrap_v, border),
                (uv, sigma, minor, scale, D, None, *levels), need, grad)
        need_levels = need[6:]
        kernel = native.load()
        gl, guv, gsig, gmin, gsc, gD = kernel.ewa_backward(
            *_ewa_args(levels, uv, sigma, minor, scale, D), grad, H, W, ctx.read,
            kernel.EwaNeeds(levels=any(need_levels), uv=need[0], ellipse=any(need[1:4]), D=need[4]))
        return (guv if need[0] else None, gsig if need[1] else None, gmin if need[2] else None,
                gsc if need[3] else None, gD if need[4] else None, None,
                *native.level_grads(gl, need_levels, levels))


def _ewa_args(levels, uv: Tensor, sigma: Tensor, minor: Tensor, scale: Tensor, D: Tensor) -> tuple:
    return ([lv[0].contiguous() for lv in levels], uv.contiguous(), sigma.contiguous(), minor.contiguous(),
            scale.contiguous(), D.contiguous())

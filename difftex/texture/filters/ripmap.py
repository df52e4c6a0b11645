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

On the CPU one node (``_NativeRipmap``, ``native/csrc/ripmap.cpp``) builds
only the levels the points read (and those on their way), reads the four
levels per point and, backward, scatters the level gradients and folds them
into the texture by the build's adjoint; a prebuilt ``Ripmap``'s levels get
their gradients directly. The torch path (``_torch_read``: ``mip_blend``
nested over ``separable_sample``, on levels built by autograd-tracked ops)
is its tested reference and serves CUDA, ``difftex.backend("reference")``
and double backward.
"""
from __future__ import annotations

from typing import Optional, Union

import torch
from torch import Tensor

from ... import _native as native
from ..lod import footprint, level, log2_extents
from ..pyramid.ripmap import Ripmap, build_ripmap, ripmap_counts
from ..taps import levels_read
from ..wrap import WRAP_CODES
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
    if native.kernel(uv) is not None:
        texture, levels = (None, [lv for row in source.grid for lv in row]) if isinstance(source, Ripmap) \
            else (base, [])
        return _NativeRipmap.apply(uv, D_u, D_v, (wrap_u, wrap_v, float(border), *counts), texture, *levels)
    if isinstance(source, Ripmap):
        rip = source
    else:
        counts = (levels_read(D_u, counts[0], False), levels_read(D_v, counts[1], False))
        rip = Ripmap(build_ripmap(base, *counts))
    return _torch_read(rip, counts, uv, D_u, D_v, wrap_u, wrap_v, border)


def _torch_read(rip: Ripmap, counts: tuple[int, int], uv: Tensor, D_u: Tensor, D_v: Tensor, wrap_u: str,
                wrap_v: str, border: float) -> Tensor:
    """The ripmap read in torch ops (the reference of the native kernel): [C, M]."""
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


def _wanted(D_u: Tensor, D_v: Tensor, n_u: int, n_v: int, d_grad: bool) -> list[bool]:
    """Which ripmap levels (flat, ``j * n_u + i``) the points read: per axis floor(D), and floor(D) + 1 where D is
    not an integer (or floor(D) - 1 at an integer D > 0 that needs a gradient), as ``mip_blend`` reads them."""
    def axis(D: Tensor, n: int) -> tuple[Tensor, Tensor]:
        Dd = D.detach()
        k0 = torch.floor(Dd).clamp_(0, n - 1)
        other = torch.where(Dd > k0, k0 + 1, k0 - 1 if d_grad else k0).clamp_(0, n - 1)
        return k0.long(), other.long()

    (a0, a1), (b0, b1) = axis(D_u, n_u), axis(D_v, n_v)
    flat = torch.cat([b * n_u + a for a in (a0, a1) for b in (b0, b1)])
    return (torch.bincount(flat, minlength=n_u * n_v) > 0).tolist()


class _NativeRipmap(torch.autograd.Function):
    """``ripmap_points`` on the native CPU kernel (``native/csrc/ripmap.cpp``).

    uv [M, 2], D_u, D_v [M]; opts (wrap_u, wrap_v, border, n_u, n_v); then
    either the base texture [1, C, H, W] (its levels are built in the
    kernel, only those read, and its gradient is the kernel's adjoint of the
    build) and no levels, or None and a Ripmap's n_u * n_v levels (flat,
    ``j * n_u + i``; each gets its own gradient) -> [C, M].
    """

    @staticmethod
    def forward(ctx, uv: Tensor, D_u: Tensor, D_v: Tensor, opts: tuple, texture: Optional[Tensor],
                *levels: Tensor) -> Tensor:
        wrap_u, wrap_v, border, n_u, n_v = opts
        kernel = native.load()
        ctx.opts = opts
        # Where a level needs a gradient, an integer D = k > 0 reads level k - 1 too (mip_blend does the same).
        d_grad = ctx.needs_input_grad[1] or ctx.needs_input_grad[2]
        ctx.read = kernel.ReadOptions(wrap_u=WRAP_CODES[wrap_u], wrap_v=WRAP_CODES[wrap_v], border=border,
                                      d_grad=d_grad)
        none = uv.new_empty(0)
        if texture is not None:
            built = kernel.ripmap_build(texture[0], n_u, n_v, _wanted(D_u, D_v, n_u, n_v, d_grad))
            lv = [none if b is None else b for b in built]
        else:
            lv = [x[0].contiguous() for x in levels]
        # The built levels are the values the backward reads: kept on ctx (they are no input).
        ctx.levels = lv
        ctx.save_for_backward(uv, D_u, D_v, texture, *levels)
        return kernel.ripmap_read(lv, n_u, uv.contiguous(), D_u.contiguous(), D_v.contiguous(), ctx.read)

    @staticmethod
    def backward(ctx, grad: Tensor):
        uv, D_u, D_v, texture, *levels = ctx.saved_tensors
        wrap_u, wrap_v, border, n_u, n_v = ctx.opts
        need = ctx.needs_input_grad
        if torch.is_grad_enabled():
            # Double backward (create_graph=True): the differentiable torch path.
            def recompute() -> Tensor:
                rip = Ripmap(build_ripmap(texture, n_u, n_v) if texture is not None
                             else [levels[j * n_u:(j + 1) * n_u] for j in range(n_v)])
                return _torch_read(rip, (n_u, n_v), uv, D_u, D_v, wrap_u, wrap_v, border)
            return native.double_backward(recompute, (uv, D_u, D_v, None, texture, *levels), need, grad)
        kernel = native.load()
        need_levels = need[4] or any(need[5:])
        gl, guv, gu, gv = kernel.ripmap_read_backward(
            ctx.levels, n_u, uv.contiguous(), D_u.contiguous(), D_v.contiguous(), grad, ctx.read,
            need_levels=need_levels, need_uv=need[0], need_D=need[1] or need[2])
        grad_tex = None
        if need[4]:
            if all(g is None for g in gl):
                grad_tex = torch.zeros_like(texture)
            else:
                none = uv.new_empty(0)
                H, W = texture.shape[-2:]
                grad_tex = kernel.ripmap_adjoint([none if g is None else g for g in gl], n_u, n_v, H, W).unsqueeze(0)
        level_grads = native.level_grads(gl, need[5:], levels) if levels else ()
        return (guv, gu if need[1] else None, gv if need[2] else None, None, grad_tex, *level_grads)

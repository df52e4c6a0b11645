"""Trilinear (and nearest-mip) filtering: the bilinear tap of two adjacent mip levels, blended.

This is the *trilinear tap* that the anisotropic filter calls (N taps along
the major axis per point), and ``mip_blend``, its level grouping and blend,
is shared with the EWA filter. On the CPU ``trilinear_points`` runs the
native kernel (``difftex._native``: one pass over the points, taps and
levels included). The torch path below serves CUDA, float16, double
backward and machines without the kernel, and is the reference the tests
compare the kernel with. Work is proportional to the points a level serves: points are
sorted by level once, each level is read (with ``separable_sample``, the one
bilinear of the package) only at the points that use it, and the results
are put back in order with one ``index_add``. A point whose level is an
exact integer, or clamped to the ends of the pyramid, costs one bilinear
tap, not two.

Given a plain texture (``TexturePyramid``) rather than a ``Mipmap``, the
pyramid is built and every level read inside one autograd node
(``_PyramidRead``), whose backward folds the levels' texture gradients into
one another in place: one gradient buffer per level read, where separate
nodes would allocate (and on CPU page-fault) a second, summed, copy of each.

Flat layout: one texture's levels ``[1, C, H_k, W_k]``, points ``[M, ...]``,
result ``[C, M]``; ``difftex.sample`` does batching and checks.
"""
from __future__ import annotations

from typing import Callable, Sequence, Union

import torch
from torch import Tensor

from ...backend import single_level
from ... import _native as native
from ..pyramid.mipmap import build_levels, level_size, mipmap, pyramid_adjoint, step_adjoint
from ..wrap import WRAP_CODES
from .gather import separable_backward
from .grid import FastSample
from .separable import separable_sample

# read(used levels, entries per level, entry tensors sorted by level) -> [C, E]
Reader = Callable[[list[int], list[int], list[Tensor]], Tensor]


def per_level(read_one: Callable[[int, list[Tensor]], Tensor]) -> Reader:
    """A ``mip_blend`` reader from a function that reads one level at its entries."""
    def read(used: list[int], sizes: list[int], xs: list[Tensor]) -> Tensor:
        chunks = zip(*(x.split(sizes) for x in xs))
        parts = [read_one(k, list(chunk)) for k, chunk in zip(used, chunks)]
        return parts[0] if len(parts) == 1 else torch.cat(parts, 1)
    return read


class TexturePyramid:
    """The pyramid of ``texture`` [1, C, H, W] down to ``count`` levels, built where it is read."""

    def __init__(self, texture: Tensor, count: int):
        self.texture, self.count = texture, count

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, k: int) -> Tensor:
        if k != 0:
            raise IndexError("TexturePyramid: only level 0 exists before the pyramid is built")
        return self.texture


Levels = Union[Sequence[Tensor], TexturePyramid]

# A level read at fewer than 1/_SPARSE points per texel gets its texture
# gradient by the gather scatter into the spread of the coarser levels'
# total, not by grid_sample's zero-filled buffer (measured on CPU: the fill of
# a 1024^2 level costs more than scattering 15k points).
_SPARSE = 8


class _PyramidRead(torch.autograd.Function):
    """Bilinear reads of several levels of the pyramid of one texture, in one node.

    texture [1, C, H, W], uv [E, 2] entries sorted by level (``sizes[i]`` of
    them read level ``used[i]``) -> [C, E].
    """

    @staticmethod
    def forward(ctx, texture: Tensor, uv: Tensor, used: list[int], sizes: list[int], wrap_u: str, wrap_v: str,
                border: float) -> Tensor:
        ctx.save_for_backward(texture, uv)
        ctx.args = (used, sizes, wrap_u, wrap_v, border)
        levels = build_levels(texture, used[-1] + 1)
        ctx.reads = [FastSample(levels[k], chunk.unsqueeze(0), "linear", wrap_u, wrap_v, border,
                                tex_grad=ctx.needs_input_grad[0]) for k, chunk in zip(used, uv.split(sizes))]
        parts = [r.out[0] for r in ctx.reads]
        return parts[0] if len(parts) == 1 else torch.cat(parts, 1)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        texture, uv = ctx.saved_tensors
        used, sizes, wrap_u, wrap_v, border = ctx.args
        need_tex, need_uv = ctx.needs_input_grad[:2]
        g_parts = grad_out.split(sizes, 1)
        if torch.is_grad_enabled():
            # Double backward (create_graph=True): the differentiable reference.
            levels = mipmap(texture, max_levels=used[-1] + 1).levels
            grads: list[Tensor | None] = [None] * (used[-1] + 1)
            guv = []
            for k, u, g in zip(used, uv.split(sizes), g_parts):
                grads[k], gu = separable_backward(levels[k], u.unsqueeze(0), g.unsqueeze(0), "linear",
                                                  wrap_u, wrap_v, border, need_tex, need_uv)
                guv.append(gu)
            grad_tex = pyramid_adjoint(grads, tuple(texture.shape[-2:]), inplace=False) if need_tex else None
        else:
            # Coarse to fine, each level's total gradient in one buffer: a
            # level read at few points (next to its texels) gets the spread
            # of the coarser total first and its own gradient scattered into
            # it, instead of a zero-filled texture-sized buffer plus an add.
            guv = [None] * len(used)
            acc = None
            H, W = texture.shape[-2:]
            for k in range(used[-1], -1, -1):
                hw = level_size(H, W, k)
                if k not in used:
                    acc = None if acc is None else step_adjoint(None, acc, hw, True)
                    continue
                i = used.index(k)
                sparse = need_tex and acc is not None and sizes[i] * _SPARSE < hw[0] * hw[1]
                gt, guv[i] = ctx.reads[i].backward(g_parts[i].unsqueeze(0), need_tex, need_uv,
                                                   into=step_adjoint(None, acc, hw, True) if sparse else None)
                acc = gt if sparse or acc is None else step_adjoint(gt, acc, hw, True)
            grad_tex = acc if need_tex else None
        grad_uv = (guv[0] if len(guv) == 1 else torch.cat(guv, 1))[0] if need_uv else None
        return grad_tex, grad_uv, None, None, None, None, None


class _NativeTaps(torch.autograd.Function):
    """``trilinear_points`` on the native CPU kernel (``difftex._native``).

    uv [M, 2], D [M], axis [M, 2] and count [M] int64 (or both None: one tap
    a point), levels ``[1, C, H_k, W_k]`` -> [C, M].
    """

    @staticmethod
    def forward(ctx, uv: Tensor, D: Tensor, axis: Tensor | None, count: Tensor | None, opts: tuple,
                *levels: Tensor) -> Tensor:
        wrap_u, wrap_v, border, nearest = opts
        # Where D needs a gradient, an integer D = k > 0 reads level k - 1 too (mip_blend does the same).
        ctx.d_grad = ctx.needs_input_grad[1]
        ctx.opts = opts
        ctx.taps = axis is not None
        ctx.save_for_backward(uv, D, axis, count, *levels)
        kernel = native.load()
        ctx.read = kernel.ReadOptions(wrap_u=WRAP_CODES[wrap_u], wrap_v=WRAP_CODES[wrap_v], border=border,
                                      nearest=nearest, d_grad=ctx.d_grad)
        return kernel.forward(*_native_args(levels, uv, D, axis, count), ctx.read)

    @staticmethod
    def backward(ctx, grad: Tensor):
        uv, D, axis, count, *levels = ctx.saved_tensors
        wrap_u, wrap_v, border, nearest = ctx.opts
        need = ctx.needs_input_grad
        need_uv, need_D, need_axis, need_levels = need[0], need[1] and not nearest, need[2], need[5:]
        if torch.is_grad_enabled():
            # Double backward (create_graph=True): the differentiable torch path.
            return native.double_backward(
                lambda: _torch_taps(levels, uv, D, wrap_u, wrap_v, border, nearest, axis, count),
                (uv, D, axis, None, None, *levels), need, grad)
        kernel = native.load()
        gl, guv, gD, gax = kernel.backward(
            *_native_args(levels, uv, D, axis, count), grad, ctx.read,
            kernel.TapNeeds(levels=any(need_levels), uv=need_uv, D=need_D, axis=need_axis and ctx.taps))
        return (guv, gD if need_D else None, gax if need_axis and ctx.taps else None, None, None,
                *native.level_grads(gl, need_levels, levels))


def _native_args(levels, uv: Tensor, D: Tensor, axis: Tensor | None, count: Tensor | None) -> tuple:
    """The kernel's (levels [C, h, w], uv, D, axis, count) arguments: contiguous, empty for no taps."""
    none = uv.new_empty(0)
    return ([lv[0].contiguous() for lv in levels], uv.contiguous(), D.contiguous(),
            none if axis is None else axis.contiguous(), none.long() if count is None else count.contiguous())


def mip_blend(D: Tensor, levels: int, inputs: Sequence[Tensor], read: Reader, *, nearest: bool = False) -> Tensor:
    """Blend per-level results at ``floor(D)`` and ``floor(D) + 1``, each level read once for its points.

    Args:
        D: [M] level per point, already clamped to ``[0, levels - 1]``
            (``difftex.texture.lod.level``); may carry a gradient.
        levels: number of levels.
        inputs: per-point tensors ``[M, ...]`` that ``read`` needs (uv, ...).
        read: ``read(used, sizes, [x[entries] for x in inputs])`` -> [C, E]:
            the values at the entries, which come sorted by level, ``sizes[i]``
            of them reading level ``used[i]`` (``per_level`` makes one from a
            one-level reader).
        nearest: read only the nearest level ``round(D)``, weight 1.

    Returns:
        [C, M]: ``(1 - frac(D)) read(floor D) + frac(D) read(floor D + 1)``,
        differentiable in D through the weights. At an integer ``D = k`` the
        derivative is the one from below, ``read(k) - read(k - 1)``, and 0 at
        ``D = 0`` (DESIGN.md, "mip level"); the native kernel does the same.

    Every (point, level) pair to read is one *entry*: each point's level
    ``floor(D)``, plus ``floor(D) + 1`` where D is not an integer, or, where
    D is an integer k > 0 that needs a gradient, ``k - 1`` with weight 0 for
    the derivative. Entries are sorted by level once, so each level's
    entries are one contiguous block: one gather of the inputs, one split, a
    read per level, one concatenation and one ``index_add`` back to the
    points, whatever the number of levels (the backward is as short).
    """
    M = D.shape[0]
    Dd = D.detach()
    k0 = torch.floor(Dd + 0.5 if nearest else Dd).clamp_(0, levels - 1)
    lev = k0.to(torch.uint8) if levels <= 256 else k0.long()
    point = role = None
    if not nearest:
        # role per entry: -1 the lower level of a pair (weight 1 - (D - k)), +1 the upper (weight 1 + (D - k)),
        # 0 a level read alone (weight 1, no derivative).
        up = Dd > k0
        down = (Dd == k0) & (k0 > 0) if D.requires_grad else torch.zeros_like(up)
        up_i, down_i = up.nonzero().squeeze(1), down.nonzero().squeeze(1)
        if up_i.numel() or down_i.numel():
            one = Dd.new_ones(())
            role = torch.cat((down.to(Dd.dtype) - up.to(Dd.dtype), one.expand(up_i.numel()),
                              -one.expand(down_i.numel())))
            point = torch.cat((torch.arange(M, device=D.device), up_i, down_i))
            lev = torch.cat((lev, lev.index_select(0, up_i) + 1, lev.index_select(0, down_i) - 1))
        elif D.requires_grad:
            role = Dd.new_zeros(M)  # no pair: a zero derivative, but the result stays in D's graph
    counts = torch.bincount(lev, minlength=levels).tolist()
    used = [k for k, c in enumerate(counts) if c]
    if len(used) > 1:
        # Small keys sort several times faster as uint8 (measured on CPU).
        perm = torch.sort(lev, stable=True).indices
        point = perm if point is None else point.index_select(0, perm)
        lev = lev.index_select(0, perm)
        role = None if role is None else role.index_select(0, perm)
    if point is None:  # every point reads one level, in order
        xs, De = list(inputs), D
    else:
        xs = [x.index_select(0, point) for x in inputs]
        De = D.index_select(0, point)
    vals = read(used, [counts[k] for k in used], xs)
    if role is not None:
        vals = vals * (1 + role * (De - lev.to(D.dtype)))
    if point is None:
        return vals
    return vals.new_zeros((vals.shape[0], M)).index_add(1, point, vals)


def trilinear_points(levels: Levels, uv: Tensor, D: Tensor, wrap_u: str, wrap_v: str, border: float, *,
                     nearest_mip: bool = False, axis: Tensor | None = None, count: Tensor | None = None) -> Tensor:
    """Trilinear taps of one texture: one a point, or ``count`` spread along ``axis`` (the anisotropic filter).

    Args:
        levels: the pyramid of one texture, ``[1, C, H_k, W_k]`` each, or a
            ``TexturePyramid`` (built inside the read).
        uv: [M, 2] sample points (DESIGN.md convention).
        D: [M] clamped level per point.
        wrap_u, wrap_v, border: as in ``separable_sample``.
        nearest_mip: bilinear at the nearest level instead of blending two.
        axis, count: optional [M, 2] uv vector and [M] int64 (>= 1): point
            m averages ``count[m]`` taps at ``uv + ((i + 1/2) / count - 1/2)
            * axis``, i = 0 .. count - 1, all at level ``D[m]``.

    Returns:
        [C, M]. Differentiable in every level (or the texture), uv, D
        (trilinear only) and axis.

    On the CPU this runs the native kernel (``difftex._native``) where it is
    built, else (and on CUDA, and as the tests' reference) the torch path.
    """
    if native.kernel(uv) is not None:
        lv = build_levels(levels.texture, len(levels)) if isinstance(levels, TexturePyramid) else list(levels)
        return _NativeTaps.apply(uv, D, axis, count, (wrap_u, wrap_v, float(border), nearest_mip), *lv)
    # A non-finite uv reads a safe point and gets NaN put back, as the kernel
    # and ewa_points do: its NaN value would otherwise meet a zero upstream
    # gradient in mip_blend's d/dD (0 * NaN) and send NaN to uv_dx / uv_dy /
    # lod_bias even where the loss masks the pixel out.
    ok = torch.isfinite(uv).all(-1)
    out = _torch_taps(levels, torch.where(ok.unsqueeze(-1), uv, 0.0), D, wrap_u, wrap_v, border, nearest_mip,
                      axis, count)
    return torch.where(ok, out, float("nan"))


def spread_taps(uv: Tensor, axis: Tensor, count: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The anisotropic taps as one flat list: point m's ``count[m]`` taps at ``uv + ((i + 1/2) / count - 1/2) axis``.

    uv, axis: [M, 2]; count: [M] int64 >= 1. Returns (point [T] int64, the
    point of each tap; taps [T, 2]; count [T] of the tap's point, in uv's
    dtype), taps ordered by point; differentiable in uv and axis.
    """
    point = torch.repeat_interleave(torch.arange(uv.shape[0], device=uv.device), count)
    start = torch.cumsum(count, 0) - count
    # index_select: several times faster than advanced indexing on CPU.
    i = torch.arange(point.numel(), device=uv.device) - start.index_select(0, point)
    nt = count.to(uv.dtype).index_select(0, point)
    offset = ((i.to(uv.dtype) + 0.5) / nt - 0.5).unsqueeze(-1)
    return point, torch.addcmul(uv.index_select(0, point), axis.index_select(0, point), offset), nt


def _torch_taps(levels: Levels, uv: Tensor, D: Tensor, wrap_u: str, wrap_v: str, border: float, nearest_mip: bool,
                axis: Tensor | None, count: Tensor | None) -> Tensor:
    """``trilinear_points`` in torch ops: the taps flattened into one list (point, tap), one ``mip_blend``."""
    if count is not None:
        point, taps, nt = spread_taps(uv, axis, count)
        vals = _torch_taps(levels, taps, D.index_select(0, point), wrap_u, wrap_v, border, nearest_mip, None, None)
        return uv.new_zeros((vals.shape[0], uv.shape[0])).index_add(1, point, vals / nt)
    if isinstance(levels, TexturePyramid):
        tex = levels.texture
        if (single_level() == "grid_sample" and torch.is_grad_enabled()
                and (tex.requires_grad or uv.requires_grad)):
            def read(used: list[int], sizes: list[int], xs: list[Tensor]) -> Tensor:
                return _PyramidRead.apply(tex, xs[0], used, sizes, wrap_u, wrap_v, float(border))
            return mip_blend(D, len(levels), [uv], read, nearest=nearest_mip)
        # No gradient (or the reference path): the levels as plain tensors.
        levels = mipmap(tex, max_levels=len(levels)).levels

    def read_one(k: int, xs: list[Tensor]) -> Tensor:
        return separable_sample(levels[k], xs[0].unsqueeze(0), "linear", wrap_u, wrap_v, border)[0]

    return mip_blend(D, len(levels), [uv], per_level(read_one), nearest=nearest_mip)

"""Stochastic texture filtering: one read a draw, drawn from the filter's own weights.

Pharr, Wronski, Salvi, Fajardo, "Filtering After Shading With Stochastic
Texture Filtering" (2024): a filter ``f = sum_i w_i t_i`` is the expectation
of ``(w_i / p_i) t_i`` with tap ``i`` drawn with probability ``p_i``, for
any pmf p that is positive wherever ``w_i`` is not 0; it reads one tap and is
exact in expectation, negative weights (bicubic) included: the sign and the
normaliser ride in ``w / p``. The paper's choice, importance sampling the
filter, is ``p = |w| / sum |w|``; here each pmf is that one mixed with the
uniform pmf over the same taps (``DEFENSIVE`` = 1/4 of it, "defensive"
importance sampling), for the gradients (below).

Every estimator is written as ``(w(theta) / p) * t(theta)``: the draw (which
tap) and its probability ``p`` are fixed from detached inputs, and ``w``,
the tap's weight in the deterministic filter, is recomputed differentiably.
The derivative with the draw held fixed is ``dw / p * t + w / p * dt``,
whose expectation over the draw is ``sum_i dw_i t_i + w_i dt_i``: the
deterministic filter's gradient, for every input, wherever the filter's
weights are smooth. That includes what the weights depend on (the level
blend's D, hence uv_dx / uv_dy / lod_bias; EWA's ellipse and sample point;
a bilinear / bicubic texel's uv), which a plain "read the drawn tap" would
leave with no gradient at all. With ``p = w`` alone the terms ``dw / p``
grow as ``1 / w`` where a weight is small but its slope is not (a blend
weight ``frac(D)`` near 0, a bilinear weight near a texel centre, an EWA
texel on the ellipse's rim): an infinite variance in the mean (the integral
of ``1 / f``), seen in the tests as means 26 standard errors off the exact
gradient where a tap of probability 0.009 was never drawn. The uniform
share bounds every ``dw / p`` by ``n / DEFENSIVE`` times dw, at the price
of value weights ``w / p`` up to ``1 / (1 - DEFENSIVE)``.

What is drawn, per filter (``u`` [M, R] uniforms in [0, 1) per point, ``ROLES``):

- trilinear: the level, ``floor(D) + 1`` with probability
  ``(3/4) frac(D) + 1/8`` where D blends two levels (``u[:, -1]``; an
  integer D reads its one level), then one bilinear tap there. The bilinear
  tap rather than one of its four texels: it keeps the uv gradient local
  (the tap's own slope, no variance from a texel draw) and it is the native
  kernel's read (``trilinear_points`` with ``nearest_mip`` on the drawn
  integer level).
- anisotropic: one of the N probes along the major axis, uniformly
  (``u[:, 0]``; the weights are all 1/N, so ``w / p = 1``), and the
  deterministic trilinear tap there (both levels blended, no level draw):
  in the main job's fit the level draw was most of the noise that hurts
  (2.8 dB of texture PSNR at one draw a pixel, docs/stochastic.md), for
  one bilinear tap more a draw. Where every point has one probe the draw
  is the deterministic filter.
- ewa: the level as trilinear, then one texel of that level's ellipse
  by the exact normalised Gaussian weights of the deterministic filter,
  mixed (``u[:, 0]``, an inverse-CDF walk over the ellipse's texels, the
  same enumeration as ``ewa.py``).
- bilinear / bicubic (one level): one texel of the 2x2 / 4x4, drawn per
  axis by ``|w_x| / sum |w_x|`` mixed (``u[:, 0]``), likewise along v
  (``u[:, 1]``): the separable weights make the pmf a product, so two
  independent draws draw it exactly.

The k draws of a point (``sample``'s ``stochastic=k``) are stratified in
their first uniform: draw j takes it in ``[j / k, (j + 1) / k)``
(``hashed_uniforms``' ``strata``). Each stratum holds one draw, so the
mean of the k stays unbiased and its variance is at most that of k
independent draws; k stratified anisotropic draws of a point with k
probes (or with a divisor of k) read every probe equally often: the
deterministic filter exactly.

Decorrelated gradients (``Stream.grad_seed``; ``sample``'s
``decorrelate``): the value comes from one set of draws and the gradient
from another, independent one of the same law. A squared error of a draw
``x`` has the expectation ``(E x - y)^2 + Var x``; its gradient
``2 (x - y) dx`` with ``x`` and ``dx`` from independent draws is unbiased
for that of ``(E x - y)^2``, without the variance term that would pull a
fit towards textures smooth inside each footprint. The native kernels'
backwards draw the gradient's set from its seed in place of the value's,
so decorrelating costs nothing; the torch path evaluates both
(``decorrelated``).

Not unbiased: at an exact integer level D (a set of measure zero for a
continuous footprint) the level-blend derivative, which the deterministic
filter takes from below (``t_k - t_(k-1)``, DESIGN.md), is 0 here (one
level is read there). Everything else, values and first derivatives, is
unbiased; the tests check it exactly by enumerating the draws.
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Optional, Sequence

import torch
from torch import Tensor

from ... import _native as native
from ..options import STOCHASTIC_FILTERS
from ..lod import Ellipse, Footprint, level
from ..pyramid.mipmap import build_levels
from ..wrap import WRAP_CODES, drop_periods
from .ewa import _far_clamped, _pairs, covariance, gaussian, level_ellipse, texels
from .gather import _axis_weights, reduce_uv
from .separable import separable_sample
from .trilinear import Levels, TexturePyramid, _native_args, trilinear_points

# Uniforms per draw and filter, in this order: the level's last where there is one.
ROLES = {"trilinear": ("level",), "anisotropic": ("probe",), "ewa": ("texel", "level"),
         "bilinear": ("texel along u", "texel along v"), "bicubic": ("texel along u", "texel along v")}
# Every draw's pmf is mixed with the uniform one over its outcomes in this proportion (``defensive``), so
# that no outcome whose weight or weight derivative is nonzero has a tiny probability: the gradient terms
# ``dw / p`` stay bounded (at most ``n / DEFENSIVE`` times dw) and have finite variance; with p = w alone a
# blend weight frac(D) or a bilinear weight t near 0 gives terms of size 1 / frac, whose variance diverges
# (the integral of 1 / f). The values' weights w / p stay below 1 / (1 - DEFENSIVE).
DEFENSIVE = 0.25


# SplitMix64 (Steele, Lea, Flood 2014): the stream's increment and the finaliser's multipliers, as signed
# int64 (torch has no uint64 arithmetic; products wrap modulo 2^64 alike).
_GAMMA = 0x9E3779B97F4A7C15 - (1 << 64)
_MIX1 = 0xBF58476D1CE4E5B9 - (1 << 64)
_MIX2 = 0x94D049BB133111EB - (1 << 64)


def _shift_right(x: Tensor, s: int) -> Tensor:
    """``x >> s`` of int64 x read as unsigned (torch's ``>>`` on int64 copies the sign bit)."""
    return (x >> s) & ((1 << (64 - s)) - 1)


def hashed_uniforms(seed: int, first: int, count: int, roles: int, device: torch.device | str = "cpu",
                    strata: int = 1) -> Tensor:
    """Uniforms in [0, 1) of the draw counters ``first .. first + count - 1``: [count, roles] float64.

    Entry (i, r) is uniform number ``(first + i) * roles + r`` of ``seed``:
    SplitMix64's output at that position + 1 of the stream seeded by seed,
    its top 53 bits over 2^53 (every float64 step of [0, 1), fine enough to
    draw a tap of probability 1e-8 at its rate). Counter-based: each number
    depends on (seed, counter) alone, so the native kernel
    (``csrc/cpu/common.h`` draw_uniform, the same arithmetic on uint64)
    draws the same ones inside its loop, in any order, on any thread.
    With ``strata`` = k > 1, the first uniform of draw d = first + i moves
    into the stratum ``[j / k, (j + 1) / k)`` of ``j = d mod k`` (common.h
    stratified_uniform): the k draws of a point are consecutive counters.
    """
    ctr = torch.arange(first * roles, (first + count) * roles, dtype=torch.int64, device=device)
    z = (ctr + 1) * _GAMMA + seed
    z = (z ^ _shift_right(z, 30)) * _MIX1
    z = (z ^ _shift_right(z, 27)) * _MIX2
    z = z ^ _shift_right(z, 31)
    u = (_shift_right(z, 11).to(torch.float64) * 2.0 ** -53).view(count, roles)
    if strata > 1:
        j = torch.arange(first, first + count, dtype=torch.int64, device=device) % strata
        u[:, 0] = (j.to(torch.float64) + u[:, 0]) / strata
    return u


def draw_seed(generator: Optional[torch.Generator], device: torch.device | str) -> int:
    """One 64-bit seed (a signed int) from ``generator`` (None: torch's default one on ``device``)."""
    return int(torch.randint(-(1 << 63), (1 << 63) - 1, (), generator=generator, dtype=torch.int64,
                             device=device))


class Stream(NamedTuple):
    """The draws of one ``sample`` call: its seed, the uniforms per draw (``len(ROLES[filter])``), the
    counter of the first draw of the points at hand (a slice of the call's flat (point, draw) list), the
    draws a point (``strata``: their first uniforms are stratified) and the seed of the gradient's draws
    (``grad_seed``; None: the value's own)."""

    seed: int
    roles: int
    first: int = 0
    strata: int = 1
    grad_seed: Optional[int] = None

    def at(self, first: int) -> "Stream":
        """The same draws from counter ``first`` on (the points of one texture of a batch)."""
        return self._replace(first=first)

    def for_grad(self) -> "Stream":
        """The draws the gradient comes from: the value's, or the independent set of ``grad_seed``."""
        return self if self.grad_seed is None else self._replace(seed=self.grad_seed, grad_seed=None)

    def uniforms(self, count: int, device: torch.device | str = "cpu") -> Tensor:
        """The uniforms of ``count`` draws from ``first`` on: [count, roles] float64 (``hashed_uniforms``)."""
        return hashed_uniforms(self.seed, self.first, count, self.roles, device, self.strata)


def stream(filter: str, generator: Optional[torch.Generator], device: torch.device | str, draws: int = 1,
           decorrelate: bool = False) -> Stream:
    """The draws of one ``sample`` call with ``filter``, ``draws`` (k) a point: one seed drawn from
    ``generator`` (a second one for the gradient's draws where ``decorrelate``), so that a seeded generator
    repeats the call bit for bit, whatever the thread count. Draw j of flat point i (pixels in batch-major
    raster order) takes the ``len(ROLES[filter])`` uniforms of counter ``i * k + j``, its first in stratum j."""
    seed = draw_seed(generator, device)
    return Stream(seed, len(ROLES[filter]), strata=draws,
                  grad_seed=draw_seed(generator, device) if decorrelate else None)


def decorrelated(draw: Callable[[Stream], Tensor], st: Stream) -> Tensor:
    """``draw(st)``'s value with ``draw(st.for_grad())``'s gradient: the torch path's decorrelation.

    ``draw`` evaluates the estimator on a stream's uniforms; without a
    ``grad_seed`` (or with no gradient to take) it runs once.
    """
    if st.grad_seed is None or not torch.is_grad_enabled():
        return draw(st)
    with torch.no_grad():
        value = draw(st)
    slope = draw(st.for_grad())
    # Exactly the value (slope - slope is 0), the slope's gradient.
    return value + (slope - slope.detach())


class LevelDraw(NamedTuple):
    """A drawn mip level per point: ``level`` [M] (integer-valued, uv dtype) and its probability ``pdf`` [M]."""

    level: Tensor
    pdf: Tensor


def defensive(p: Tensor, n: int | Tensor) -> Tensor:
    """The mixture ``(1 - DEFENSIVE) p + DEFENSIVE / n`` of a pmf p over n outcomes with the uniform one."""
    return (1 - DEFENSIVE) * p + DEFENSIVE / n


def upper_probability(D: Tensor) -> Tensor:
    """P(draw level ``floor(D) + 1``) [M]: ``defensive(frac(D), 2)`` where D blends two levels, else 0 (detached)."""
    Dd = D.detach()
    f = Dd - torch.floor(Dd)
    return torch.where(f > 0, defensive(f, 2), 0.0)


def draw_level(D: Tensor, u: Tensor) -> LevelDraw:
    """Level ``floor(D) + 1`` with probability ``upper_probability(D)``, else ``floor(D)``; D [M], u [M] float64."""
    with torch.no_grad():
        Dd = D.detach()
        p = upper_probability(Dd)
        upper = u < p.to(u.dtype)
        return LevelDraw(torch.floor(Dd) + upper.to(Dd.dtype), torch.where(upper, p, 1 - p))


def level_weight(D: Tensor, draw: LevelDraw) -> Tensor:
    """The drawn level's weight in the trilinear blend over its probability, ``w(D) / p``: [M].

    ``w`` is ``1 - (D - k)`` for the lower level k, ``D - (k' - 1)`` for the
    upper level k'; differentiable in D.
    """
    upper = draw.level > D.detach()
    w = torch.where(upper, D - (draw.level - 1), 1 - (D - draw.level))
    return w / draw.pdf


def trilinear_estimate(levels: Levels, uv: Tensor, D: Tensor, draw: LevelDraw, wrap_u: str, wrap_v: str,
                       border: float) -> Tensor:
    """One trilinear draw per point, the draw given: ``w(D) / p * bilinear(level, uv)``: [C, M].

    levels, uv [M, 2], D [M] as ``trilinear_points``. Differentiable in the
    levels (or the texture), uv and D; deterministic given ``draw`` (the
    function that gradcheck checks).
    """
    # nearest_mip on an integer level reads exactly that level's bilinear tap: the native kernel's read on the
    # CPU, the torch path elsewhere (NaN uv handled there too).
    if native.kernel(uv) is None:  # the torch path groups the points by level itself (mip_blend)
        tap = trilinear_points(levels, uv, draw.level, wrap_u, wrap_v, border, nearest_mip=True)
    else:
        # The kernel reads the points in order; drawn at random, neighbouring points alternate between two
        # levels, which cost 9.3 ms fwd+bwd against 5.5 ms for the same reads at the smooth round(D) (65k
        # points, one thread). Read them grouped by level (a stable sort keeps raster order within a
        # level; 7.8 ms with the sort and the permutations) and put them back.
        with torch.no_grad():
            perm = torch.sort(draw.level.to(torch.uint8 if len(levels) <= 256 else torch.int64), stable=True).indices
            inv = torch.empty_like(perm).index_copy_(0, perm, torch.arange(perm.numel(), device=perm.device))
        tap = trilinear_points(levels, uv.index_select(0, perm), draw.level.index_select(0, perm), wrap_u, wrap_v,
                               border, nearest_mip=True).index_select(1, inv)
    return tap * level_weight(D, draw)


class _NativeDraw(torch.autograd.Function):
    """``stochastic_trilinear`` on the native CPU kernel: the draws hashed inside it, read and weighted in one
    pass; the backward draws the gradient's set (``Stream.for_grad``) from the same counters, so the node
    saves nothing but its inputs. uv [M, 2], D [M], levels ``[1, C, H_k, W_k]``, opts (wrap_u, wrap_v,
    border, stream) -> [C, M]."""

    @staticmethod
    def forward(ctx, uv: Tensor, D: Tensor, opts: tuple, *levels: Tensor) -> Tensor:
        wrap_u, wrap_v, border, st = opts
        ctx.opts = opts
        ctx.save_for_backward(uv, D, *levels)
        kernel = native.load()
        ctx.read = kernel.ReadOptions(wrap_u=WRAP_CODES[wrap_u], wrap_v=WRAP_CODES[wrap_v], border=border)
        lv, uv, D, _, _ = _native_args(levels, uv, D, None, None)
        return kernel.stochastic_forward(lv, uv, D, st.seed, st.first, st.strata, ctx.read)

    @staticmethod
    def backward(ctx, grad: Tensor):
        uv, D, *levels = ctx.saved_tensors
        wrap_u, wrap_v, border, st = ctx.opts
        st = st.for_grad()
        need = ctx.needs_input_grad
        if torch.is_grad_enabled():
            # Double backward (create_graph=True): the torch path on the same uniforms.
            return native.double_backward(
                lambda: stochastic_trilinear(levels, uv, D, st.uniforms(uv.shape[0], uv.device), wrap_u, wrap_v,
                                             border),
                (uv, D, None, *levels), need, grad)
        kernel = native.load()
        lv, uvc, Dc, _, _ = _native_args(levels, uv, D, None, None)
        gl, guv, gD = kernel.stochastic_backward(lv, uvc, Dc, grad, st.seed, st.first, st.strata, ctx.read,
                                                 kernel.TapNeeds(levels=any(need[3:]), uv=need[0], D=need[1],
                                                                 axis=False))
        return (guv, gD if need[1] else None, None, *native.level_grads(gl, need[3:], levels))


def _kernel_levels(levels: Levels) -> list[Tensor]:
    """The levels as the native kernels take them (a ``TexturePyramid`` built: its reading node is bypassed)."""
    return build_levels(levels.texture, len(levels)) if isinstance(levels, TexturePyramid) else list(levels)


def stochastic_trilinear(levels: Levels, uv: Tensor, D: Tensor, u: Tensor | Stream, wrap_u: str, wrap_v: str,
                         border: float) -> Tensor:
    """One draw of the trilinear filter per point: [C, M].

    Args:
        levels, uv [M, 2], D [M]: as ``trilinear_points``.
        u: [M, 1] float64 uniforms (the level's); or the ``Stream`` they
            come from (``Stream.uniforms``), which on the CPU the native
            kernel draws inside its loop (the same uniforms, so the same
            draws), the gradient from ``Stream.for_grad``'s.

    Returns:
        [C, M], whose expectation over ``u`` is ``trilinear_points``'s value,
        and whose gradient's expectation is its gradient (texture, uv, D;
        module docstring for the exception at integer D).
    """
    if isinstance(u, Stream):
        if native.kernel(uv) is not None:
            return _NativeDraw.apply(uv, D, (wrap_u, wrap_v, float(border), u), *_kernel_levels(levels))
        return decorrelated(lambda s: stochastic_trilinear(levels, uv, D, s.uniforms(uv.shape[0], uv.device),
                                                           wrap_u, wrap_v, border), u)
    return trilinear_estimate(levels, uv, D, draw_level(D, u[:, -1]), wrap_u, wrap_v, border)


def probe_offsets(count: Tensor, u: Tensor) -> Tensor:
    """The drawn probe's offset along the axis, ``(i + 1/2) / N - 1/2`` of ``i = floor(u N)``: [M] float64.

    count [M] int64 (N >= 1), u [M] float64 in [0, 1): the native op
    ``probe_offsets`` computes the same (``tap_offset`` in taps.cpp).
    """
    n = count.to(torch.float64)
    i = torch.minimum(torch.floor(u * n), n - 1)
    return (i + 0.5) / n - 0.5


class _NativeProbe(torch.autograd.Function):
    """``stochastic_anisotropic`` on the native CPU kernels: the probes' offsets hashed by ``probe_offsets``,
    then the deterministic one-tap trilinear read at ``uv + offset * axis``; the backward reads at the
    gradient's probes (``Stream.for_grad``) and gives the axis ``offset`` times the tap's uv gradient, as
    the torch path's ``addcmul`` does. Arguments as ``_NativeDraw``, plus axis [M, 2] and count [M]."""

    @staticmethod
    def forward(ctx, uv: Tensor, D: Tensor, axis: Tensor, count: Tensor, opts: tuple, *levels: Tensor) -> Tensor:
        wrap_u, wrap_v, border, st = opts
        kernel = native.load()
        ctx.opts = opts
        # Where D needs a gradient, an integer D = k > 0 reads level k - 1 too (as _NativeTaps).
        ctx.read = kernel.ReadOptions(wrap_u=WRAP_CODES[wrap_u], wrap_v=WRAP_CODES[wrap_v], border=border,
                                      d_grad=ctx.needs_input_grad[1])
        offset = kernel.probe_offsets(count.contiguous(), uv, st.seed, st.first, st.strata)
        # The value's offsets serve the backward unless it draws its own.
        ctx.save_for_backward(uv, D, axis, count, offset if st.grad_seed is None else None, *levels)
        return kernel.forward(*_native_args(levels, torch.addcmul(uv, axis, offset.unsqueeze(-1)), D, None, None),
                              ctx.read)

    @staticmethod
    def backward(ctx, grad: Tensor):
        uv, D, axis, count, offset, *levels = ctx.saved_tensors
        wrap_u, wrap_v, border, st = ctx.opts
        st = st.for_grad()
        need = ctx.needs_input_grad
        if torch.is_grad_enabled():
            # Double backward (create_graph=True): the torch path on the same uniforms.
            return native.double_backward(
                lambda: stochastic_anisotropic(levels, uv, D, st.uniforms(uv.shape[0], uv.device), wrap_u, wrap_v,
                                               border, axis, count),
                (uv, D, axis, None, None, *levels), need, grad)
        kernel = native.load()
        if offset is None:
            offset = kernel.probe_offsets(count.contiguous(), uv, st.seed, st.first, st.strata)
        uvp = torch.addcmul(uv, axis, offset.unsqueeze(-1))
        gl, guv, gD, _ = kernel.backward(
            *_native_args(levels, uvp, D, None, None), grad, ctx.read,
            kernel.TapNeeds(levels=any(need[5:]), uv=need[0] or need[2], D=need[1], axis=False))
        return (guv if need[0] else None, gD if need[1] else None,
                guv * offset.unsqueeze(-1) if need[2] else None, None, None,
                *native.level_grads(gl, need[5:], levels))


def stochastic_anisotropic(levels: Levels, uv: Tensor, D: Tensor, u: Tensor | Stream, wrap_u: str, wrap_v: str,
                           border: float, axis: Tensor, count: Tensor) -> Tensor:
    """One draw of the anisotropic filter per point: the trilinear tap at one of its probes: [C, M].

    Args:
        levels, uv [M, 2], D [M], axis [M, 2], count [M]: as
            ``trilinear_points`` (``anisotropic_taps``'s D, axis and count).
        u: [M, 1] float64 uniforms (the probe's), or their ``Stream`` (as
            ``stochastic_trilinear``'s; native: ``_NativeProbe``).

    Returns:
        [C, M]: ``trilinear(uv + o_i * axis, D)`` of probe ``i = floor(u N)``,
        whose expectation is ``trilinear_points(..., axis, count)``, for the
        value and every gradient (texture, uv, D, axis): each probe's weight
        1 / N is its probability.
    """
    if isinstance(u, Stream):
        if native.kernel(uv) is not None:
            return _NativeProbe.apply(uv, D, axis, count, (wrap_u, wrap_v, float(border), u),
                                      *_kernel_levels(levels))
        return decorrelated(lambda s: stochastic_anisotropic(levels, uv, D, s.uniforms(uv.shape[0], uv.device),
                                                             wrap_u, wrap_v, border, axis, count), u)
    with torch.no_grad():
        offset = probe_offsets(count, u[:, 0]).to(uv.dtype)
    return trilinear_points(levels, torch.addcmul(uv, axis, offset.unsqueeze(-1)), D, wrap_u, wrap_v, border)


# ---------------------------------------------------------------- EWA


class TexelDraw(NamedTuple):
    """A drawn texel per point of one level: integer-valued ``col``, ``row`` [m], its probability ``pdf`` [m]
    and the ellipse's weight sum ``total`` [m] (detached, uv dtype)."""

    col: Tensor
    row: Tensor
    pdf: Tensor
    total: Tensor


def _segment_pick(point: Tensor, w: Tensor, m: int, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per point, one of its pairs with probability ``w / sum w`` by inverse CDF: (pair index, pdf, sum w) [m].

    point [n] sorted ascending (each point's pairs contiguous), every point
    owning a pair of positive weight; w [n] >= 0 float64; u [m] float64.
    """
    n = point.numel()
    cw = torch.cumsum(w, 0)
    counts = torch.bincount(point, minlength=m)
    end = torch.cumsum(counts, 0)
    before = torch.where(end - counts > 0, cw.index_select(0, (end - counts - 1).clamp(min=0)), 0.0)
    total = cw.index_select(0, end - 1) - before
    # The first pair whose running sum passes the target has positive weight; rounding can push the target
    # to the point's end, so cap at its last positive pair.
    idx = torch.searchsorted(cw, before + u * total, right=True)
    last = torch.full((m,), -1, dtype=torch.long, device=w.device).scatter_reduce(
        0, point, torch.where(w > 0, torch.arange(n, device=w.device), -1), "amax")
    idx = torch.minimum(idx, last)
    return idx, w.index_select(0, idx) / total, total


def draw_ewa_texel(H: int, W: int, uv: Tensor, sigma: Tensor, minor: Tensor, scale: Tensor, full_h: int,
                   full_w: int, coarsest: bool, u: Tensor) -> TexelDraw:
    """One texel of each point's EWA ellipse on an H x W level, drawn by its normalised Gaussian weight."""
    with torch.no_grad():
        sxx, sxy, syy, origin, frac = level_ellipse(H, W, uv.detach(), sigma.detach(), minor.detach(),
                                                    scale.detach(), full_h, full_w, coarsest)
        point, rx, ry = _pairs(frac[:, 0], frac[:, 1], sxx, sxy, syy)
        per_pair = lambda x: x.index_select(0, point)  # noqa: E731
        det = sxx * syy - sxy * sxy
        w = gaussian(rx - per_pair(frac[:, 0]), ry - per_pair(frac[:, 1]), per_pair(sxx), per_pair(sxy),
                     per_pair(syy), per_pair(det))
        m = uv.shape[0]
        w = w.to(torch.float64)
        total = w.new_zeros(m).index_add(0, point, w)
        count = torch.bincount(point, minlength=m).to(w.dtype)
        # The Gaussian pmf mixed with the uniform one over the ellipse's texels (DEFENSIVE): the texels at
        # the rim have weights near 0 but slopes that are not.
        p = defensive(w / total.index_select(0, point), count.index_select(0, point))
        idx, pdf, _ = _segment_pick(point, p, m, u)
        return TexelDraw(origin[:, 0] + rx.index_select(0, idx), origin[:, 1] + ry.index_select(0, idx),
                         pdf.to(uv.dtype), total.to(uv.dtype))


def ewa_texel_estimate(lev: Tensor, uv: Tensor, sigma: Tensor, minor: Tensor, scale: Tensor, full_h: int,
                       full_w: int, coarsest: bool, draw: TexelDraw, wrap_u: str, wrap_v: str,
                       border: float) -> Tensor:
    """One EWA draw on one level [1, C, Hk, Wk], the texel given: ``(w / sum w) / p * texel``: [C, m].

    Differentiable in the level, uv and the ellipse (sigma, minor, scale):
    ``w`` and the normaliser ``sum w`` over the ellipse's texels are
    recomputed with gradients (the set of texels is fixed by the detached
    inputs; the Gaussian is 0 on the ellipse's edge, so the sum is
    continuous as texels enter or leave). Deterministic given ``draw``.
    """
    _, C, H, W = lev.shape
    sxx, sxy, syy, origin, frac = level_ellipse(H, W, uv, sigma, minor, scale, full_h, full_w, coarsest)
    det = sxx * syy - sxy * sxy
    # The drawn texel's offset from the sample point: (col - origin) - frac, as ewa's pairs (rx - sx).
    w = gaussian(draw.col - origin[:, 0] - frac[:, 0], draw.row - origin[:, 1] - frac[:, 1], sxx, sxy, syy, det)
    if torch.is_grad_enabled() and (frac.requires_grad or sxx.requires_grad):
        with torch.no_grad():
            point, rx, ry = _pairs(frac[:, 0].detach(), frac[:, 1].detach(), sxx.detach(), sxy.detach(),
                                   syy.detach())
        per_pair = lambda x: x.index_select(0, point)  # noqa: E731 (index_select: see ewa._ewa_chunk)
        wall = gaussian(rx - per_pair(frac[:, 0]), ry - per_pair(frac[:, 1]), per_pair(sxx), per_pair(sxy),
                        per_pair(syy), per_pair(det))
        total = wall.new_zeros(uv.shape[0]).index_add(0, point, wall)
    else:
        total = draw.total  # no gradient through the weights: the sum the draw was made from
    vals = texels(lev[0].reshape(C, H * W), H, W, draw.col, draw.row, wrap_u, wrap_v, border)
    return vals * (w / total / draw.pdf)


def stochastic_ewa(levels: Sequence[Tensor], uv: Tensor, fp: Footprint, ell: Ellipse, lod_bias: Tensor | float,
                   max_aniso: float, wrap_u: str, wrap_v: str, border: float, u: Tensor) -> Tensor:
    """One draw of ``ewa_points`` per point (same arguments, plus ``u`` [M, 2] float64: texel, level): [C, M].

    The level as ``stochastic_trilinear``, then one texel of that level's
    ellipse by its normalised Gaussian weight. NaN where uv is not finite.
    """
    H, W = levels[0].shape[-2:]
    n = len(levels)
    ok = torch.isfinite(uv).all(-1)
    uv_safe = torch.where(ok.unsqueeze(-1), uv, torch.zeros_like(uv))
    # The same period removal and far clamp as ewa_points (why: there).
    uv_safe = torch.stack([_far_clamped(drop_periods(uv_safe[:, 0], wrap_u), wrap_u),
                           _far_clamped(drop_periods(uv_safe[:, 1], wrap_v), wrap_v)], -1)
    sigma, minor, log2_minor = covariance(fp, ell, max_aniso)
    D = level(log2_minor, lod_bias, n)
    scale = torch.exp2(fp.log2_scale)
    ldraw = draw_level(D, u[:, -1])
    factor = level_weight(D, ldraw)
    out = uv.new_zeros((levels[0].shape[1], uv.shape[0]))
    lev_id = ldraw.level.long()
    parts, where = [], []
    for k in torch.unique(lev_id).tolist():
        idx = (lev_id == k).nonzero().squeeze(1)
        pick = lambda x: x.index_select(0, idx)  # noqa: E731
        args = (pick(uv_safe), pick(sigma), pick(minor), pick(scale), H, W, k == n - 1)
        tdraw = draw_ewa_texel(*levels[k].shape[-2:], *args[:4], H, W, k == n - 1, pick(u[:, 0]))
        parts.append(ewa_texel_estimate(levels[k], *args, tdraw, wrap_u, wrap_v, border))
        where.append(idx)
    if parts:
        out = out.index_add(1, torch.cat(where), torch.cat(parts, 1))
    out = out * factor
    return torch.where(ok, out, torch.full_like(out, float("nan")))


# ---------------------------------------------------------------- one level: bilinear, bicubic


class SeparableDraw(NamedTuple):
    """Per point the drawn tap offset along u and v (int64, from floor of the texel position) and ``pdf``."""

    ox: Tensor
    oy: Tensor
    pdf: Tensor


_FIRST = {"linear": 0, "cubic": -1}  # the offset of the kernel's first tap from floor(x)


def _texel_position(texture: Tensor, uv: Tensor, wrap_u: str, wrap_v: str) -> tuple[Tensor, Tensor]:
    """(floor, frac) of the texel position ``uv * (W, H) - 1/2`` of uv [B, M, 2], as ``gather`` forms it."""
    H, W = texture.shape[-2:]
    xy = reduce_uv(uv, wrap_u, wrap_v) * uv.new_tensor([W, H]) - 0.5
    base = torch.floor(xy.detach())
    return base, xy - base


def _axis_pick(w: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Per point a tap of w [..., K, M] with probability ``|w| / sum |w|`` over K; u [..., M]: (index, pdf) [..., M]."""
    K = w.shape[-2]
    a = w.abs().to(torch.float64)
    a = defensive(a / a.sum(-2, keepdim=True), K)
    cw = torch.cumsum(a, -2)
    total = cw[..., -1:, :]
    i = (cw <= u.unsqueeze(-2) * total).sum(-2, keepdim=True)
    last = torch.where(a > 0, torch.arange(K, device=w.device).view(-1, 1), -1).amax(-2, keepdim=True)
    i = torch.minimum(i, last.clamp(min=0))  # no positive weight (NaN uv): tap 0, whose NaN weight shows
    return i.squeeze(-2), (a.gather(-2, i) / total).squeeze(-2)


def draw_separable(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, u: Tensor) -> SeparableDraw:
    """One texel of the 2x2 ("linear") or 4x4 ("cubic") kernel per point of uv [B, M, 2]; u [B, M, 2]."""
    with torch.no_grad():
        _, t = _texel_position(texture, uv.detach(), wrap_u, wrap_v)
        wx, _ = _axis_weights(t[..., 0], kind, False)
        wy, _ = _axis_weights(t[..., 1], kind, False)
        ix, px = _axis_pick(wx, u[..., 0])
        iy, py = _axis_pick(wy, u[..., 1])
        first = _FIRST[kind]
        return SeparableDraw(ix + first, iy + first, (px * py).to(uv.dtype))


def separable_estimate(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float,
                       draw: SeparableDraw) -> Tensor:
    """One draw of the bilinear / bicubic filter, the texel given: ``w(uv) / p * texel``: [B, C, M].

    texture [Bt, C, H, W], uv [B, M, 2] as ``separable_sample``.
    Differentiable in the texture and uv (through the weight); deterministic
    given ``draw``.
    """
    H, W = texture.shape[-2:]
    base, t = _texel_position(texture, uv, wrap_u, wrap_v)
    wx, _ = _axis_weights(t[..., 0], kind, False)
    wy, _ = _axis_weights(t[..., 1], kind, False)
    first = _FIRST[kind]
    w = (wx.gather(-2, (draw.ox - first).unsqueeze(-2)).squeeze(-2)
         * wy.gather(-2, (draw.oy - first).unsqueeze(-2)).squeeze(-2))
    # The texel read by nearest at its centre: the one wrap rule, the native kernel on the CPU, and a texture
    # gradient that lands on that texel only. NaN uv: NaN base, NaN centre, a NaN pixel.
    centre = (base + torch.stack((draw.ox, draw.oy), -1).to(uv.dtype) + 0.5) / uv.new_tensor([W, H])
    tex = separable_sample(texture, centre, "nearest", wrap_u, wrap_v, border)
    return tex * (w / draw.pdf).unsqueeze(1)


def stochastic_separable(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float,
                         u: Tensor) -> Tensor:
    """One draw of ``separable_sample(texture, uv, kind, ...)`` per point (kind "linear" / "cubic"): [B, C, M].

    u: [B, M, 2] float64 (along u, along v). The expectation over u is the filter's value
    and its texture and uv gradients (module docstring).
    """
    return separable_estimate(texture, uv, kind, wrap_u, wrap_v, border,
                              draw_separable(texture, uv, kind, wrap_u, wrap_v, u))


__all__ = ["STOCHASTIC_FILTERS", "ROLES", "hashed_uniforms", "draw_seed", "Stream", "stream", "decorrelated",
           "LevelDraw", "draw_level", "level_weight", "trilinear_estimate", "stochastic_trilinear", "probe_offsets",
           "stochastic_anisotropic", "TexelDraw", "draw_ewa_texel",
           "ewa_texel_estimate", "stochastic_ewa", "SeparableDraw", "draw_separable", "separable_estimate",
           "stochastic_separable", "DEFENSIVE", "defensive", "upper_probability"]

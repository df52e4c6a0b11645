"""``sample()``: one entry point for every texture filter and wrap mode."""
from __future__ import annotations

import math
from typing import Optional, Union

import torch
from torch import Tensor

from .._checks import broadcast_batch, check_float, check_same, describe
from .filters.ewa import ewa_points
from .filters.ripmap import ripmap_points
from .filters.sat import sat_points
from .filters.separable import separable_sample
from .filters.stochastic import (Stream, decorrelated, stochastic_anisotropic, stochastic_ewa, stochastic_separable,
                                 stochastic_trilinear, stream)
from .filters.trilinear import Levels, TexturePyramid, trilinear_points
from .lod import ellipse, footprint
from .options import (BOX_FILTERS, DEFAULT_TOLERANCE, MAX_ANISO, MIP_FILTERS, SEPARABLE, check_bias, check_filter,
                      check_generator, check_number, check_stochastic)
from .pyramid.mipmap import Mipmap, level_count, mipmap
from .pyramid.ripmap import Ripmap, check_ripmap
from .taps import levels_read, taps
from .wrap import Wrap, parse_wrap



def sample(
    texture: Union[Tensor, Mipmap, Ripmap],
    uv: Tensor,
    *,
    filter: str = "bilinear",
    wrap: Wrap = "repeat",
    border_value: float = 0.0,
    uv_dx: Optional[Tensor] = None,
    uv_dy: Optional[Tensor] = None,
    lod_bias: Union[float, Tensor] = 0.0,
    max_aniso: float = 16,
    tolerance: float = DEFAULT_TOLERANCE,
    stochastic: int = 0,
    generator: Optional[torch.Generator] = None,
    decorrelate: bool = False,
) -> Tensor:
    """Sample a texture at uv coordinates.

    Args:
        texture: [B, C, H, W] float tensor, or a Mipmap (``difftex.mipmap``)
            or a Ripmap (``difftex.ripmap``); B = 1 broadcasts over the uv
            batch. The single-level filters and "sat" read the base level of
            either, "ripmap" a Ripmap's levels (a Mipmap's base), the other
            mip filters a Ripmap's diagonal; the mip filters build the
            pyramid of a plain tensor on the fly (differentiably; all but
            ewa only as deep as the points read). On the CPU the
            single-level filters read a ``torch.channels_last`` texture in
            place, faster than a planar one (docs/bench_sample.md), and its
            gradient comes back channels_last.
        uv: [B, Ho, Wo, 2]; (0, 0) is the top-left corner of texel (0, 0),
            (1, 1) the bottom-right corner of the last texel; u runs along the
            width, v along the rows (DESIGN.md). ``grid_sample`` with
            ``grid = 2 * uv - 1`` and ``align_corners=False`` samples the same
            point. B = 1 broadcasts over the texture batch.
        filter: "nearest" (round half to even, like grid_sample), "bilinear",
            "bicubic" (Keys cubic, a = -0.75, like grid_sample); the mip
            filters "trilinear" (level ``D = log2 L + lod_bias``, L the longer
            footprint vector in texels, blend of floor(D) and floor(D) + 1),
            "nearest-mip" (bilinear at level round(D)), "anisotropic" (up to
            max_aniso trilinear taps along the footprint's major axis),
            "ewa" (Gaussian elliptical weighted average, pbrt-v4 style),
            "auto" (per pixel the cheapest that ``tolerance`` allows: one
            bilinear tap on level 0 where the footprint is under half a
            texel, one trilinear tap where
            the footprint is nearly round, else anisotropic with just enough
            taps), and two filters of the footprint's axis-aligned bounding
            box: "ripmap" (a level per axis, ``D_u = log2 w_u + lod_bias``,
            ``w_u`` the box's width in texels, likewise along v; bilinear
            reads of four levels blended) and "sat" (the exact box average
            over the box scaled by ``2^lod_bias``, at least one texel and
            at most one period wide per axis, from a summed-area table).
            See ``difftex.texture.filters`` for each.
        wrap: "repeat" | "clamp" | "mirror" | "border", one for both axes or a
            pair (wrap_u, wrap_v).
        border_value: the constant that "border" reads outside the texture
            (a finite number, the same for every channel).
        uv_dx, uv_dy: [B, Ho, Wo, 2] uv per pixel column / row (times
            (W, H) texels per pixel); required by the mip filters. B = 1
            broadcasts.
        lod_bias: added to the level; a number or a [B, Ho, Wo] tensor.
        max_aniso: most taps per pixel ("anisotropic", "auto"), largest
            axis ratio kept ("ewa"); a number in [1, 1024].
        tolerance: "auto" only: how much wider a tap's prefilter (2^level)
            may be than the anisotropic filter's, as a fraction; a number
            >= 0. 0 takes the anisotropic filter's taps (fewer only where
            the minor axis is under half a level-0 texel); larger values
            take ``1 + tolerance`` times fewer taps (rounded up) and blur
            more across the footprint. The default 0.1 stays within 0.5 dB
            of "anisotropic" at the same max_aniso on the test scenes.
        stochastic: 0 (default): the deterministic filter. k >= 1 (True
            is 1): stochastic texture filtering (Pharr et al. 2024), the
            mean of k stratified draws a pixel, each reading one tap drawn
            from the filter's own weights (3/4 of each draw; 1/4 uniform
            over the same taps, which keeps the gradients' variance finite):
            "trilinear" one bilinear tap on a level drawn by the blend
            weight; "anisotropic" the trilinear tap of one probe of the
            line, drawn uniformly; "ewa" a level, then one texel drawn by
            its normalised Gaussian weight; "bilinear" / "bicubic" one texel
            drawn by |weight| (the sign and the normaliser carried). Other
            filters raise. Unbiased: the expectation over the draws is the
            deterministic filter's value, and the expectation of the
            gradient its gradient for texture, uv, uv_dx, uv_dy and
            lod_bias (except at an exact integer level, where the level
            derivative is 0). Draw j of a pixel's k takes its first uniform
            (the probe, trilinear's level, EWA's texel, the texel along u)
            in [j / k, (j + 1) / k): the variance falls at least as 1 / k,
            and k anisotropic draws of a pixel with k probes are its
            deterministic filter (``difftex.texture.filters.stochastic``,
            docs/stochastic.md).
        generator: the ``torch.Generator`` of the draws (on uv's device),
            or None for torch's default generator. A call draws one 64-bit
            seed from it (two with ``decorrelate``) and hashes every draw
            from the seed and the draw's index, so a seeded generator
            repeats the result bit for bit, whatever the thread count.
            Ignored when ``stochastic`` is 0.
        decorrelate: with ``stochastic``: the value from one set of draws,
            its gradient from a second, independent one (same law; the
            value is the one ``decorrelate=False`` gives with the same
            generator state). A squared error's gradient ``2 (x - y) dx``
            is then unbiased for that of the deterministic filter's error,
            without the draws' variance as an extra smoothing term. Free on
            the CPU's trilinear and anisotropic kernels (the backward draws
            the second set); elsewhere the second set is evaluated too.

    Returns:
        [B, C, Ho, Wo], same dtype and device as the inputs.

    Gradients flow to texture (through every mip level back to the base) and
    uv (nearest: texture only), and for the mip filters to
    uv_dx, uv_dy and lod_bias through the level blend and the tap placement
    (nearest-mip: none). The single-level backward is itself differentiable
    (double backward). A pixel with a NaN or infinite uv comes out NaN and
    passes no gradient to the texture; other pixels are unaffected. Zero or
    NaN derivatives read level 0, infinite ones the coarsest level; both
    give finite values and zero derivative gradients.

    Raises ValueError naming the argument on bad shapes, batch mismatch,
    different devices, an unknown filter / wrap, missing derivatives for a
    mip filter, ``max_aniso`` outside [1, 1024], ``tolerance < 0`` or a
    non-finite ``border_value``, ``stochastic < 0``, ``stochastic`` with a
    filter that has no stochastic mode or a ``generator`` on another device
    type; TypeError on non-float tensors, mixed dtypes, a ``border_value``
    that is not a number, a ``stochastic`` that is not an int or a
    ``generator`` that is not a ``torch.Generator``.
    """
    pyramid = None
    if isinstance(texture, Ripmap):
        texture = check_ripmap(texture)  # user-built levels, as a Mipmap's below
        if filter == "ripmap":
            pyramid = texture
        # The other mip filters read its diagonal, the mip chain (then validated as a Mipmap below).
        texture = texture.mipmap() if filter in MIP_FILTERS and filter not in BOX_FILTERS else texture.base
    if isinstance(texture, Mipmap):
        pyramid = mipmap(list(texture.levels))  # re-validates user-built levels
        texture = pyramid.levels[0]
    check_float("texture", texture, 4, shape_doc="[B, C, H, W]")
    check_float("uv", uv, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_same("uv", uv, "texture", texture)
    if texture.shape[-1] < 1 or texture.shape[-2] < 1 or texture.shape[1] < 1:
        raise ValueError(f"texture: expected C, H, W >= 1, got shape {tuple(texture.shape)}")
    wrap_u, wrap_v = parse_wrap(wrap)
    check_filter(filter)
    max_aniso = check_number("max_aniso", max_aniso, 1, MAX_ANISO)
    border_value = check_number("border_value", border_value, -math.inf)
    tolerance = check_number("tolerance", tolerance, 0)
    draws = check_stochastic(stochastic, filter)
    if not isinstance(decorrelate, bool):
        raise TypeError(f"decorrelate: expected a bool, got {type(decorrelate).__name__}")
    if draws:
        check_generator(generator, uv)
    _, Ho, Wo, _ = uv.shape
    derivs = _check_derivatives(filter, uv, texture, uv_dx, uv_dy)
    bias = check_bias(lod_bias, uv, "uv", texture, "texture")
    sizes = [texture.shape[0], uv.shape[0]] + [d.shape[0] for d in derivs]
    names = ["texture", "uv", "uv_dx", "uv_dy"][:len(sizes)]
    if isinstance(bias, Tensor) and bias.dim() == 3:
        sizes.append(bias.shape[0])
        names.append("lod_bias")
    B = broadcast_batch(names, sizes)
    Bt, C = texture.shape[:2]
    if B * Ho * Wo == 0:
        # An empty image: nothing to read, but the result stays in the inputs' graph.
        parts = [t for t in (texture, uv, *derivs, bias) if isinstance(t, Tensor)]
        return sum(t.reshape(-1)[:0].reshape(B, C, Ho, Wo) for t in parts)
    u = stream(filter, generator, uv.device, draws, decorrelate) if draws else None
    if filter in MIP_FILTERS:
        if pyramid is None:
            pyramid = texture
        return _sample_mip(pyramid, uv, derivs[0], derivs[1], bias, B, filter, max_aniso, tolerance,
                           wrap_u, wrap_v, border_value, u, draws)
    if u is not None:
        # k draws of each pixel as k neighbouring points, averaged.
        pts = uv.expand(B, -1, -1, -1).reshape(B, Ho * Wo, 2)
        pts = pts if draws == 1 else pts.repeat_interleave(draws, 1)
        out = decorrelated(lambda s: stochastic_separable(
            texture, pts, SEPARABLE[filter], wrap_u, wrap_v, border_value,
            s.uniforms(B * Ho * Wo * draws, uv.device).view(B, Ho * Wo * draws, -1)), u)
        return out.view(B, C, Ho, Wo) if draws == 1 else out.view(B, C, Ho, Wo, draws).mean(-1)
    return separable_sample(texture, uv if uv.shape[0] == B else uv.expand(B, -1, -1, -1), SEPARABLE[filter],
                            wrap_u, wrap_v, border_value)


def _check_derivatives(filter: str, uv: Tensor, texture: Tensor, uv_dx: object, uv_dy: object) -> list[Tensor]:
    """Validated [uv_dx, uv_dy], or [] where neither is given to a single-level filter."""
    if uv_dx is None and uv_dy is None and filter not in MIP_FILTERS:
        return []
    B, Ho, Wo, _ = uv.shape
    for name, d in (("uv_dx", uv_dx), ("uv_dy", uv_dy)):
        if d is None:
            raise ValueError(f"{name}: required by filter {filter!r} (and given together with "
                             f"{'uv_dy' if name == 'uv_dx' else 'uv_dx'}): expected [B, Ho, Wo, 2] = "
                             f"[{B}, {Ho}, {Wo}, 2], got None")
        check_float(name, d, 4, last=2, shape_doc=f"[B, Ho, Wo, 2] = [{B}, {Ho}, {Wo}, 2]")
        check_same(name, d, "texture", texture)
        if tuple(d.shape[1:3]) != (Ho, Wo):
            raise ValueError(f"{name}: expected shape [B, Ho, Wo, 2] = [{B}, {Ho}, {Wo}, 2] like uv, "
                             f"got {describe(d)}")
    return [uv_dx, uv_dy]  # type: ignore[list-item]


def _sample_mip(pyramid: Union[Mipmap, Tensor], uv: Tensor, uv_dx: Tensor, uv_dy: Tensor,
                bias: Union[float, Tensor], B: int, filter: str, max_aniso: float, tolerance: float,
                wrap_u: str, wrap_v: str, border: float, u: Optional[Stream] = None,
                draws: int = 1) -> Tensor:
    """The mip filters on flat point lists; one pass per texture of the batch.

    A plain texture's pyramid is built only as deep as its points read (the
    same values and gradients as the full chain; a view that only magnifies
    builds none): by the reading node of the bilinear-tap filters
    (``TexturePyramid``), here for EWA, which reads the full chain.
    With ``u`` (the call's ``filters.stochastic.Stream``) the stochastic filter, ``draws`` (k) a point:
    each point becomes k neighbouring points, one draw each, averaged.
    """
    base = pyramid.levels[0] if isinstance(pyramid, Mipmap) else pyramid.base if isinstance(pyramid, Ripmap) \
        else pyramid
    Bt, C, H, W = base.shape
    _, Ho, Wo, _ = uv.shape
    P = Ho * Wo
    flat = lambda t: t.expand(B, Ho, Wo, *t.shape[3:]).reshape(B * P, *t.shape[3:])
    pts, dx, dy = flat(uv), flat(uv_dx), flat(uv_dy)
    if isinstance(bias, Tensor):
        bias = flat(bias) if bias.dim() == 3 else bias
    if filter in BOX_FILTERS:
        # Their own pyramid (a ripmap, built by ripmap_points where not given) or table, per texture.
        src = pyramid if filter == "ripmap" and isinstance(pyramid, Ripmap) else base
        read = ripmap_points if filter == "ripmap" else sat_points

        def run_box(s: Union[Tensor, Ripmap], sl: slice) -> Tensor:
            b = bias[sl] if isinstance(bias, Tensor) and bias.dim() == 1 else bias
            return read(s, pts[sl], dx[sl], dy[sl], b, wrap_u, wrap_v, border)

        return _per_texture(run_box, lambda i: src if i is None else src.select(i) if isinstance(src, Ripmap)
                            else src[i:i + 1], Bt, B, C, Ho, Wo)
    n_levels = len(pyramid.levels) if isinstance(pyramid, Mipmap) else level_count(H, W)
    levels = pyramid.levels if isinstance(pyramid, Mipmap) else None
    if filter == "ewa":
        fp = footprint(dx, dy, H, W)
        ell = ellipse(fp)
        if levels is None:
            levels = mipmap(pyramid, max_levels=n_levels).levels  # EWA reads levels with its own gather
    else:
        D, axis, count = taps(filter, dx, dy, bias, H, W, n_levels, max_aniso, tolerance)
        if levels is None:
            # The bilinear-tap filters get the texture and build its pyramid inside their reading node.
            n_levels = levels_read(D, n_levels, filter == "nearest-mip")
            if filter == "nearest-mip":
                D = D.clamp(max=n_levels - 1)  # round(D) may lie below D

    def run(lv: Levels, sl: slice) -> Tensor:
        if u is not None:
            return _run_stochastic(lv, sl)
        if filter == "ewa":
            b = bias[sl] if isinstance(bias, Tensor) and bias.dim() == 1 else bias
            f = type(fp)(*(x[sl] for x in fp))
            e = type(ell)(*(x[sl] for x in ell))
            return ewa_points(lv, pts[sl], f, e, b, max_aniso, wrap_u, wrap_v, border)
        return trilinear_points(lv, pts[sl], D[sl], wrap_u, wrap_v, border, nearest_mip=filter == "nearest-mip",
                                axis=None if axis is None else axis[sl], count=None if count is None else count[sl])

    def _run_stochastic(lv: Levels, sl: slice) -> Tensor:
        k = draws
        # k draws of a point: k neighbouring points (one draw: the points as they are).
        rep = (lambda t: t[sl]) if k == 1 else (lambda t: t[sl].repeat_interleave(k, 0))  # noqa: E731
        first = (sl.start or 0) * k
        uk = u.at(first)
        if filter == "ewa":
            b = rep(bias) if isinstance(bias, Tensor) and bias.dim() == 1 else bias
            n = (pts.shape[0] if sl.stop is None else sl.stop) * k - first
            out = decorrelated(lambda s: stochastic_ewa(lv, rep(pts), type(fp)(*map(rep, fp)),
                                                        type(ell)(*map(rep, ell)), b, max_aniso, wrap_u, wrap_v,
                                                        border, s.uniforms(n, pts.device)), uk)
        elif filter == "anisotropic":
            if axis is None:  # one probe everywhere: every draw is the deterministic filter
                return trilinear_points(lv, pts[sl], D[sl], wrap_u, wrap_v, border)
            out = stochastic_anisotropic(lv, rep(pts), rep(D), uk, wrap_u, wrap_v, border, rep(axis), rep(count))
        else:
            out = stochastic_trilinear(lv, rep(pts), rep(D), uk, wrap_u, wrap_v, border)
        return out if k == 1 else out.view(out.shape[0], -1, k).mean(-1)

    def levels_of(i: int | None) -> Levels:
        if levels is None:
            return TexturePyramid(base if i is None else base[i:i + 1], n_levels)
        return levels if i is None else [lv[i:i + 1] for lv in levels]

    return _per_texture(run, levels_of, Bt, B, C, Ho, Wo)


def _per_texture(run, source_of, Bt: int, B: int, C: int, Ho: int, Wo: int) -> Tensor:
    """``run(source_of(i), points of view i)`` -> [C, points], per texture, as [B, C, Ho, Wo]."""
    P = Ho * Wo
    if Bt == 1:
        # One texture for every view: all points in one flat list (copied into DESIGN.md's contiguous output).
        return run(source_of(None), slice(None)).view(C, B, Ho, Wo).transpose(0, 1).contiguous()
    outs = [run(source_of(i), slice(i * P, (i + 1) * P)) for i in range(B)]
    return torch.stack(outs).view(B, C, Ho, Wo)

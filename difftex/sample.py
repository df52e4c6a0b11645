"""``sample()``: one entry point for every texture filter and wrap mode."""
from __future__ import annotations

import math
import numbers
from typing import Optional, Union

import torch
from torch import Tensor

from ._checks import broadcast_batch, check_float, check_same, describe
from .filters.anisotropic import anisotropic_points
from .filters.basic import separable_sample
from .filters.ewa import ewa_points
from .filters.trilinear import trilinear_points
from .lod import ellipse, footprint, level, log2_length
from .mipmap import Mipmap, mipmap
from .wrap import Wrap, parse_wrap

# Filters that read one texture level; the value is the per-axis kernel.
SEPARABLE = {"nearest": "nearest", "bilinear": "linear", "bicubic": "cubic"}
# Filters that read a mip pyramid and need uv_dx / uv_dy.
MIP_FILTERS = ("trilinear", "nearest-mip", "anisotropic", "ewa")
FILTERS = tuple(SEPARABLE) + MIP_FILTERS


def sample(
    texture: Union[Tensor, Mipmap],
    uv: Tensor,
    *,
    filter: str = "bilinear",
    wrap: Wrap = "repeat",
    border_value: float = 0.0,
    uv_dx: Optional[Tensor] = None,
    uv_dy: Optional[Tensor] = None,
    lod_bias: Union[float, Tensor] = 0.0,
    max_aniso: float = 16,
) -> Tensor:
    """Sample a texture at uv coordinates.

    Args:
        texture: [B, C, H, W] float tensor, or a Mipmap (``difftex.mipmap``);
            B = 1 broadcasts over the uv batch. The single-level filters read
            a Mipmap's level 0; the mip filters build the pyramid of a plain
            tensor on the fly (differentiably).
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
            max_aniso trilinear taps along the footprint's major axis) and
            "ewa" (Gaussian elliptical weighted average, pbrt-v4 style). See
            ``difftex.filters`` for each.
        wrap: "repeat" | "clamp" | "mirror" | "border", one for both axes or a
            pair (wrap_u, wrap_v).
        border_value: the constant that "border" reads outside the texture.
        uv_dx, uv_dy: [B, Ho, Wo, 2] uv per pixel column / row (times
            (W, H) texels per pixel); required by the mip filters. B = 1
            broadcasts.
        lod_bias: added to the level; a number or a [B, Ho, Wo] tensor.
        max_aniso: most taps per pixel ("anisotropic"), largest axis ratio
            kept ("ewa"); a number >= 1.

    Returns:
        [B, C, Ho, Wo], same dtype and device as the inputs.

    Gradients flow to texture (through every mip level back to the base) and
    uv (nearest, nearest-mip: texture only), and for the mip filters to
    uv_dx, uv_dy and lod_bias through the level blend and the tap placement
    (nearest-mip: none). The single-level backward is itself differentiable
    (double backward). A pixel with a NaN or infinite uv comes out NaN and
    passes no gradient to the texture; other pixels are unaffected. Zero or
    NaN derivatives read level 0, infinite ones the coarsest level; both
    give finite values and zero derivative gradients.

    Raises ValueError naming the argument on bad shapes, batch mismatch,
    different devices, an unknown filter / wrap, missing derivatives for a
    mip filter or ``max_aniso < 1``; TypeError on non-float tensors or mixed
    dtypes.
    """
    pyramid = None
    if isinstance(texture, Mipmap):
        pyramid = mipmap(list(texture.levels))  # re-validates user-built levels
        texture = pyramid.levels[0]
    check_float("texture", texture, 4, shape_doc="[B, C, H, W]")
    check_float("uv", uv, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_same("uv", uv, "texture", texture)
    if texture.shape[-1] < 1 or texture.shape[-2] < 1 or texture.shape[1] < 1:
        raise ValueError(f"texture: expected C, H, W >= 1, got shape {tuple(texture.shape)}")
    wrap_u, wrap_v = parse_wrap(wrap)
    if not isinstance(filter, str) or filter not in FILTERS:
        raise ValueError(f"filter: unknown filter {filter!r}; expected one of {FILTERS}")
    max_aniso = _check_max_aniso(max_aniso)
    _, Ho, Wo, _ = uv.shape
    derivs = _check_derivatives(filter, uv, texture, uv_dx, uv_dy)
    bias = _check_bias(lod_bias, uv, texture)
    sizes = [texture.shape[0], uv.shape[0]] + [d.shape[0] for d in derivs]
    names = ["texture", "uv", "uv_dx", "uv_dy"][:len(sizes)]
    if isinstance(bias, Tensor) and bias.dim() == 3:
        sizes.append(bias.shape[0])
        names.append("lod_bias")
    B = broadcast_batch(names, sizes)
    Bt, C = texture.shape[:2]
    if filter in MIP_FILTERS:
        if pyramid is None:
            pyramid = mipmap(texture)
        return _sample_mip(pyramid, uv, derivs[0], derivs[1], bias, B, filter, max_aniso,
                           wrap_u, wrap_v, float(border_value))
    if Bt == 1:
        # One texture for every view: all sample points in one flat row.
        flat_uv = uv.reshape(1, -1, 2)
    else:
        flat_uv = uv.expand(B, -1, -1, -1).reshape(B, -1, 2)
    out = separable_sample(texture, flat_uv, SEPARABLE[filter], wrap_u, wrap_v, border_value)
    if Bt == 1 and B > 1:
        return out.view(C, B, Ho, Wo).transpose(0, 1)
    return out.view(B, C, Ho, Wo)


def _check_max_aniso(max_aniso: object) -> float:
    if isinstance(max_aniso, bool) or not isinstance(max_aniso, numbers.Real):
        raise TypeError(f"max_aniso: expected a number >= 1, got {type(max_aniso).__name__}")
    if not (math.isfinite(max_aniso) and max_aniso >= 1):
        raise ValueError(f"max_aniso: expected a finite number >= 1, got {max_aniso!r}")
    return float(max_aniso)


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


def _check_bias(lod_bias: object, uv: Tensor, texture: Tensor) -> Union[float, Tensor]:
    if isinstance(lod_bias, Tensor):
        B, Ho, Wo, _ = uv.shape
        check_float("lod_bias", lod_bias, (0, 3), shape_doc=f"scalar or [B, Ho, Wo] = [{B}, {Ho}, {Wo}]")
        check_same("lod_bias", lod_bias, "texture", texture)
        if lod_bias.dim() == 3 and tuple(lod_bias.shape[1:]) != (Ho, Wo):
            raise ValueError(f"lod_bias: expected a scalar or [B, Ho, Wo] = [{B}, {Ho}, {Wo}] like uv, "
                             f"got {describe(lod_bias)}")
        return lod_bias
    if isinstance(lod_bias, bool) or not isinstance(lod_bias, numbers.Real):
        raise TypeError(f"lod_bias: expected a number or a float tensor [B, Ho, Wo], got {type(lod_bias).__name__}")
    return float(lod_bias)


def _sample_mip(pyramid: Mipmap, uv: Tensor, uv_dx: Tensor, uv_dy: Tensor, bias: Union[float, Tensor], B: int,
                filter: str, max_aniso: float, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """The mip filters on flat point lists; one pass per texture of the batch."""
    levels = pyramid.levels
    Bt, C, H, W = levels[0].shape
    _, Ho, Wo, _ = uv.shape
    P = Ho * Wo
    flat = lambda t: t.expand(B, Ho, Wo, *t.shape[3:]).reshape(B * P, *t.shape[3:])
    pts, dx, dy = flat(uv), flat(uv_dx), flat(uv_dy)
    if isinstance(bias, Tensor):
        bias = flat(bias) if bias.dim() == 3 else bias
    if filter in ("trilinear", "nearest-mip"):
        log2_len = log2_length(dx, dy, H, W)
    else:
        fp = footprint(dx, dy, H, W)
        ell = ellipse(fp)

    def run(lv: list[Tensor], sl: slice) -> Tensor:
        b = bias[sl] if isinstance(bias, Tensor) and bias.dim() == 1 else bias
        if filter in ("trilinear", "nearest-mip"):
            D = level(log2_len[sl], b, len(lv))
            return trilinear_points(lv, pts[sl], D, wrap_u, wrap_v, border, nearest_mip=filter == "nearest-mip")
        f = type(fp)(*(x[sl] for x in fp))
        e = type(ell)(*(x[sl] for x in ell))
        fn = anisotropic_points if filter == "anisotropic" else ewa_points
        return fn(lv, pts[sl], f, e, b, max_aniso, wrap_u, wrap_v, border)

    if Bt == 1:
        # One texture for every view: all points in one flat list.
        return run(levels, slice(None)).view(C, B, Ho, Wo).transpose(0, 1)
    outs = [run([lv[i:i + 1] for lv in levels], slice(i * P, (i + 1) * P)) for i in range(B)]
    return torch.stack(outs).view(B, C, Ho, Wo)

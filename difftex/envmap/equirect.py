"""Sampling a latitude-longitude (equirectangular) environment map by direction, and converting it to a cube map.

The map's convention is :func:`difftex.envmap.direction_to_equirect_uv`'s
(row 0 straight up, -z at the centre column, the seam behind at +z).  Both
functions read through :func:`difftex.sample` with wrap ("repeat", "clamp"):
u wraps around the seam, v is clamped at the poles, and the uv derivatives
are the analytic ones of the direction mapping, so the seam has no line and
the level of detail follows the true footprint on the sphere.
"""
from __future__ import annotations

import math
from typing import Optional, Union

import torch
from torch import Tensor

from .._checks import broadcast_batch, check_float, check_same
from ..texture import Mipmap, sample
from ..texture.options import MIP_FILTERS, check_filter
from ..mapping.common import EPS
from .directions import check_dirs_derivs, cube_to_direction, equirect_uv_of_unit


def _unit(dirs: Tensor, dds: list[Tensor]) -> tuple[Tensor, list[Tensor], Tensor]:
    """(n, dn, zero): unit directions, the derivatives of the normalisation, and where dirs is the zero vector.

    Zero vectors are swapped for a harmless direction (-z) with zero derivatives before any division, so
    neither the values nor the backward ever divide by zero; the caller zeroes their output.  NaN / inf
    are not zero: they flow on and become NaN in their own pixel.
    """
    length = lambda d: torch.hypot(torch.hypot(d[..., 0], d[..., 1]), d[..., 2])  # hypot: no overflow
    zero = length(dirs.detach()) == 0
    safe = torch.where(zero[..., None], torch.tensor([0.0, 0.0, -1.0], dtype=dirs.dtype, device=dirs.device), dirs)
    norm = length(safe)[..., None]
    n = safe / norm
    # d(d / |d|) = (dd - n (n . dd)) / |d|: the radial part of dd changes only the length.
    dn = []
    for dd in dds:
        dd = torch.where(zero[..., None], 0.0, dd)
        dn.append((dd - n * (n * dd).sum(-1, keepdim=True)) / norm)
    return n, dn, zero


def _pole_derivatives(n: Tensor, dn: list[Tensor], duv: list[Tensor]) -> list[Tensor]:
    """The uv derivatives with the exact poles given the limit footprint (see :func:`equirect`)."""
    rho = torch.hypot(n[..., 0].detach(), n[..., 2].detach())
    pole = rho <= EPS  # direction_to_equirect_uv's own test for the axis, on a unit vector
    if not bool(pole.any()):
        return duv
    north = n[..., 1] > 0
    # The tangential (x, z) parts of both derivatives; their combined length is how far theta gets in a pixel.
    t = torch.stack([dn[0][..., 0], dn[0][..., 2], dn[1][..., 0], dn[1][..., 2]], dim=-1)
    moving = (t.detach() != 0).any(-1)
    # The norm's backward at 0 is 0 / 0: feed it a harmless point where the result is not used.
    r = torch.where(moving, torch.where(moving[..., None], t, 1.0).norm(dim=-1), 0.0)
    zero = torch.zeros_like(r)
    # The pixel's disk around the pole is the strip of every longitude by [0, r / pi] of v: one derivative
    # spans the whole turn (the limit of 1 / sin(theta)), the other the v extent (signed into the map).
    at_dx = torch.stack([moving.to(r.dtype), zero], dim=-1)
    at_dy = torch.stack([zero, torch.where(north, r, -r) / math.pi], dim=-1)
    return [torch.where(pole[..., None], at, g) for at, g in zip((at_dx, at_dy), duv)]


def _at_most_one_turn(duv: list[Tensor]) -> list[Tensor]:
    """The derivatives with their u parts scaled so that hypot(du_dx, du_dy) <= 1, one turn of longitude.

    Near a pole du grows without bound (1 / sin(theta)); beyond a whole turn the footprint already covers
    every longitude, and a longer one would only send the filters to coarser levels that average other
    latitudes too (up to the whole map's mean).  The scaling keeps the footprint's direction and its v
    parts, and meets the exact pole's (1, 0) continuously.
    """
    du = torch.stack([duv[0][..., 0], duv[1][..., 0]], dim=-1)
    h = torch.hypot(du[..., 0].detach(), du[..., 1].detach())
    over = h > 1  # False for NaN
    if not bool(over.any()):
        return duv
    # Divide only where h > 1, so neither the value nor the backward meets a small or zero h.
    hn = torch.where(over, torch.where(over[..., None], du, 1.0).norm(dim=-1), 1.0)
    return [torch.stack([g[..., 0] / hn, g[..., 1]], dim=-1) for g in duv]


def _check_dirs(name: str, d: object, like_name: str, like: Tensor, shape_doc: str) -> Tensor:
    d = check_float(name, d, 4, last=3, shape_doc=shape_doc)
    check_same(name, d, like_name, like)
    return d


def equirect(
    env: Union[Tensor, Mipmap],
    dirs: Tensor,
    *,
    filter: str = "bilinear",
    dirs_dx: Optional[Tensor] = None,
    dirs_dy: Optional[Tensor] = None,
    lod_bias: Union[float, Tensor] = 0.0,
    max_aniso: float = 16,
) -> Tensor:
    """Look up a latitude-longitude environment map by direction.

    Args:
        env: [B, C, He, We] equirectangular map in the convention of
            :func:`difftex.envmap.direction_to_equirect_uv` (row 0 is +y,
            the centre column -z, the seam u = 0 / 1 at +z), usually
            He = We / 2; or a Mipmap of one.  B = 1 broadcasts over dirs.
        dirs: [B, H, W, 3] directions, y up, of any length from 1e-18
            (float32; 1e-100 in float64) up (they are normalised here).  B = 1 broadcasts over env.
        filter: any filter of :func:`difftex.sample`; the mip filters
            ("trilinear", "nearest-mip", "anisotropic", "ewa", "auto") need
            dirs_dx and dirs_dy.
        dirs_dx, dirs_dy: [B, H, W, 3] d(dirs)/d(pixel column / row) of the
            same (unnormalised) directions, e.g. of a reflected view vector.
        lod_bias: added to the mip level; a number or a [B, H, W] tensor.
        max_aniso: most taps ("anisotropic", "auto") / largest axis ratio
            ("ewa"), in [1, 1024].

    Returns:
        [B, C, H, W], env's dtype and device.

    The map wraps in u (repeat) and is clamped in v.  The uv derivatives
    are the analytic ones of direction_to_equirect_uv, continuous across
    the seam.  Near a pole the u derivative grows like 1 / sin(theta)
    (theta the angle from the pole): the anisotropic and EWA filters see a
    long thin footprint along the latitude circle, trilinear (isotropic)
    a correspondingly coarse level.  The u parts of the two derivatives are
    scaled so that their length is at most one whole turn (u = 1): a longer
    footprint covers no more longitudes, only coarser levels.  Exactly at a pole (distance from the
    y axis <= 1e-9 after normalising), where longitude is undefined, the
    point is uv (0.5, 0) / (0.5, 1) and each derivative is the limit
    footprint, the strip of every longitude by the v extent of the pixel:
    uv_dx = (1, 0) (one whole turn of longitude, so the filters average the
    polar rows around the whole circle) and uv_dy = (0, r / pi), signed
    into the map, with r the length of the four components of dirs_dx and
    dirs_dy across the axis (after normalising; the rate of theta).  These
    two stand for the pixel's disk, not for its column and row; when both
    derivatives lie along the axis both are (0, 0).  The
    pole's uv has no gradient w.r.t. dirs (the mapping is not
    differentiable there); its footprint, through r, still passes
    gradients to dirs, dirs_dx and dirs_dy.

    A zero direction gives 0 in every channel and no gradient to anything;
    a NaN or infinite direction gives NaN in its own pixel only (and no
    gradient to env from it).

    Gradients flow to env (through every mip level), dirs and, for the mip
    filters, dirs_dx, dirs_dy and lod_bias.

    Raises ValueError naming the argument on bad shapes, batch mismatch,
    different devices, an unknown filter, or missing dirs_dx / dirs_dy for
    a mip filter; TypeError on non-float tensors or mixed dtypes (and
    whatever :func:`difftex.sample` raises for lod_bias / max_aniso).
    """
    if isinstance(env, Mipmap):
        base = env.levels[0]
    else:
        base = check_float("env", env, 4, shape_doc="[B, C, He, We] (or a Mipmap)")
    dirs = _check_dirs("dirs", dirs, "env", base, "[B, H, W, 3]")
    check_filter(filter)
    B, H, W, _ = dirs.shape
    dds = check_dirs_derivs(dirs_dx, dirs_dy, dirs, filter, filter in MIP_FILTERS, "env", base)
    sizes = [base.shape[0], B] + [d.shape[0] for d in dds]
    broadcast_batch(["env", "dirs", "dirs_dx", "dirs_dy"][:len(sizes)], sizes)
    if dds:
        Bd = max(B, dds[0].shape[0], dds[1].shape[0])
        dirs = dirs.expand(Bd, -1, -1, -1)
        dds = [d.expand(Bd, -1, -1, -1) for d in dds]
    n, dn, zero = _unit(dirs, dds)
    if dn:
        uv, uv_dx, uv_dy = equirect_uv_of_unit(n, dn)
        uv_dx, uv_dy = _pole_derivatives(n, dn, _at_most_one_turn([uv_dx, uv_dy]))
    else:
        uv, uv_dx, uv_dy = equirect_uv_of_unit(n, []), None, None
    out = sample(env, uv, filter=filter, wrap=("repeat", "clamp"), uv_dx=uv_dx, uv_dy=uv_dy,
                 lod_bias=lod_bias, max_aniso=max_aniso)
    if bool(zero.any()):
        out = torch.where(zero[:, None], 0.0, out)
    return out


def _cube_directions(size: int, dtype: torch.dtype, device) -> tuple[Tensor, Tensor, Tensor]:
    """Directions of every cube texel centre and their derivatives per texel column / row, [1, 6 size, size, 3]."""
    c = (torch.arange(size, dtype=dtype, device=device) + 0.5) / size
    v, u = torch.meshgrid(c, c, indexing="ij")
    uv = torch.stack([u, v], dim=-1).expand(6, size, size, 2)
    face = torch.arange(6, device=device)[:, None, None].expand(6, size, size)
    d = cube_to_direction(face, uv)
    # cube_to_direction is affine in uv: one step of uv gives the Jacobian's columns exactly.
    step = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=dtype, device=device)
    d_du = cube_to_direction(face, uv + step[0]) - d
    d_dv = cube_to_direction(face, uv + step[1]) - d
    flat = lambda t: t.reshape(1, 6 * size, size, 3)
    return flat(d), flat(d_du / size), flat(d_dv / size)


def equirect_to_cube(
    env: Union[Tensor, Mipmap],
    size: int,
    *,
    filter: str = "anisotropic",
    lod_bias: float = 0.0,
    max_aniso: float = 16,
) -> Tensor:
    """Resample a latitude-longitude environment map into the six faces of a cube map.

    Every cube texel centre's direction (:func:`difftex.envmap.cube_to_direction`,
    OpenGL face order +X, -X, +Y, -Y, +Z, -Z; row 0 of a face is t = 0) is
    looked up with :func:`equirect`, with the analytic derivatives of the
    direction per cube texel column / row (the Jacobian of cube_to_direction
    w.r.t. uv times 1 / size), so a cube smaller than the map is filtered by
    its footprint rather than aliased.

    Args:
        env: [B, C, He, We] equirectangular map (or a Mipmap), as for :func:`equirect`.
        size: cube face width = height in texels, an int >= 1.
        filter: any filter of :func:`difftex.sample`. The default "anisotropic"
            follows the map's stretch towards the poles (1 / sin(theta) along
            u); "trilinear" blurs the two polar faces to the level of that
            stretch (errors 0.1-0.3 there on smooth maps, not shrinking with
            resolution, against 1e-3 for anisotropic up to size 32).
        lod_bias, max_aniso: as for :func:`equirect` (lod_bias a number).

    Returns:
        [B, 6, C, size, size], env's dtype and device.

    Differentiable w.r.t. env (and lod_bias if a tensor).  Raises ValueError
    naming the argument for a size that is not an int >= 1 and whatever
    :func:`equirect` raises for env / filter.
    """
    if isinstance(size, bool) or not isinstance(size, int):
        raise TypeError(f"size: expected an int >= 1 (cube face width in texels), got {type(size).__name__} {size!r}")
    if size < 1:
        raise ValueError(f"size: expected an int >= 1 (cube face width in texels), got {size}")
    base = env.levels[0] if isinstance(env, Mipmap) else check_float("env", env, 4, shape_doc="[B, C, He, We]")
    d, dx, dy = _cube_directions(size, base.dtype, base.device)
    out = equirect(env, d, filter=filter, dirs_dx=dx, dirs_dy=dy, lod_bias=lod_bias, max_aniso=max_aniso)
    B, C = out.shape[:2]
    return out.view(B, C, 6, size, size).transpose(1, 2).contiguous()

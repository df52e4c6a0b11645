"""Environment-map directions: equirectangular (latitude / longitude) uv and OpenGL cube-map faces, both ways.

Like the uv generators (``difftex.mapping``), each function is a plain differentiable torch
function with optional analytic screen-space derivatives.
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from .._checks import check_float, check_same, describe
from ..geometry.raster import pow2_normalise
from ..mapping.common import (
    UVResult, check_derivs, check_tensor, cube_tables, dir_floor, result, sphere_uv,
)


def direction_to_equirect_uv(dirs: torch.Tensor, *,
                             dirs_dx: Optional[torch.Tensor] = None,
                             dirs_dy: Optional[torch.Tensor] = None) -> UVResult:
    """Equirectangular (latitude / longitude) uv of directions, y-up world.

    Convention: ``v = theta / pi`` with theta the angle from +y (the top row
    is straight up); ``u = (phi + pi) / 2pi`` with ``phi = atan2(x, -z)``:
    the default OpenGL view direction -z is the centre of the panorama
    (u = 0.5), +x is u = 0.75 (right of centre, so the panorama is not
    mirrored for a viewer inside looking along -z), -x is u = 0.25, and the
    seam (u = 1 -> 0) is behind, at +z.  Inverse: :func:`equirect_uv_to_direction`.

    Args:
        dirs: [..., 3] directions of any length from 1e-18 (float32; 1e-100
            in float64) up: only the direction matters.
        dirs_dx, dirs_dy: optional [..., 3] d(dir)/d(pixel column / row), e.g.
            of the reflected view vector.

    Returns:
        uv [..., 2], or ``(uv, uv_dx, uv_dy)``; the derivatives are
        continuous across the seam.  Straight up / down u = 0.5; a zero
        direction gives (0.5, 0.5).

    Differentiable w.r.t. dirs and their derivatives, NaN-free everywhere.
    Raises ValueError naming the argument for a last dimension other than 3,
    TypeError for non-floating tensors.
    """
    dirs = check_tensor(dirs, "dirs", 3)
    dds = check_derivs(dirs_dx, dirs_dy, "dirs", 3, dirs)
    # A power of two per direction brings its largest component into [0.5, 1) exactly (the angles and their
    # derivatives do not change): sphere_uv's axis test is an absolute length, which a short direction is under.
    m = dirs.detach().abs().amax(-1, keepdim=True)
    return equirect_uv_of_unit(pow2_normalise(dirs, m), [pow2_normalise(d, m) for d in dds])


def equirect_uv_of_unit(dirs: torch.Tensor, dds: list[torch.Tensor]) -> UVResult:
    """:func:`direction_to_equirect_uv` of checked directions of about unit length (``equirect`` normalises
    its own), without the rescaling: uv, or (uv, uv_dx, uv_dy) with the two derivatives ``dds``."""
    uv, duv = sphere_uv(-dirs[..., 2], dirs[..., 0], dirs[..., 1],
                         [-d[..., 2] for d in dds], [d[..., 0] for d in dds], [d[..., 1] for d in dds])
    return result(uv, duv)


def equirect_uv_to_direction(uv: torch.Tensor) -> torch.Tensor:
    """Unit direction of an equirectangular uv; the inverse of :func:`direction_to_equirect_uv`.

    Args:
        uv: [..., 2].

    Returns:
        [..., 3] unit directions.

    Differentiable w.r.t. uv.  Raises ValueError naming the argument for a
    last dimension other than 2, TypeError for non-floating tensors.
    """
    uv = check_tensor(uv, "uv", 2)
    phi = uv[..., 0] * (2 * math.pi) - math.pi
    theta = uv[..., 1] * math.pi
    s = torch.sin(theta)
    return torch.stack([s * torch.sin(phi), torch.cos(theta), -s * torch.cos(phi)], dim=-1)


def direction_to_cube(dirs: torch.Tensor, *,
                      dirs_dx: Optional[torch.Tensor] = None,
                      dirs_dy: Optional[torch.Tensor] = None):
    """Cube-map face and uv of directions, OpenGL convention.

    Faces are numbered as ``GL_TEXTURE_CUBE_MAP_POSITIVE_X + i``: 0 +X,
    1 -X, 2 +Y, 3 -Y, 4 +Z, 5 -Z (:data:`CUBE_FACES`); the face is the
    largest |component| (ties prefer x over y over z; a zero direction gives
    +X).  Within the face, OpenGL 4.6 table 8.19: ``u = (s_c / |m_a| + 1) / 2``,
    ``v = (t_c / |m_a| + 1) / 2`` with (s_c, t_c, m_a) = (-z, -y, x) on +X,
    (z, -y, x) on -X, (x, z, y) on +Y, (x, -z, y) on -Y, (x, -y, z) on +Z,
    (-x, -y, z) on -Z; OpenGL's t is our v, i.e. row 0 of each face image is
    t = 0 as the faces are stored in files.  The face centre is (0.5, 0.5).

    Args:
        dirs: [..., 3] directions of any length from 1e-18 (float32; 1e-100
            in float64) up: only the direction matters.
        dirs_dx, dirs_dy: optional [..., 3] d(dir)/d(pixel column / row).

    Returns:
        ``(face, uv)``: face [...] int64, uv [..., 2]; or
        ``(face, uv, uv_dx, uv_dy)`` with the derivatives of the face's own
        projection (the face is piecewise constant).

    Differentiable w.r.t. dirs and their derivatives (not the face index);
    a zero direction gives finite values and gradients.  Raises ValueError
    naming the argument for a last dimension other than 3, TypeError for
    non-floating tensors.
    """
    dirs = check_tensor(dirs, "dirs", 3)
    dds = check_derivs(dirs_dx, dirs_dy, "dirs", 3, dirs)
    face, sc, tc, ma, dsc, dtc, dma = _face_coords(dirs, dds)
    # Below the floor (the zero vector) m_a = inf, as the kernel: the face centre, zero derivatives, no gradient.
    ma = torch.where(ma >= dir_floor(ma.dtype), ma, torch.inf)
    s, t = sc / ma, tc / ma
    uv = torch.stack([0.5 * (s + 1.0), 0.5 * (t + 1.0)], dim=-1)
    # d(s_c / m_a) = (d s_c - (s_c / m_a) d m_a) / m_a: no m_a^2, which underflows for short float32 directions.
    duv = [torch.stack([0.5 * (a - s * c) / ma, 0.5 * (b - t * c) / ma], dim=-1) for a, b, c in zip(dsc, dtc, dma)]
    return (face, uv, duv[0], duv[1]) if duv else (face, uv)


def _face_coords(dirs: torch.Tensor, dds: list[torch.Tensor]):
    """(face, s_c, t_c, m_a, [d s_c], [d t_c], [d m_a]) of OpenGL table 8.19, by selects on the components.

    The same values as ``cube_tables`` + ``pick`` (the face of ``major_face``:
    ties prefer x over y over z), in elementwise selects instead of table
    lookups and gathers: on the CPU 3-4x fewer passes over the points, the
    face pick of every cube-map read. Per face, (s_c, t_c, m_a) = (-g z, -y,
    g x) on +-X, (x, g z, g y) on +-Y, (g x, -y, g z) on +-Z, g = +-1 the
    sign of the major component.
    """
    a = dirs.detach().abs()
    ax, ay, az = a.unbind(-1)
    isx = (ax >= ay) & (ax >= az)
    isy = ~isx & (ay >= az)
    d = dirs.detach()
    neg = torch.where(isx, d[..., 0] < 0, torch.where(isy, d[..., 1] < 0, d[..., 2] < 0))
    face = torch.where(isx, 0, torch.where(isy, 2, 4)) + neg.long()
    g = 1.0 - 2.0 * neg.to(dirs.dtype)

    def coords(v: torch.Tensor):
        x, y, z = v.unbind(-1)
        sc = torch.where(isx, -g * z, torch.where(isy, x, g * x))
        tc = torch.where(isy, g * z, -y)
        ma = g * torch.where(isx, x, torch.where(isy, y, z))
        return sc, tc, ma

    sc, tc, ma = coords(dirs)
    ds = [coords(dd) for dd in dds]
    return face, sc, tc, ma, [t[0] for t in ds], [t[1] for t in ds], [t[2] for t in ds]


def cube_to_direction(face: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Direction (not normalised, |m_a| = 1) of a cube-map face and uv; inverse of :func:`direction_to_cube`.

    Args:
        face: [...] integer face indices 0..5 (:data:`CUBE_FACES`).
        uv: [..., 2] uv within the face.

    Returns:
        [..., 3] the point of the cube [-1, 1]^3 on that face.

    Differentiable w.r.t. uv.  Raises ValueError naming the argument for bad
    shapes, TypeError for a non-integer face or non-floating uv.
    """
    uv = check_tensor(uv, "uv", 2)
    if not isinstance(face, torch.Tensor) or face.is_floating_point() or face.is_complex():
        raise TypeError(f"face must be an integer tensor of shape [...], got "
                        f"{type(face).__name__ if not isinstance(face, torch.Tensor) else face.dtype}")
    if face.shape != uv.shape[:-1]:
        raise ValueError(f"face must have shape uv.shape[:-1] = {tuple(uv.shape[:-1])}, got {tuple(face.shape)}")
    if face.dtype == torch.bool:
        raise TypeError("face must be an integer tensor of shape [...] with values 0..5, got dtype torch.bool")
    face = face.long()
    if face.numel() and not bool(((face >= 0) & (face <= 5)).all()):
        raise ValueError(f"face must hold values 0..5, got values in [{int(face.min())}, {int(face.max())}]")
    sc_ax, sc_sg, tc_ax, tc_sg, ma_ax, ma_sg = cube_tables(face)
    sc = (2.0 * uv[..., 0] - 1.0) * sc_sg.to(uv.dtype)
    tc = (2.0 * uv[..., 1] - 1.0) * tc_sg.to(uv.dtype)
    ma = ma_sg.to(uv.dtype)
    axes = torch.arange(3, device=uv.device)
    out = (torch.where(sc_ax[..., None] == axes, sc[..., None], 0.0)
           + torch.where(tc_ax[..., None] == axes, tc[..., None], 0.0)
           + torch.where(ma_ax[..., None] == axes, ma[..., None], 0.0))
    return out


def check_dirs_derivs(dirs_dx: object, dirs_dy: object, dirs: torch.Tensor, filter: str, needed: bool,
                      ref_name: str, ref: torch.Tensor) -> list[torch.Tensor]:
    """The ``dirs_dx`` / ``dirs_dy`` arguments of an environment lookup (``cubemap``, ``equirect``), checked.

    Args:
        dirs_dx, dirs_dy: what the caller got: None, or [B, H, W, 3] float tensors with the H, W of
            ``dirs`` [B, H, W, 3] (B may differ: the caller broadcasts the batches).
        filter: the lookup's filter, named in the message when ``needed``.
        needed: whether the filter needs the derivatives (the mip filters).
        ref_name, ref: the tensor whose dtype and device they must share, and its argument name.

    Returns:
        [] where neither is given and none is needed, else [dirs_dx, dirs_dy].

    Raises ValueError naming the missing one (required by the filter, or by the other one given: they
    come together) or one of a wrong rank, last dimension or H, W; TypeError for a non-float one or one
    of another dtype / device than ``ref``.
    """
    if dirs_dx is None and dirs_dy is None and not needed:
        return []
    B, H, W, _ = dirs.shape
    shape_doc = f"[B, H, W, 3] = [{B}, {H}, {W}, 3] like dirs"
    out = []
    for name, other, d in (("dirs_dx", "dirs_dy", dirs_dx), ("dirs_dy", "dirs_dx", dirs_dy)):
        if d is None:
            why = f"filter {filter!r}" if needed else f"given {other}"
            raise ValueError(f"{name}: required by {why} (give dirs_dx and dirs_dy together): expected shape "
                             f"{shape_doc}, got None")
        d = check_float(name, d, 4, last=3, shape_doc=shape_doc)
        check_same(name, d, ref_name, ref)
        if tuple(d.shape[1:3]) != (H, W):
            raise ValueError(f"{name}: expected shape {shape_doc}, got {describe(d)}")
        out.append(d)
    return out

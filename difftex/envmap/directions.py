"""Environment-map directions: equirectangular (latitude / longitude) uv and OpenGL cube-map faces, both ways.

Like the uv generators (``difftex.mapping``), each function is a plain differentiable torch
function with optional analytic screen-space derivatives.
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from ..mapping.common import (
    EPS, UVResult, check_derivs, check_tensor, cube_tables, major_face, pick, result, sphere_uv,
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
        dirs: [..., 3] directions, any non-zero length.
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
        dirs: [..., 3] directions, any non-zero length.
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
    face = major_face(dirs)
    sc_ax, sc_sg, tc_ax, tc_sg, ma_ax, ma_sg = cube_tables(face)
    sc_sg, tc_sg, ma_sg = (t.to(dirs.dtype) for t in (sc_sg, tc_sg, ma_sg))
    sc = sc_sg * pick(dirs, sc_ax)
    tc = tc_sg * pick(dirs, tc_ax)
    ma = (ma_sg * pick(dirs, ma_ax)).clamp_min(EPS)  # > 0 except for the zero vector
    uv = torch.stack([0.5 * (sc / ma + 1.0), 0.5 * (tc / ma + 1.0)], dim=-1)
    duv = []
    for dd in dds:
        dsc = sc_sg * pick(dd, sc_ax)
        dtc = tc_sg * pick(dd, tc_ax)
        dma = ma_sg * pick(dd, ma_ax)
        duv.append(torch.stack([0.5 * (dsc * ma - sc * dma) / (ma * ma),
                                0.5 * (dtc * ma - tc * dma) / (ma * ma)], dim=-1))
    return (face, uv, duv[0], duv[1]) if duv else (face, uv)


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

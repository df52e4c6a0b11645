"""Closed-form test scenes for the filters: a textured ground plane seen at a grazing angle.

No rasterizer is involved: every pixel's ray is intersected with the plane
``y = 0`` analytically, and ``uv_dx`` / ``uv_dy`` are the exact derivatives
of that intersection with respect to the pixel column / row (DESIGN.md
section 2), so filter accuracy can be measured without screen-space
finite differences getting in the way.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor


def grazing_plane(
    res: int | Sequence[int] = 256,
    pitch_deg: float = 20.0,
    height: float = 1.0,
    *,
    fov_deg: float = 36.0,
    tile: float = 2.0,
    ss: int = 1,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """uv and exact uv derivatives of the ground plane seen by a pitched-down pinhole camera.

    The camera sits at ``(0, height, 0)`` looking along -z, pitched down by
    ``pitch_deg``; the plane ``y = 0`` carries ``uv = (x, -z) / tile`` (one
    texture repeat per ``tile`` world units, so use ``wrap="repeat"``).

    Args:
        res: image size, an int or (H, W).
        pitch_deg: angle between the view direction and the horizon, degrees.
        height: camera height above the plane, world units.
        fov_deg: vertical field of view, degrees. The default keeps the top
            row just below the horizon (pitch 20, fov 36: the top edge looks
            2 degrees down), so every pixel hits the plane.
        tile: world units per texture repeat.
        ss: supersampling factor; the result is the scene rendered at
            ``(H * ss, W * ss)``, i.e. the ss x ss sub-pixel centres of every
            pixel, so ``avg_pool2d(image, ss)`` box-filters them.
        dtype, device: of the returned tensors (computed in float64 first).

    Returns:
        ``(uv, uv_dx, uv_dy)``, each ``[1, H * ss, W * ss, 2]``; derivatives
        are per (sub-)pixel column / row of the returned grid. Pixels whose
        ray misses the plane (above the horizon) get NaN uv and zero
        derivatives.

    Not differentiable (a fixture). Raises ValueError on a non-positive
    size, ss, height, tile or fov.
    """
    H, W = (res, res) if isinstance(res, int) else tuple(int(r) for r in res)
    if H < 1 or W < 1 or ss < 1 or not height > 0 or not tile > 0 or not 0 < fov_deg < 180:
        raise ValueError(f"grazing_plane: expected res, ss, height, tile > 0 and 0 < fov_deg < 180, got "
                         f"res={res!r}, ss={ss}, height={height}, tile={tile}, fov_deg={fov_deg}")
    H, W = H * ss, W * ss
    f64 = torch.float64
    t = math.tan(math.radians(fov_deg) / 2)
    aspect = W / H
    r = torch.arange(H, dtype=f64, device=device).view(H, 1).expand(H, W)
    c = torch.arange(W, dtype=f64, device=device).view(1, W).expand(H, W)
    # Camera-space ray through the pixel centre (DESIGN.md: row 0 at NDC y = +1).
    x_ndc = (c + 0.5) / W * 2 - 1
    y_ndc = 1 - (r + 0.5) / H * 2
    dcam = torch.stack((x_ndc * t * aspect, y_ndc * t, -torch.ones_like(x_ndc)), -1)
    # d(ray)/d(column) and d(ray)/d(row) in camera space: constant vectors.
    ddc = torch.tensor([2 / W * t * aspect, 0.0, 0.0], dtype=f64, device=device)
    ddr = torch.tensor([0.0, -2 / H * t, 0.0], dtype=f64, device=device)
    p = math.radians(pitch_deg)
    # Pitch down: rotate about the x axis so that -z tilts towards -y.
    rot = torch.tensor([[1, 0, 0], [0, math.cos(p), math.sin(p)], [0, -math.sin(p), math.cos(p)]],
                       dtype=f64, device=device)
    d = dcam @ rot.T
    ddc, ddr = rot @ ddc, rot @ ddr
    dy = d[..., 1]
    hit = dy < 0
    dy_safe = torch.where(hit, dy, -torch.ones_like(dy))
    s = height / -dy_safe                            # ray parameter at y = 0
    P = d * s.unsqueeze(-1)                          # hit point, camera at origin in x, z
    # P = s d with s = -h / d_y: dP = s (dd - d * dd_y / d_y).
    def dP(dd: Tensor) -> Tensor:
        return s.unsqueeze(-1) * (dd - d * (dd[1] / dy_safe).unsqueeze(-1))
    def to_uv(q: Tensor) -> Tensor:
        return torch.stack((q[..., 0], -q[..., 2]), -1) / tile
    uv, uv_dx, uv_dy = to_uv(P), to_uv(dP(ddc)), to_uv(dP(ddr))
    miss = ~hit.unsqueeze(-1)
    uv = uv.masked_fill(miss, float("nan"))
    uv_dx = uv_dx.masked_fill(miss, 0.0)
    uv_dy = uv_dy.masked_fill(miss, 0.0)
    return tuple(x.unsqueeze(0).to(dtype) for x in (uv, uv_dx, uv_dy))  # type: ignore[return-value]


def checker_noise_texture(
    size: int = 1024,
    checks: int = 16,
    noise: float = 0.25,
    *,
    channels: int = 3,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """A checkerboard plus per-texel uniform noise, values in [0, 1], tiling seamlessly.

    Args:
        size: texels per side (square texture).
        checks: checker squares per side (even keeps the tiling seamless).
        noise: amplitude of the per-texel noise, added around the checker.
        channels: C; each channel gets its own noise and a tint.
        seed: of the noise generator (deterministic on CPU).

    Returns:
        [1, channels, size, size].
    """
    g = torch.Generator().manual_seed(seed)
    i = torch.arange(size)
    cell = max(size // max(checks, 1), 1)
    board = (((i.view(-1, 1) // cell) + (i.view(1, -1) // cell)) % 2).to(torch.float64)
    tint = torch.linspace(0.8, 1.0, channels, dtype=torch.float64).view(channels, 1, 1)
    base = 0.15 + 0.7 * board * tint
    n = (torch.rand((channels, size, size), generator=g, dtype=torch.float64) - 0.5) * noise
    tex = (base + n).clamp(0, 1)
    return tex.unsqueeze(0).to(dtype=dtype, device=device)
def checker_texture(size: int = 512, checks: int = 32, lo: float = 0.1, hi: float = 0.9,
                    channels: int = 3, dtype: torch.dtype = torch.float32) -> Tensor:
    """[1, C, size, size] texel image of the checker whose ideal form :func:`checker_footprint_mean` integrates.

    Texel (i, j) is ``hi`` where ``floor(i / cell) + floor(j / cell)`` is
    odd, ``lo`` elsewhere; cell = size / checks texels, so check edges lie on
    texel edges and mip levels up to log2(cell) are exact checkers too.
    """
    if size % checks:
        raise ValueError(f"checker_texture: size {size} must be a multiple of checks {checks}")
    i = torch.arange(size) // (size // checks)
    board = ((i.view(-1, 1) + i.view(1, -1)) % 2).to(torch.float64)
    return (lo + (hi - lo) * board).expand(channels, size, size).unsqueeze(0).to(dtype).contiguous()




def reflection_dirs(points: Tensor, points_dx: Tensor, points_dy: Tensor, normals: Tensor, normals_dx: Tensor,
                    normals_dy: Tensor, eye: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Mirror directions ``r = v - 2 (v . n) n`` of the view vectors about the normals, with their derivatives.

    Args:
        points, normals: [..., 3] surface points and normals (any length; normalised here), with
            their derivatives per pixel column / row ``*_dx``, ``*_dy`` [..., 3] (e.g. from
            ``difftex.interpolate(..., derivatives=True)``).
        eye: [3] or [..., 3] camera position; ``v`` is the unit vector from the eye to the point.

    Returns:
        ``(r, r_dx, r_dy)`` [..., 3]: unit reflected directions and their exact derivatives (the
        ``dirs_dx`` / ``dirs_dy`` of :func:`difftex.envmap.cubemap`). Differentiable in every input.
        Zero-length points or normals (background pixels) give finite values.
    """
    def unit(x: Tensor, dxs: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        n = x.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        u = x / n
        return u, [(d - u * (u * d).sum(-1, keepdim=True)) / n for d in dxs]

    v, dvs = unit(points - eye, [points_dx, points_dy])
    n, dns = unit(normals, [normals_dx, normals_dy])
    vn = (v * n).sum(-1, keepdim=True)
    r = v - 2 * vn * n
    drs = [dv - 2 * (((dv * n).sum(-1, keepdim=True) + (v * dn).sum(-1, keepdim=True)) * n + vn * dn)
           for dv, dn in zip(dvs, dns)]
    return r, drs[0], drs[1]


def mirror_sphere(eye, res: int, *, ss: int = 1, fov_deg: float = 30.0, subdivisions: int = 4,
                  dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """A unit mirror sphere at the origin seen from ``eye`` (looking at the origin, +y up), rasterized.

    Args:
        eye: camera position, a 3-sequence or [3] tensor (distance > 1).
        res: image size; ``ss``: supersampling (the image is rendered at res * ss, so that
            ``avg_pool2d(x, ss)`` box-filters the ss x ss sub-pixels of every pixel).
        fov_deg: vertical field of view; subdivisions: of the icosphere.

    Returns:
        ``(dirs, dirs_dx, dirs_dy, mask)``: [1, R, R, 3] reflected view directions (R = res * ss),
        their derivatives per (sub-)pixel column / row, and the coverage [1, R, R] bool. The
        normal is the interpolated position's direction (the sphere's exact normal at that
        point). Background pixels hold the view direction and zero derivatives.
    """
    import difftex
    from ..geometry import camera
    from .meshes import icosphere

    R = res * ss
    e = torch.as_tensor(eye, dtype=dtype)
    verts, faces = icosphere(subdivisions, dtype=dtype)
    proj = camera.perspective(fov_deg, 1.0, 0.1, float(e.norm()) + 2.0, degrees=True)
    mvp = proj @ camera.look_at(e, torch.zeros(3, dtype=dtype), torch.tensor([0.0, 1.0, 0.0], dtype=dtype))
    frags = difftex.rasterize(camera.transform(verts, mvp.unsqueeze(0)), faces, (R, R))
    p, pdx, pdy = difftex.interpolate(verts, faces, frags, derivatives=True)
    mask = frags.tri_id >= 0
    r, rdx, rdy = reflection_dirs(p, pdx, pdy, p, pdx, pdy, e)
    m = mask.unsqueeze(-1)
    # Background: the camera ray itself (a direction the environment can show behind the object).
    t = math.tan(math.radians(fov_deg) / 2)
    c = (torch.arange(R, dtype=dtype) + 0.5) / R * 2 - 1
    yy, xx = torch.meshgrid(-c * t, c * t, indexing="ij")
    fwd = -e / e.norm()
    right = torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0], dtype=dtype))
    right = right / right.norm()
    up = torch.linalg.cross(right, fwd)
    ray = (fwd + xx.unsqueeze(-1) * right + yy.unsqueeze(-1) * up).unsqueeze(0)
    return (torch.where(m, r, ray), torch.where(m, rdx, 0.0), torch.where(m, rdy, 0.0), mask)

"""Texture baking: evaluate a function of the surface point and normal at every texel of a mesh's uv atlas.

:func:`bake` rasterizes the mesh in uv space: the uv of each corner becomes
its clip-space position ``(2 u - 1, 1 - 2 v, 0, 1)``, so pixel ``(r, c)`` of
the rasterizer's ``size x size`` image samples NDC
``x = (c + 0.5) / size * 2 - 1``, ``y = 1 - (r + 0.5) / size * 2``, which is
uv ``((c + 0.5) / size, (r + 0.5) / size)``: the centre of texel ``(r, c)``
(DESIGN.md section 2). The barycentrics of that pixel then give the surface
point and the normal of the same uv, and ``difftex.sample`` reading the baked
texture at a texel centre returns exactly the value ``fn`` gave there.

:func:`ambient_occlusion` is the worked example: the cosine-weighted
fraction of directions in which a point sees the sky, from shadow maps
rendered by the same rasterizer.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import torch
from torch import Tensor

from .._checks import check_float, check_index, describe
from ..geometry import Mesh, interpolate, rasterize
from ..geometry.mesh import unit, vertex_normals

# Shadow maps rendered per rasterizer call in occlusion().
_VIEWS_PER_PASS = 8

__all__ = ["bake", "vertex_normals", "uv_clip_positions", "sphere_directions", "occlusion", "ambient_occlusion"]


def _check_mesh(mesh: object) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh: expected a difftex.Mesh, got {type(mesh).__name__}")
    check_float("mesh.positions", mesh.positions, ndim=2, last=3, shape_doc="[V, 3]")
    check_float("mesh.uv", mesh.uv, ndim=2, last=2, shape_doc="[T, 2]")
    return mesh


def _check_size(size: object) -> tuple[int, int]:
    pair = (size, size) if not isinstance(size, (tuple, list)) else tuple(size)
    if len(pair) != 2 or any(isinstance(s, bool) or not isinstance(s, int) for s in pair):
        raise TypeError(f"size: expected an int or an (H, W) pair of ints, got {size!r}")
    if min(pair) < 1:
        raise ValueError(f"size: expected positive texture sizes, got {size!r}")
    return pair  # type: ignore[return-value]


def _check_count(name: str, n: object, low: int) -> int:
    if isinstance(n, bool) or not isinstance(n, int) or n < low:
        raise ValueError(f"{name}: expected an int >= {low}, got {n!r}")
    return n


def uv_clip_positions(uv: Tensor) -> Tensor:
    """[T, 2] uv -> [T, 4] clip-space positions that rasterize texel (i, j) at pixel (i, j)."""
    uv = check_float("uv", uv, ndim=2, last=2, shape_doc="[T, 2]")
    u, v = uv.unbind(-1)
    return torch.stack((2 * u - 1, 1 - 2 * v, torch.zeros_like(u), torch.ones_like(u)), -1)


def _dilation_sources(mask: Tensor, steps: int) -> Tensor:
    """[H, W] int64 flat index of the covered texel that each texel copies, -1 for none.

    A brushfire: each of ``steps`` rounds lets an uncovered texel take, among
    the sources of itself and its 8 neighbours, the one nearest to it
    (Euclidean, in texels). Covered texels keep themselves, and after
    ``steps`` rounds every texel within ``steps`` texels (Chebyshev) of the
    chart has a source, the nearest one for convex charts.
    """
    H, W = mask.shape
    device = mask.device
    rows = torch.arange(H, device=device).view(H, 1).expand(H, W)
    cols = torch.arange(W, device=device).view(1, W).expand(H, W)
    src = torch.where(mask, rows * W + cols, torch.full_like(rows, -1))
    big = torch.iinfo(torch.int64).max
    for _ in range(steps):
        padded = torch.nn.functional.pad(src, (1, 1, 1, 1), value=-1)
        cand = torch.stack([padded[a:a + H, b:b + W] for a in range(3) for b in range(3)])  # [9, H, W]
        sr = torch.div(cand, W, rounding_mode="floor")
        sc = cand - sr * W
        dist = (sr - rows) ** 2 + (sc - cols) ** 2
        dist = torch.where(cand >= 0, dist, torch.full_like(dist, big))
        best = dist.argmin(0, keepdim=True)
        src = torch.gather(cand, 0, best).squeeze(0)
    return src


def bake(mesh: Mesh, fn: Callable[[Tensor, Tensor], Tensor], size: int | Sequence[int], *, dilate: int = 2,
         fill: float = 0.0, return_mask: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """Bake ``fn(points, normals)`` over a mesh's uv atlas into a 2D texture.

    Args:
        mesh: a :class:`difftex.Mesh` with uv (DESIGN.md convention). Its
            normals are interpolated where it has them, else the
            area-weighted :func:`vertex_normals` of its positions.
        fn: called once with ``points`` [N, 3] (object space, the surface
            point at each covered texel centre) and ``normals`` [N, 3]
            (unit); returns [N, C] or [N] float values.
        size: texture size, an int (square) or (H, W).
        dilate: texels outside every uv chart within this many texels of it
            take the value of the nearest covered texel, so that bilinear
            and mip-mapped reads near a seam do not blend in ``fill``.
        fill: value of the texels that are neither covered nor dilated.
        return_mask: also return the [H, W] bool mask of covered or dilated texels.

    Returns:
        [C, H, W] texture (``[1, H, W]`` for a [N] result): texel ``(i, j)``
        holds ``fn`` at the surface point of uv
        ``((j + 0.5) / W, (i + 0.5) / H)``, the point ``difftex.sample``
        reads there. Where uv charts overlap the lowest face index wins;
        uv outside [0, 1] is not wrapped (those parts are not baked).

    Gradients flow from the texture to whatever ``fn`` depends on (its
    parameters, and through ``points`` / ``normals`` to ``mesh.positions`` /
    ``mesh.normals``); the texel-to-triangle assignment is discrete. Raises
    TypeError / ValueError naming the argument on bad input or when ``fn``
    returns something other than [N, C] / [N] floats.
    """
    mesh = _check_mesh(mesh)
    H, W = _check_size(size)
    dilate = _check_count("dilate", dilate, 0)
    if isinstance(fill, bool) or not isinstance(fill, (int, float)):
        raise TypeError(f"fill: expected a number, got {type(fill).__name__}")
    if not callable(fn):
        raise TypeError(f"fn: expected a callable fn(points, normals), got {type(fn).__name__}")
    pos = mesh.positions
    # In the positions' dtype: float64 positions get float64 barycentrics.
    clip = uv_clip_positions(mesh.uv.detach().to(device=pos.device, dtype=pos.dtype))
    frags = rasterize(clip, mesh.uv_faces, (H, W))
    mask = frags.tri_id[0] >= 0
    points = interpolate(pos, mesh.uv_faces, frags, attr_faces=mesh.faces)[0][mask]
    if mesh.normals is not None:  # indexed by normal_faces, or like the positions (tangent_frames' rule)
        nf = mesh.normal_faces if mesh.normal_faces is not None else mesh.faces
        normals = interpolate(mesh.normals, mesh.uv_faces, frags, attr_faces=nf)[0][mask]
    else:
        normals = interpolate(vertex_normals(pos, mesh.faces), mesh.uv_faces, frags, attr_faces=mesh.faces)[0][mask]
    normals = unit(normals)
    values = fn(points, normals)
    if not isinstance(values, Tensor) or not values.is_floating_point():
        raise TypeError(f"fn: expected it to return a float tensor [N, C], got "
                        f"{describe(values) if isinstance(values, Tensor) else type(values).__name__}")
    n = points.shape[0]
    if values.dim() == 1:
        values = values.unsqueeze(1)
    if values.dim() != 2 or values.shape[0] != n:
        raise ValueError(f"fn: expected it to return [N, C] or [N] values for N = {n} points, got {describe(values)}")
    C = values.shape[1]
    flat_mask = mask.reshape(-1)
    dense = values.new_zeros((H * W, C)).index_put((flat_mask.nonzero().squeeze(1),), values)
    with torch.no_grad():
        src = _dilation_sources(mask, dilate).reshape(-1)
    have = src >= 0
    out = torch.where(have[:, None], dense[src.clamp(min=0)], values.new_tensor(float(fill)))
    out = out.t().reshape(C, H, W)
    return (out, have.view(H, W)) if return_mask else out


def sphere_directions(n: int, *, dtype: torch.dtype = torch.float32,
                      device: torch.device | str | None = None) -> Tensor:
    """[n, 3] unit directions spread evenly over the sphere (the Fibonacci lattice), deterministic."""
    n = _check_count("n", n, 1)
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / n
    r = torch.sqrt((1 - z * z).clamp(min=0))
    phi = k * math.pi * (3 - math.sqrt(5))
    return torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), -1).to(dtype=dtype, device=device)


def _frames(d: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors completing each direction of d [K, 3] to an orthonormal frame."""
    a = torch.where((d[:, :1].abs() < 0.9), d.new_tensor([1.0, 0.0, 0.0]), d.new_tensor([0.0, 1.0, 0.0]))
    e1 = unit(torch.linalg.cross(d, a))
    return e1, torch.linalg.cross(d, e1)


def occlusion(positions: Tensor, faces: Tensor, points: Tensor, normals: Tensor, *, directions: int | Tensor = 64,
              resolution: int = 256) -> Tensor:
    """Ambient visibility: the cosine-weighted fraction of directions in which a point is not occluded.

    For each direction ``d`` the mesh is rasterized orthographically as
    seen from ``d`` (a shadow map of ``resolution^2`` texels over its
    bounding sphere); a point is visible along ``d`` when it is no deeper
    than the shadow map's nearest surface at its texel, after a normal
    offset of one shadow texel (the shadow-map acne cure of normal-offset
    shadows). The result is
    ``sum_d max(n . d, 0) vis_d / sum_d max(n . d, 0)``.

    Args:
        positions: [V, 3] float, faces: [F, 3] integer: the occluders.
        points: [N, 3], normals: [N, 3] unit (same dtype as positions).
        directions: a number of Fibonacci-lattice directions over the
            sphere, or a [K, 3] tensor of unit directions.
        resolution: shadow-map size in texels.

    Returns:
        [N] visibility in [0, 1] (1 = open sky, 0 = fully occluded); 1 where
        no direction lies above the point's tangent plane.

    Not differentiable (visibility is a discrete test; computed without
    autograd). Raises TypeError / ValueError naming the argument on bad input.
    """
    positions = check_float("positions", positions, ndim=2, last=3, shape_doc="[V, 3]")
    faces = check_index("faces", faces, positions.shape[0], "number of vertices", positions.device)
    points = check_float("points", points, ndim=2, last=3, shape_doc="[N, 3]")
    normals = check_float("normals", normals, ndim=2, last=3, shape_doc="[N, 3]")
    if normals.shape != points.shape:
        raise ValueError(f"normals: expected the shape of points {tuple(points.shape)}, got {describe(normals)}")
    res = _check_count("resolution", resolution, 2)
    dtype, device = positions.dtype, positions.device
    if isinstance(directions, Tensor):
        d = check_float("directions", directions, ndim=2, last=3, shape_doc="[K, 3]").to(dtype=dtype, device=device)
        d = unit(d)
    else:
        d = sphere_directions(_check_count("directions", directions, 1), dtype=dtype, device=device)
    with torch.no_grad():
        points, normals = points.detach().to(dtype=dtype, device=device), normals.detach().to(dtype=dtype,
                                                                                             device=device)
        lo, hi = positions.amin(0), positions.amax(0)
        centre = (lo + hi) / 2
        radius = float((positions - centre).norm(dim=1).max()) * 1.01 + 1e-12
        texel = 2.0 / res  # one shadow texel, in NDC (and in radii)
        cos = normals @ d.t()  # [N, K]
        w = cos.clamp(min=0)
        seen = torch.zeros_like(cos[:, 0])
        offset = points + normals * (texel * radius)
        # A few views at a time: the shadow maps and the [views, N] lookups stay small.
        for a in range(0, d.shape[0], _VIEWS_PER_PASS):
            dk = d[a:a + _VIEWS_PER_PASS]
            e1, e2 = _frames(dk)
            basis = torch.stack((e1, e2, -dk), 1) / radius  # [k, 3, 3]: rows give clip x, y, z

            def clip(p: Tensor) -> Tensor:
                return torch.einsum("kij,nj->kni", basis, p - centre)

            verts = clip(positions)
            frags = rasterize(torch.cat((verts, torch.ones_like(verts[..., :1])), -1), faces, (res, res))
            depth = torch.where(frags.tri_id >= 0, frags.depth, torch.full_like(frags.depth, 4.0))
            q = clip(offset)  # [k, N, 3]
            col = ((q[..., 0] + 1) / 2 * res).floor().long().clamp(0, res - 1)
            row = ((1 - q[..., 1]) / 2 * res).floor().long().clamp(0, res - 1)
            view = torch.arange(dk.shape[0], device=device)[:, None]
            occ = depth[view, row, col]
            # The normal offset lifts a point h = 1 texel above its own plane, h / cos(angle) in depth, more than
            # the depth its plane changes within the half texel diagonal (0.71 texel * tan(angle)); the constant
            # half texel covers the rasterizer's float32 depth comparisons.
            visible = q[..., 2] <= occ + 0.5 * texel
            seen = seen + (w[:, a:a + _VIEWS_PER_PASS] * visible.t().to(dtype)).sum(1)
        total = w.sum(1)
        frac = (seen / torch.where(total > 0, total, torch.ones_like(total))).clamp(0, 1)
        return torch.where(total > 0, frac, torch.ones_like(total))


def ambient_occlusion(mesh: Mesh, size: int | Sequence[int], *, directions: int | Tensor = 64,
                      resolution: int = 256, dilate: int = 2) -> Tensor:
    """Bake an ambient-occlusion map: :func:`occlusion` of the mesh by itself at every texel.

    Args:
        mesh: a :class:`difftex.Mesh` with uv.
        size: texture size, int or (H, W).
        directions, resolution: as :func:`occlusion`.
        dilate: as :func:`bake`.

    Returns:
        [1, H, W] visibility in [0, 1]; multiply it into the ambient (or
        diffuse) shading. Not differentiable. Raises like :func:`bake`.
    """
    mesh = _check_mesh(mesh)

    def fn(points: Tensor, normals: Tensor) -> Tensor:
        return occlusion(mesh.positions, mesh.faces, points, normals, directions=directions, resolution=resolution)

    with torch.no_grad():
        return bake(mesh, fn, size, dilate=dilate)

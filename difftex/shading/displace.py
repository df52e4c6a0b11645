"""Displacement mapping (vertices actually move along their normals) and the midpoint subdivision that carries it."""
from __future__ import annotations

from typing import Union

import numpy as np
import torch
from torch import Tensor

from .._checks import broadcast_batch, check_float, check_index, check_same, describe
from ..geometry.mesh import Mesh
from ..texture.pyramid.mipmap import Mipmap
from ..texture.sample import sample
from ..texture.wrap import Wrap
from .common import operand, unit


def displace(
    pos: Tensor,
    normals: Tensor,
    height: Union[Tensor, Mipmap],
    uv: Tensor,
    scale: Union[float, Tensor] = 1.0,
    *,
    filter: str = "bilinear",
    wrap: Wrap = "repeat",
    border_value: float = 0.0,
) -> Tensor:
    """Move each vertex along its unit normal by the sampled height: ``pos + scale * h(uv) * normalize(n)``.

    Args:
        pos: [V, 3] or [B, V, 3] vertex positions.
        normals: [V, 3] or [B, V, 3] vertex normals (normalised here).
        height: [B, 1, H, W] height map (or a Mipmap; a mip filter is
            pointless without screen-space derivatives, so use "bilinear"
            or "bicubic").
        uv: [V, 2] or [B, V, 2] one uv per vertex (for a mesh with
            face-varying uv use ``Mesh.unified()``; seam copies of a
            vertex then move apart only where the height map differs
            across the seam).
        scale: a number or a tensor broadcasting to [B, V] (learnable).
        filter, wrap, border_value: as :func:`difftex.sample` (single-level
            filters).

    Returns:
        [B, V, 3] displaced positions (B = 1 when no input is batched).

    Differentiable with respect to pos, normals, the height map, uv and
    scale. Raises TypeError / ValueError naming the argument for non-float
    tensors, mismatched dtypes / devices, bad shapes, vertex counts that
    differ, a height map that is not one channel, batches that do not match
    and what ``sample`` rejects.
    """
    for name, t, k in (("pos", pos, 3), ("normals", normals, 3), ("uv", uv, 2)):
        check_float(name, t, (2, 3), last=k, shape_doc=f"[V, {k}] or [B, V, {k}]")
    check_same("normals", normals, "pos", pos)
    check_same("uv", uv, "pos", pos)
    base = height.levels[0] if isinstance(height, Mipmap) else height
    check_float("height", base, 4, shape_doc="[B, 1, H, W]")
    check_same("height", base, "pos", pos)
    if base.shape[1] != 1:
        raise ValueError(f"height: expected one channel [B, 1, H, W], got {describe(base)}")
    V = pos.shape[-2]
    for name, t in (("normals", normals), ("uv", uv)):
        if t.shape[-2] != V:
            raise ValueError(f"{name}: expected one row per vertex of pos ({V}), got {describe(t)}")
    batched = lambda t: t if t.dim() == 3 else t.unsqueeze(0)
    pos, normals, uv = batched(pos), batched(normals), batched(uv)
    s = operand("scale", scale, pos, "broadcasting to [B, V]", "pos")
    if s.dim() > 0:
        s = s.unsqueeze(-1)
    h = sample(height, uv.unsqueeze(1), filter=filter, wrap=wrap, border_value=border_value)  # [B, 1, 1, V]
    h = h[:, 0, 0, :, None]
    broadcast_batch(["pos", "normals", "uv", "height"], [pos.shape[0], normals.shape[0], uv.shape[0], h.shape[0]])
    return pos + s * h * unit(normals)


def _midpoint_subdivide(vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """One step of trimesh's 1-to-4 midpoint subdivision, with the new vertices computed by torch (differentiable).

    trimesh.remesh.subdivide gives the topology: its vertices are the old
    ones followed by one midpoint per unique edge, and old face (a, b, c)
    becomes [a, m_ab, m_ca], [m_ab, b, m_bc], [m_ca, m_bc, c], [m_ab, m_bc, m_ca];
    the midpoints' parents are read back from that pattern.
    """
    from trimesh.remesh import subdivide as tm_subdivide

    f_np = faces.detach().cpu().numpy()
    v_np = vertices.detach().cpu().numpy().astype(np.float64)
    new_v, new_f = tm_subdivide(v_np, f_np)
    n_old, n_new = vertices.shape[0], new_v.shape[0]
    quads = new_f.reshape(-1, 4, 3)
    if quads.shape[0] != f_np.shape[0] or not (quads[:, 0, 0] == f_np[:, 0]).all():
        raise RuntimeError("trimesh.remesh.subdivide changed its face layout; expected 4 faces per face in order")
    parents = np.zeros((n_new - n_old, 2), dtype=np.int64)
    for mid, (i, j) in ((quads[:, 0, 1], (0, 1)), (quads[:, 1, 2], (1, 2)), (quads[:, 0, 2], (2, 0))):
        parents[mid - n_old] = f_np[:, [i, j]]
    p = torch.as_tensor(parents, device=vertices.device)
    mids = 0.5 * (vertices[p[:, 0]] + vertices[p[:, 1]])
    if not np.allclose(mids.detach().cpu().numpy(), new_v[n_old:], atol=1e-5, rtol=1e-5):
        raise RuntimeError("trimesh.remesh.subdivide changed its vertex order; expected one midpoint per edge")
    return torch.cat([vertices, mids]), torch.as_tensor(new_f, dtype=torch.int64, device=faces.device)


def subdivide(mesh: Mesh, iterations: int = 1) -> Mesh:
    """Split every triangle into four at its edge midpoints, ``iterations`` times (trimesh's subdivision).

    Positions, face-varying uv and normals are subdivided on their own
    index lists, so uv seams stay seams; face ``4 f + k`` of the result lies
    in face ``f`` of the input. Midpoint normals are renormalised. A coarse
    mesh subdivided this way has enough vertices to carry
    :func:`displace`.

    Args:
        mesh: a :class:`difftex.Mesh`.
        iterations: number of 1-to-4 steps, an integer >= 0 (faces grow 4x each).

    Returns:
        A new Mesh; the new vertices are midpoints computed with torch,
        so they are differentiable with respect to the input's fields.

    Raises TypeError for a mesh that is no Mesh, ValueError for a negative
    or non-integer ``iterations``.
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh: expected a difftex.Mesh, got {type(mesh).__name__}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        raise ValueError(f"iterations: expected an integer >= 0, got {iterations!r}")
    pos, faces, uv, uvf, nrm, nf = (mesh.positions, mesh.faces, mesh.uv, mesh.uv_faces, mesh.normals,
                                    mesh.normal_faces)
    check_index("faces", faces, pos.shape[0], "number of positions", pos.device)
    for _ in range(iterations):
        pos, new_faces = _midpoint_subdivide(pos, faces)
        uv, uvf = _midpoint_subdivide(uv, uvf)
        if nrm is not None:
            nrm, nf = _midpoint_subdivide(nrm, nf if nf is not None else faces)
            nrm = unit(nrm)
        faces = new_faces
    return Mesh(pos, faces, uv, uvf, nrm, nf)


__all__ = ["displace", "subdivide"]

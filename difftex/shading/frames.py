"""Tangent frames from uv: per-vertex tangents with handedness, and the per-pixel orthonormal frame.

Tangent space is (T, B, N): T points along increasing u, B along
increasing v (DESIGN.md: v runs down the texture rows), N is the surface
normal. A tangent-space vector (x, y, z) is ``x T + y B + z N`` in world
space. Per vertex only T and a handedness ``w = +-1`` are stored (the glTF /
MikkTSpace layout): ``B = w * cross(N, T)``. With DESIGN.md's v-down uv an
ordinary (unmirrored, counter-clockwise) chart has ``w = -1`` and a
mirrored one ``w = +1``; the bump and normal-map formulas hold for both.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import torch
from torch import Tensor

from .._checks import check_float, check_index, check_same
from ..geometry.interpolate import interpolate
from ..geometry.mesh import vertex_normals
from ..geometry.raster import Fragments
from .common import dot, unit


def _any_perpendicular(n: Tensor) -> Tensor:
    """A unit vector perpendicular to each unit ``n`` (the fallback tangent where uv give none)."""
    ex = torch.zeros_like(n)
    ex[..., 0] = 1
    ey = torch.zeros_like(n)
    ey[..., 1] = 1
    # Cross with the axis least parallel to n: never near zero.
    axis = torch.where(n[..., :1].abs() < 0.9, ex, ey)
    return unit(torch.cross(n, axis, dim=-1))


def orthonormal_tangents(tangent: Tensor, normal: Tensor) -> Tensor:
    """Unit tangents ``T - N (N.T)`` (Gram-Schmidt against unit ``normal``); where none is left, any perpendicular."""
    t = tangent - normal * dot(normal, tangent)
    norm2 = dot(t, t)
    ok = norm2 > 1e-12 * dot(tangent, tangent).clamp_min(torch.finfo(t.dtype).tiny)
    return torch.where(ok, unit(t), _any_perpendicular(normal))


class TangentFrames(NamedTuple):
    """Per-vertex tangent frames of :func:`tangent_frames`.

    Fields:
        tangents: [N, 4]: xyz the unit tangent (along increasing u,
            orthogonal to the normal), w the handedness +-1
            (``B = w * cross(normal, tangent)``).
        normals: [N, 3] unit normals.
        faces: [F, 3] int64 rows of ``tangents`` / ``normals`` per face
            corner: one row per distinct (position, uv, normal) corner, so a
            vertex on a uv seam has one frame per side.
    """

    tangents: Tensor
    normals: Tensor
    faces: Tensor

    def at(self, frags: Fragments, faces: Tensor) -> Tensor:
        """The per-pixel frames [B, H, W, 3, 3] (rows T, B, N) of the rasterized mesh.

        ``faces`` is the [F, 3] position index given to rasterize (it fixes
        F); the frames are interpolated with the barycentrics and
        re-orthonormalised by :func:`surface_frames`. Background pixels get
        a finite frame (N = 0 rows are replaced by a fallback basis).
        """
        t = interpolate(self.tangents, faces, frags, attr_faces=self.faces)
        n = interpolate(self.normals, faces, frags, attr_faces=self.faces)
        return surface_frames(t, n)


def tangent_frames(pos: Tensor, faces: Tensor, uv: Tensor, normals: Optional[Tensor] = None,
                   uv_faces: Optional[Tensor] = None, *, normal_faces: Optional[Tensor] = None) -> TangentFrames:
    """Per-vertex tangent frames from the uv parameterisation (Lengyel's method, angle-weighted).

    Each triangle's tangent and bitangent solve ``e1 = du1 T + dv1 B``,
    ``e2 = du2 T + dv2 B`` for its edges e and uv differences; they are
    normalised and summed at each corner weighted by the corner angle
    (MikkTSpace's weighting), then T is orthogonalised against the vertex
    normal and ``w = sign(cross(N, T) . B_sum)`` (+1 where zero). Corners
    are grouped by their (position, uv, normal) indices: a vertex on a uv
    seam (``load_mesh`` keeps the OBJ's face-varying uv) gets one frame per
    side, so mirrored or separately laid out charts keep their own tangent
    and handedness. Triangles with degenerate uv add nothing; a vertex
    with no tangent left gets an arbitrary one perpendicular to N.

    Args:
        pos: [V, 3] float positions; faces: [F, 3] integer indices into pos.
        uv: [T, 2] texture coordinates (DESIGN.md convention).
        normals: [V, 3] vertex normals (or [Nn, 3] with ``normal_faces``);
            None computes :func:`vertex_normals`.
        uv_faces: [F, 3] indices into uv (face-varying uv, ``Mesh.uv_faces``);
            None: uv is per vertex, indexed by ``faces``.
        normal_faces: [F, 3] indices into normals (``Mesh.normal_faces``);
            None: normals are indexed by ``faces``.

    Returns:
        :class:`TangentFrames` (tangents [N, 4], normals [N, 3], faces [F, 3]).
        Differentiable with respect to pos, uv and normals (the grouping is
        not).

    Raises TypeError / ValueError naming the argument for non-float or
    mismatched dtypes / devices, bad shapes or out-of-range indices.
    """
    check_float("pos", pos, 2, last=3, shape_doc="[V, 3]")
    check_float("uv", uv, 2, last=2, shape_doc="[T, 2]")
    check_same("uv", uv, "pos", pos)
    dev = pos.device
    faces = check_index("faces", faces, pos.shape[0], "number of positions", dev)
    F = faces.shape[0]

    def index(name: str, idx: Optional[Tensor], rows: int, what: str) -> Tensor:
        if idx is None:
            if rows != pos.shape[0]:
                raise ValueError(f"{name}: required when {what} has {rows} rows and pos {pos.shape[0]}; expected "
                                 f"[F, 3] = [{F}, 3] indices into {what}")
            return faces
        idx = check_index(name, idx, rows, f"rows of {what}", dev)
        if idx.shape[0] != F:
            raise ValueError(f"{name}: expected one row per face [F, 3] = [{F}, 3], got shape {tuple(idx.shape)}")
        return idx

    uvf = index("uv_faces", uv_faces, uv.shape[0], "uv")
    if normals is None:
        if normal_faces is not None:
            raise ValueError("normal_faces: given without normals; expected normals [N, 3] with it, or neither")
        normals = vertex_normals(pos, faces)
    check_float("normals", normals, 2, last=3, shape_doc="[V, 3]")
    check_same("normals", normals, "pos", pos)
    nf = index("normal_faces", normal_faces, normals.shape[0], "normals")

    # index_select, not pos[faces]: shared vertices would get their gradient terms summed by atomics in a
    # run-dependent order (DESIGN.md, "determinism").
    p = pos.index_select(0, faces.reshape(-1)).view(-1, 3, 3)  # [F, 3, 3]
    t = uv.index_select(0, uvf.reshape(-1)).view(-1, 3, 2)  # [F, 3, 2]
    # Per corner k: edges to the next two corners (k+1, k+2), so every corner sees its own angle.
    nxt, prv = [1, 2, 0], [2, 0, 1]
    e1, e2 = p[:, nxt] - p, p[:, prv] - p
    d1, d2 = t[:, nxt] - t, t[:, prv] - t
    det = d1[..., 0] * d2[..., 1] - d2[..., 0] * d1[..., 1]  # [F, 3] (the same for the 3 corners up to rounding)
    ok = det.abs() > 1e-12 * (d1.abs().sum(-1) * d2.abs().sum(-1)).clamp_min(torch.finfo(det.dtype).tiny)
    safe = torch.where(ok, det, torch.ones_like(det)).unsqueeze(-1)
    tan = (e1 * d2[..., 1:] - e2 * d1[..., 1:]) / safe
    bit = (e2 * d1[..., :1] - e1 * d2[..., :1]) / safe
    # The corner angle from atan2(|e1 x e2|, e1.e2): acos' gradient is infinite at degenerate corners.
    cr = torch.cross(e1, e2, dim=-1)
    angle = torch.atan2(torch.sqrt(dot(cr, cr).squeeze(-1) + torch.finfo(cr.dtype).tiny), dot(e1, e2).squeeze(-1))
    weight = torch.where(ok, angle, torch.zeros_like(angle)).unsqueeze(-1)
    tan = unit(tan) * weight
    bit = unit(bit) * weight

    # One row per distinct (position, uv, normal) corner, numbered by first use.
    key = torch.stack([faces.reshape(-1), uvf.reshape(-1), nf.reshape(-1)], dim=1)
    uniq, inverse = torch.unique(key, dim=0, return_inverse=True)
    n_rows = uniq.shape[0]
    first = torch.full((n_rows,), inverse.numel(), dtype=torch.int64, device=dev)
    first.scatter_reduce_(0, inverse, torch.arange(inverse.numel(), device=dev), reduce="amin")
    order = torch.argsort(first)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(n_rows, device=dev)
    rows = rank[inverse]
    uniq = uniq[order]

    t_sum = torch.zeros(n_rows, 3, dtype=pos.dtype, device=dev).index_add(0, rows, tan.reshape(-1, 3))
    b_sum = torch.zeros(n_rows, 3, dtype=pos.dtype, device=dev).index_add(0, rows, bit.reshape(-1, 3))
    n = unit(normals.index_select(0, uniq[:, 2]))  # rows may share a normal: index_select, as above
    t_out = orthonormal_tangents(t_sum, n)
    w = torch.where(dot(torch.cross(n, t_out, dim=-1), b_sum) < 0, -1.0, 1.0).to(pos.dtype)
    return TangentFrames(torch.cat([t_out, w], dim=-1), n, rows.reshape(F, 3))


def surface_frames(tangents: Tensor, normals: Tensor) -> Tensor:
    """Orthonormal frames [..., 3, 3] (rows T, B, N) from interpolated tangents [..., 4] and normals [..., 3].

    N is normalised, T orthogonalised against it (Gram-Schmidt) and
    normalised, ``B = sign(w) * cross(N, T)`` (w >= 0 counts as +1). A zero
    normal (background pixels) gets N = 0 and a finite T, B; nothing is NaN.
    Differentiable with respect to both. Raises TypeError / ValueError
    naming the argument for bad dtypes, last dimensions or shapes that do
    not broadcast.
    """
    check_float("tangents", tangents, last=4, shape_doc="[..., 4]")
    check_float("normals", normals, last=3, shape_doc="[..., 3]")
    check_same("normals", normals, "tangents", tangents)
    try:
        torch.broadcast_shapes(tangents.shape[:-1], normals.shape[:-1])
    except RuntimeError:
        raise ValueError(f"tangents {tuple(tangents.shape)} and normals {tuple(normals.shape)} do not broadcast "
                         "(expected [..., 4] and [..., 3] over the same points)") from None
    n = unit(normals)
    t = orthonormal_tangents(tangents[..., :3], n)
    sign = torch.where(tangents[..., 3:] < 0, -1.0, 1.0).to(n.dtype)
    b = sign * torch.cross(n.expand_as(t), t, dim=-1)
    return torch.stack(torch.broadcast_tensors(t, b, n), dim=-2)


__all__ = ["TangentFrames", "tangent_frames", "surface_frames", "vertex_normals", "orthonormal_tangents"]

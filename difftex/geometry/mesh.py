"""The mesh type: positions, faces and face-varying uv (and normals) as tensors."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from .._checks import check_float, check_index


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh with face-varying uv (and optionally normals).

    Fields:
        positions: [V, 3] float.
        faces: [F, 3] int64 indices into ``positions``.
        uv: [T, 2] float, DESIGN.md convention (v down, already flipped).
        uv_faces: [F, 3] int64 indices into ``uv``; corner ``k`` of face
            ``f`` has texture coordinate ``uv[uv_faces[f, k]]``.
        normals: [N, 3] float or None when the file has none.
        normal_faces: [F, 3] int64 indices into ``normals`` or None.
    """

    positions: torch.Tensor
    faces: torch.Tensor
    uv: torch.Tensor
    uv_faces: torch.Tensor
    normals: Optional[torch.Tensor] = None
    normal_faces: Optional[torch.Tensor] = None

    def to(self, device=None, dtype: Optional[torch.dtype] = None) -> "Mesh":
        """Copy to ``device``; ``dtype`` applies to the float fields only."""

        def f(t):
            return None if t is None else t.to(device=device, dtype=dtype)

        def i(t):
            return None if t is None else t.to(device=device)

        return Mesh(f(self.positions), i(self.faces), f(self.uv), i(self.uv_faces),
                    f(self.normals), i(self.normal_faces))

    def corner_uv(self) -> torch.Tensor:
        """[F, 3, 2] uv of every face corner (``uv[uv_faces]``)."""
        return self.uv[self.uv_faces]

    def unified(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Split vertices at uv seams so one index list serves both attributes.

        Returns:
            positions [N, 3], uv [N, 2], faces [F, 3] int64 with one vertex per
            distinct (position index, uv index) pair, in order of first use.
            For spot that is 3225 vertices, the same count trimesh produces.
        """
        pairs = torch.stack([self.faces.reshape(-1), self.uv_faces.reshape(-1)], dim=1)
        uniq, inverse = torch.unique(pairs, dim=0, return_inverse=True)
        # torch.unique sorts; renumber by first use so the order is stable and readable.
        n = uniq.shape[0]
        first = torch.full((n,), inverse.numel(), dtype=torch.int64, device=inverse.device)
        first.scatter_reduce_(0, inverse, torch.arange(inverse.numel(), device=inverse.device),
                              reduce="amin")
        order = torch.argsort(first)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(n, device=order.device)
        uniq = uniq[order]
        faces = rank[inverse].reshape(-1, 3)
        return self.positions[uniq[:, 0]], self.uv[uniq[:, 1]], faces



def unit(x: Tensor) -> Tensor:
    """``x / |x|`` along the last axis; a zero vector stays zero, with a zero gradient (no NaN, no inf).

    ``|x|`` comes from the squares in one pass: exact to rounding for lengths
    within about ``[1e-18, 1e18]`` in float32 (``[1e-153, 1e153]`` in float64).
    Outside that range the squares leave the dtype's normal numbers: the
    result stays finite, but a short vector comes out off unit length (by
    1 % at 1e-22 in float32, more below) or zero, and a long one zero.
    """
    length = x.norm(dim=-1, keepdim=True)
    ok = length > 0
    # The inner where keeps the division finite where the outer one discards it.
    return torch.where(ok, x / torch.where(ok, length, torch.ones_like(length)), torch.zeros_like(x))


def vertex_normals(positions: Tensor, faces: Tensor) -> Tensor:
    """Area-weighted vertex normals: the normalised sum of the adjacent faces' cross products.

    Args:
        positions: [V, 3] float. faces: [F, 3] integer, counter-clockwise
            seen from the side the normals point to.

    Returns:
        [V, 3] unit normals (zero for a vertex with no face of non-zero area).

    Differentiable with respect to ``positions``. Raises TypeError /
    ValueError naming the argument on bad dtypes, shapes or indices.
    """
    positions = check_float("positions", positions, ndim=2, last=3, shape_doc="[V, 3]")
    faces = check_index("faces", faces, positions.shape[0], "number of vertices", positions.device)
    # index_select, not positions[faces]: a vertex is shared by several faces, and the CPU backward of
    # advanced indexing sums their terms with atomics in a run-dependent order (DESIGN.md, "determinism").
    p = positions.index_select(0, faces.reshape(-1)).view(-1, 3, 3)  # [F, 3, 3]
    fn = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # length = 2 * area
    n = torch.zeros_like(positions).index_add(0, faces.reshape(-1), fn.repeat_interleave(3, dim=0))
    return unit(n)

"""The painter's algorithm: triangles sorted by depth and drawn back to front (the z-buffer's foil).

Each triangle is drawn whole over what was drawn before, in the order of
one depth per triangle. That order does not always exist: two triangles
that pierce each other, or three that overlap in a cycle, have no order
that is right in every pixel, and the painter gets some pixels wrong where
the z-buffer (one depth per pixel) gets them right. It is here to show
that, not to be used for rendering: it is O(F H W).
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from .._checks import check_index
from .raster import Fragments, rasterize

__all__ = ["painter", "SORT_KEYS"]

#: How :func:`painter` ranks triangles: by the mean or by the farthest NDC z of their corners.
SORT_KEYS = ("mean", "farthest")
# Triangles drawn per rasterize call (one per batch element): bounds the
# memory at about this many [H, W] fragment layers.
_CHUNK = 64


def painter(
    pos: Tensor,
    faces: Tensor,
    resolution: Sequence[int],
    *,
    sort: str = "farthest",
    cull_backfaces: bool = False,
) -> Fragments:
    """Rasterize with the painter's algorithm instead of a z-buffer.

    Args:
        pos: [B, V, 4] or [V, 4] clip-space positions, as for
            :func:`difftex.rasterize`.
        faces: [F, 3] integer vertex indices.
        resolution: (H, W) in pixels, the pixel centres of rasterize.
        sort: "farthest" (the classic order: by the largest NDC z of the
            corners) or "mean" (by the mean NDC z of the corners). Equal
            keys keep the lower face index in front.
        cull_backfaces: drop clockwise triangles, as rasterize does.

    Returns:
        :class:`difftex.Fragments` like rasterize's (tri_id -1 on
        background), where each pixel holds the last triangle drawn over
        it: coverage, fill rule and near / far clipping are rasterize's,
        triangle by triangle; only the visibility rule differs.

    ``bary``, ``depth``, ``bary_dx``, ``bary_dy`` are differentiable with
    respect to ``pos`` like rasterize's; the order is not. Corners with
    w <= 0 rank as farthest (the key is meant for scenes in front of the
    eye). Raises ValueError naming ``sort`` on an unknown key, and what
    rasterize raises on bad ``pos``, ``faces`` or ``resolution``.
    """
    if sort not in SORT_KEYS:
        raise ValueError(f"sort must be one of {SORT_KEYS}, got {sort!r}")
    # An empty rasterize checks pos and resolution with rasterize's words
    # and gives the background canvas.
    frags = rasterize(pos, torch.zeros((0, 3), dtype=torch.int64), resolution, cull_backfaces=cull_backfaces)
    if pos.dim() == 2:
        pos = pos.unsqueeze(0)
    faces = check_index("faces", faces, pos.shape[1], "number of vertices", pos.device)
    B, F = pos.shape[0], faces.shape[0]
    corners = pos[:, faces]  # [B, F, 3, 4]
    with torch.no_grad():
        w = corners[..., 3]
        z = torch.where(w > 0, corners[..., 2] / torch.where(w > 0, w, torch.ones_like(w)),
                        torch.full_like(w, float("inf")))
        key = z.amax(-1) if sort == "farthest" else z.mean(-1)
        # Back to front: far keys first; among equal keys the higher index
        # first, so that the lower index is drawn last and stays in front
        # (rasterize's tie rule).
        order = F - 1 - torch.argsort(key.flip(-1), dim=-1, descending=True, stable=True)
    one = torch.tensor([[0, 1, 2]], device=pos.device)
    tri_id, bary, depth, bdx, bdy = frags.tri_id, frags.bary, frags.depth, frags.bary_dx, frags.bary_dy
    H, W = frags.resolution
    for s in range(0, F, _CHUNK):
        k = order[:, s:s + _CHUNK]  # [B, n] in drawing order
        n = k.shape[1]
        tris = torch.gather(corners, 1, k[..., None, None].expand(B, n, 3, 4))
        part = rasterize(tris.reshape(B * n, 3, 4), one, (H, W), cull_backfaces=cull_backfaces)
        cover = part.tri_id.view(B, n, H, W) >= 0
        # Overwriting in drawing order = the last covering triangle wins.
        step = torch.arange(1, n + 1, device=pos.device).view(1, n, 1, 1)
        last = (cover * step).amax(1)  # [B, H, W], 0 = none of this chunk
        hit = last > 0
        j = (last - 1).clamp_min(0)

        def pick(t: Tensor) -> Tensor:
            t = t.view(B, n, H, W, *t.shape[3:])
            idx = j.view(B, 1, H, W, *([1] * (t.dim() - 4))).expand(B, 1, H, W, *t.shape[4:])
            return torch.gather(t, 1, idx).squeeze(1)

        m3 = hit[..., None]
        tri_id = torch.where(hit, torch.gather(k, 1, j.view(B, -1)).view(B, H, W), tri_id)
        bary = torch.where(m3, pick(part.bary), bary)
        depth = torch.where(hit, pick(part.depth), depth)
        bdx = torch.where(m3, pick(part.bary_dx), bdx)
        bdy = torch.where(m3, pick(part.bary_dy), bdy)
    return Fragments(tri_id=tri_id, bary=bary, depth=depth, bary_dx=bdx, bary_dy=bdy)

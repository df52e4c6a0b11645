"""A float64 ray cast of clip-space triangles: the reference the rasterizer's triangle ids are measured against.

Independent of ``difftex.geometry.raster`` (no fixed point, no edge
functions, no fill rule): every triangle is projected to NDC in float64 and
intersected with the ray through each pixel centre along +z (Moller &
Trumbore 1997, edges inclusive); the nearest hit wins, a tie goes to the
lowest triangle id. Every corner must have w > 0 (a scene in front of the
camera). Used by tests/geometry and experiments/studies/raster_accuracy.py.
"""
from __future__ import annotations

import torch
from torch import Tensor

_CHUNK = 1 << 21  # candidate (triangle, pixel) pairs per step


def ray_cast(pos: Tensor, faces: Tensor, resolution: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Nearest triangle through every pixel centre: (ids [H, W] int64, -1 = miss; NDC depth [H, W] float64, inf = miss).

    Args:
        pos: [V, 4] clip-space positions (any float dtype; cast to float64),
            every w > 0.
        faces: [F, 3] int64.
        resolution: (H, W); pixel (r, c) is at NDC x = (c + 0.5) / W * 2 - 1,
            y = 1 - (r + 0.5) / H * 2, as rasterize's.

    Raises ValueError where some w <= 0. Not differentiable.
    """
    H, W = resolution
    pos = pos.detach().to(torch.float64)
    if not bool((pos[:, 3] > 0).all()):
        raise ValueError("ray_cast: every vertex needs w > 0 (a scene in front of the camera)")
    ndc = pos[:, :3] / pos[:, 3:]
    p = ndc[faces]  # [F, 3, 3]
    # Pixel range of each triangle's NDC bounding box, a hair wider: edges are inclusive.
    lo, hi = p.amin(1), p.amax(1)
    eps = 1e-9
    c0 = torch.ceil((lo[:, 0] + 1) * (W / 2) - 0.5 - eps).clamp(0, W).long()
    c1 = torch.floor((hi[:, 0] + 1) * (W / 2) - 0.5 + eps).clamp(-1, W - 1).long()
    r0 = torch.ceil((1 - hi[:, 1]) * (H / 2) - 0.5 - eps).clamp(0, H).long()
    r1 = torch.floor((1 - lo[:, 1]) * (H / 2) - 0.5 + eps).clamp(-1, H - 1).long()
    bw, bh = (c1 - c0 + 1).clamp(min=0), (r1 - r0 + 1).clamp(min=0)
    n = bw * bh
    best = torch.full((H * W,), float("inf"), dtype=torch.float64)
    ids = torch.full((H * W,), torch.iinfo(torch.int64).max, dtype=torch.int64)
    tri_all = torch.nonzero(n > 0).squeeze(1)
    cum = torch.cumsum(n[tri_all], 0)
    start = 0
    while start < len(tri_all):
        base = int(cum[start - 1]) if start else 0
        stop = int(torch.searchsorted(cum, base + _CHUNK, right=True))
        stop = max(stop, start + 1)
        tri = tri_all[start:stop]
        cnt = n[tri]
        rep = torch.repeat_interleave(torch.arange(len(tri)), cnt)
        k = torch.arange(len(rep)) - (torch.cumsum(cnt, 0) - cnt)[rep]
        t = tri[rep]
        col = c0[t] + k % bw[t]
        row = r0[t] + torch.div(k, bw[t], rounding_mode="floor")
        x = (col.double() + 0.5) / W * 2 - 1
        y = 1 - (row.double() + 0.5) / H * 2
        v0, v1, v2 = p[t, 0], p[t, 1], p[t, 2]
        e1, e2 = v1 - v0, v2 - v0
        # Ray o = (x, y, -2), d = (0, 0, 1): pvec = d x e2, qvec = (o - v0) x e1.
        pvec = torch.stack((-e2[:, 1], e2[:, 0], torch.zeros_like(x)), 1)
        det = (e1 * pvec).sum(1)
        o = torch.stack((x, y, torch.full_like(x, -2.0)), 1)
        tv = o - v0
        ok = det != 0
        inv = 1 / torch.where(ok, det, torch.ones_like(det))
        u = (tv * pvec).sum(1) * inv
        q = torch.linalg.cross(tv, e1)
        v = q[:, 2] * inv
        depth = (e2 * q).sum(1) * inv - 2
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (depth >= -1) & (depth <= 1)
        pix = (row * W + col)[hit]
        z, f = depth[hit], t[hit]
        best.scatter_reduce_(0, pix, z, "amin")
        win = z == best[pix]
        ids.scatter_reduce_(0, pix[win], f[win], "amin")
        start = stop
    ids = torch.where(torch.isinf(best), -1, ids)
    return ids.view(H, W), best.view(H, W)


def plane_depth(pos: Tensor, faces: Tensor, tri: Tensor, rows: Tensor, cols: Tensor,
                resolution: tuple[int, int]) -> Tensor:
    """Float64 NDC depth of the planes of triangles ``tri`` [N] at pixel centres (rows, cols) [N]."""
    H, W = resolution
    pos = pos.detach().to(torch.float64)
    p = (pos[:, :3] / pos[:, 3:])[faces[tri]]  # [N, 3, 3]
    x = (cols.double() + 0.5) / W * 2 - 1
    y = 1 - (rows.double() + 0.5) / H * 2
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return p[:, 0, 2] - (n[:, 0] * (x - p[:, 0, 0]) + n[:, 1] * (y - p[:, 0, 1])) / n[:, 2]


def edge_distance(pos: Tensor, faces: Tensor, tri: Tensor, rows: Tensor, cols: Tensor,
                  resolution: tuple[int, int]) -> Tensor:
    """Distance in pixels from pixel centres (rows, cols) [N] to the nearest edge line of triangles ``tri`` [N]."""
    H, W = resolution
    pos = pos.detach().to(torch.float64)
    ndc = pos[:, :2] / pos[:, 3:]
    q = torch.stack(((ndc[:, 0] + 1) * (W / 2), (1 - ndc[:, 1]) * (H / 2)), -1)[faces[tri]]  # pixel units
    pt = torch.stack((cols.double() + 0.5, rows.double() + 0.5), -1)[:, None]
    a, b = q, q.roll(-1, 1)
    d = b - a
    cross = d[..., 0] * (pt[..., 1] - a[..., 1]) - d[..., 1] * (pt[..., 0] - a[..., 0])
    return (cross.abs() / d.norm(dim=-1).clamp(min=1e-300)).amin(1)


def exact_bary(pos: Tensor, faces: Tensor, tri_id: Tensor, resolution: tuple[int, int]) -> Tensor:
    """Float64 perspective-correct barycentrics of triangles ``tri_id`` [H, W] (-1: none) at the pixel centres.

    The reference rasterize's barycentrics are measured against (see
    :func:`exact_bary_at`). ``pos`` [V, 4] (any float dtype, cast to
    float64), every w > 0 at the triangles named. Returns [H, W, 3] float64,
    zeros where ``tri_id`` < 0. Not differentiable.
    """
    H, W = resolution
    flat = tri_id.reshape(-1)
    pix = torch.nonzero(flat >= 0).squeeze(1)
    rows, cols = torch.div(pix, W, rounding_mode="floor"), pix % W
    x = (cols.double() + 0.5) / W * 2 - 1
    y = 1 - (rows.double() + 0.5) / H * 2
    out = torch.zeros(H * W, 3, dtype=torch.float64)
    out[pix] = exact_bary_at(pos, faces, flat[pix], x, y)
    return out.view(H, W, 3)


def exact_bary_at(pos: Tensor, faces: Tensor, tri: Tensor, x: Tensor, y: Tensor) -> Tensor:
    """Float64 perspective-correct barycentrics [N, 3] of triangles ``tri`` [N] at NDC points (x, y) [N].

    Written independently of rasterize's homogeneous edge functions: the
    corners are projected to NDC in float64, the screen-space barycentrics
    come from the 2D cross products of the corners taken relative to the
    point (so no large terms cancel: the error is about 1e-16 over the
    triangle's size in NDC), and the perspective correction divides each by
    its corner's w. ``pos`` [V, 4] (any float dtype, cast to float64), every
    w > 0 at the triangles named. Not differentiable.
    """
    pos = pos.detach().to(torch.float64)
    v = pos[faces[tri]]  # [N, 3, 4]
    dx = v[..., 0] / v[..., 3] - x.double()[:, None]
    dy = v[..., 1] / v[..., 3] - y.double()[:, None]
    dxj, dyj, dxk, dyk = dx.roll(-1, 1), dy.roll(-1, 1), dx.roll(-2, 1), dy.roll(-2, 1)
    lam = (dxj * dyk - dyj * dxk) / v[..., 3]  # screen-space weight over w: perspective-correct up to a factor
    return lam / lam.sum(1, keepdim=True)

"""Scenes that defeat the painter's algorithm, and a brute-force float64 visibility reference.

Shared by ``tests/geometry/test_painter.py`` and
``experiments/studies/painter_foil.py`` (the figure in the README).
Positions are clip space with w = 1 (an orthographic view), so NDC = clip.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["intersecting_triangles", "cyclic_triangles", "brute_force_ids"]


def intersecting_triangles(dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """Two triangles that pierce each other: each is nearer on one side of x = 0.

    Returns pos [6, 4] (clip space, w = 1) and faces [2, 3]. Both have the
    same farthest and mean corner depth, so no depth order per triangle is
    right on both halves of their overlap.
    """
    pos = torch.tensor([
        [-0.8, -0.7, -0.6, 1.0], [0.8, -0.5, 0.6, 1.0], [0.05, 0.8, 0.0, 1.0],
        [-0.8, 0.5, 0.6, 1.0], [0.8, 0.7, -0.6, 1.0], [-0.05, -0.8, 0.0, 1.0],
    ], dtype=dtype)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    return pos, faces


def cyclic_triangles(dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """Three long triangles along the sides of an equilateral triangle, each over the next (a cycle).

    Bar i runs along side i and recedes along its length (NDC z grows from
    -0.6 to 0.6), so where bar i's far end crosses bar i + 1's near end,
    bar i + 1 is in front: 1 over 0, 2 over 1 and 0 over 2. Returns pos
    [9, 4] (clip space, w = 1) and faces [3, 3].
    """
    rows = []
    near_len, far_len, half_width, apothem = 0.7, 0.9, 0.24, 0.28
    for i in range(3):
        a = math.radians(90 + 120 * i)
        mx, my = apothem * math.cos(a), apothem * math.sin(a)  # middle of side i
        dx, dy = -math.sin(a), math.cos(a)  # along the side
        nx, ny = math.cos(a), math.sin(a)  # across it
        sx, sy = mx - near_len * dx, my - near_len * dy  # the wide, near end
        rows += [[sx - half_width * nx, sy - half_width * ny, -0.6, 1.0],
                 [sx + half_width * nx, sy + half_width * ny, -0.6, 1.0],
                 [mx + far_len * dx, my + far_len * dy, 0.6, 1.0]]
    return torch.tensor(rows, dtype=dtype), torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])


def brute_force_ids(pos: Tensor, faces: Tensor, resolution: tuple[int, int]) -> Tensor:
    """[H, W] int64 nearest triangle at every pixel centre, -1 for none: every triangle tested, float64.

    For positions with w = 1 (orthographic): 2D barycentrics of the pixel
    centre in each triangle, inside where all three are >= 0, depth from
    them; the smallest depth wins. Independent of the rasterizer's code
    (no fill rule: keep pixel centres off the edges).
    """
    H, W = resolution
    p = pos.detach().to(torch.float64).cpu()
    if not bool((p[:, 3] == 1).all()):
        raise ValueError("brute_force_ids: expected w = 1 at every vertex (an orthographic scene)")
    x = (torch.arange(W, dtype=torch.float64) + 0.5) / W * 2 - 1
    y = 1 - (torch.arange(H, dtype=torch.float64) + 0.5) / H * 2
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    best = torch.full((H, W), float("inf"), dtype=torch.float64)
    ids = torch.full((H, W), -1, dtype=torch.int64)
    for f, (i, j, k) in enumerate(faces.tolist()):
        (x0, y0, z0), (x1, y1, z1), (x2, y2, z2) = p[i, :3].tolist(), p[j, :3].tolist(), p[k, :3].tolist()
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0:
            continue
        b1 = ((xx - x0) * (y2 - y0) - (x2 - x0) * (yy - y0)) / area
        b2 = ((x1 - x0) * (yy - y0) - (xx - x0) * (y1 - y0)) / area
        b0 = 1 - b1 - b2
        z = b0 * z0 + b1 * z1 + b2 * z2
        win = (b0 >= 0) & (b1 >= 0) & (b2 >= 0) & (z >= -1) & (z <= 1) & (z < best)
        best = torch.where(win, z, best)
        ids = torch.where(win, torch.full_like(ids, f), ids)
    return ids

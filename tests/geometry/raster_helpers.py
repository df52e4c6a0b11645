"""Shared fixtures for the rasterizer / interpolation / camera tests."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from difftex import camera
from difftex.testing import SPOT_MESH

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@functools.lru_cache(maxsize=None)
def spot_trimesh():
    import trimesh

    # process=False keeps the file's face order, so ids compare one to one.
    return trimesh.load(str(SPOT_MESH), process=False, force="mesh")


def view_matrix(azim_deg: float, elev_deg: float, dist: float, center=(0.0, 0.0, 0.0), fov_deg: float = 45.0,
                near: float = 0.1, far: float = 10.0, dtype=torch.float64):
    """Eye position, view and projection matrices orbiting ``center``."""
    a, e = math.radians(azim_deg), math.radians(elev_deg)
    c = torch.tensor(center, dtype=dtype)
    eye = c + dist * torch.tensor([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)], dtype=dtype)
    view = camera.look_at(eye, c, (0.0, 1.0, 0.0), dtype=dtype)
    proj = camera.perspective(fov_deg, 1.0, near, far, degrees=True, dtype=dtype)
    return eye, view, proj


def pixel_rays(mvp: torch.Tensor, H: int, W: int):
    """Ray origins on the near plane and unit directions through every pixel centre.

    Returns numpy arrays [H * W, 3] in row-major pixel order (row 0 = top).
    """
    inv = torch.linalg.inv(mvp.to(torch.float64))
    xs = (torch.arange(W, dtype=torch.float64) + 0.5) / W * 2 - 1
    ys = 1 - (torch.arange(H, dtype=torch.float64) + 0.5) / H * 2
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    pts = []
    for z in (-1.0, 1.0):
        ndc = torch.stack((x, y, torch.full_like(x, z), torch.ones_like(x)), -1).reshape(-1, 4)
        p = ndc @ inv.T
        pts.append(p[:, :3] / p[:, 3:])
    d = pts[1] - pts[0]
    d = d / d.norm(dim=-1, keepdim=True)
    return pts[0].numpy(), d.numpy()


def ray_cast(mesh, mvp: torch.Tensor, H: int, W: int):
    """trimesh reference: (tri_id [H, W] int64 with -1, hit locations [H, W, 3])."""
    origins, dirs = pixel_rays(mvp, H, W)
    tri, ray, loc = mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    ids = np.full(H * W, -1, dtype=np.int64)
    hits = np.full((H * W, 3), np.nan)
    ids[ray] = tri
    hits[ray] = loc
    return ids.reshape(H, W), hits.reshape(H, W, 3)


def random_rotation(gen: torch.Generator, dtype=torch.float64) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=dtype))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q

"""Meshes and data files shared by the tests and the experiments: the icosphere and the spot cow."""
from __future__ import annotations

import torch
from torch import Tensor

from difftex.io.files import DATA_DIR, data_path

# In the repository's data/ folder: present in a source checkout, not in a wheel.
SPOT_MESH = DATA_DIR / "spot" / "spot_triangulated.obj"
SPOT_TEXTURE = DATA_DIR / "spot" / "spot_texture.png"


def icosphere(subdivisions: int = 4, *, radius: float = 1.0, dtype: torch.dtype = torch.float32,
              device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
    """An icosphere centred at the origin (trimesh's construction), counter-clockwise seen from outside.

    Args:
        subdivisions: times each triangle is split in four; 20 * 4^subdivisions faces.
        radius: of the sphere (every vertex lies on it).
        dtype, device: of the positions.

    Returns:
        ``(positions [V, 3], faces [F, 3] int64)``. Not differentiable (a fixture).

    Raises:
        ValueError: a negative ``subdivisions`` or a non-positive ``radius``.
    """
    if int(subdivisions) != subdivisions or subdivisions < 0 or not radius > 0:
        raise ValueError(f"icosphere: expected an integer subdivisions >= 0 and radius > 0, got "
                         f"subdivisions={subdivisions!r}, radius={radius!r}")
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=float(radius))
    return (torch.tensor(m.vertices, dtype=dtype, device=device),
            torch.tensor(m.faces, dtype=torch.int64, device=device))


def spot_mesh():
    """The spot cow (5,856 triangles, one uv chart) as a :class:`difftex.Mesh`. Raises FileNotFoundError outside a checkout."""
    import difftex

    return difftex.load_mesh(data_path("spot/spot_triangulated.obj"))


def spot_texture() -> Tensor:
    """The spot texture, [1, 3, 1024, 1024] float32 in [0, 1]. Raises FileNotFoundError outside a checkout."""
    import difftex

    return difftex.load_texture(data_path("spot/spot_texture.png"))

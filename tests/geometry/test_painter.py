"""painter: the seed's foil. Right where a depth order exists, wrong on intersecting and cyclic triangles."""
from __future__ import annotations

import pytest
import torch

import difftex
from difftex import painter, rasterize
from difftex.geometry.painter import SORT_KEYS
from difftex.testing.visibility import brute_force_ids, cyclic_triangles, intersecting_triangles

RES = (96, 96)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("sort", SORT_KEYS)
@pytest.mark.parametrize("scene, wrong", [(intersecting_triangles, 781), (cyclic_triangles, 264)])
def test_painter_fails_where_the_z_buffer_does_not(scene, wrong, sort, dtype):
    pos, faces = scene(dtype)
    truth = brute_force_ids(pos, faces, RES)
    z = rasterize(pos, faces, RES).tri_id[0]
    p = painter(pos, faces, RES, sort=sort).tri_id[0]
    # Same coverage (both draw every triangle), different winners.
    assert torch.equal(p >= 0, truth >= 0)
    assert int((z != truth).sum()) == 0
    # Counted once at 96x96: about half the overlap of the two pierced
    # triangles, two of the three crossings of the cycle.
    assert int((p != truth).sum()) == wrong


def test_painter_equals_the_z_buffer_where_an_order_exists():
    # Three parallel triangles at distinct depths, given out of order.
    base = torch.tensor([[-0.7, -0.6], [0.6, -0.5], [0.0, 0.7]], dtype=torch.float64)
    pos = torch.cat([torch.cat([base + s, torch.full((3, 1), z), torch.ones(3, 1, dtype=torch.float64)], 1)
                     for s, z in ((0.1, 0.2), (-0.13, -0.4), (0.21, 0.6))])
    faces = torch.arange(9).view(3, 3)
    ref = rasterize(pos, faces, (40, 40))
    got = painter(pos, faces, (40, 40))
    assert torch.equal(got.tri_id, ref.tri_id)
    for name in ("bary", "depth", "bary_dx", "bary_dy"):
        assert torch.allclose(getattr(got, name), getattr(ref, name), atol=1e-12), name


def test_ties_keep_the_lower_face_in_front_and_batches_sort_apart():
    # Two coplanar copies of one triangle: rasterize's tie rule (lower id) holds.
    pos = torch.tensor([[-0.7, -0.6, 0.1, 1], [0.6, -0.5, 0.1, 1], [0.0, 0.7, 0.1, 1]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 1, 2]])
    assert set(painter(pos, faces, (16, 16)).tri_id.unique().tolist()) == {-1, 0}
    # Batch: per-view orders (the z of view 1 is flipped, so the other triangle wins there).
    two = torch.cat([pos, pos + torch.tensor([0.05, 0.02, 0.3, 0], dtype=torch.float64)])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    views = torch.stack([two, two * torch.tensor([1, 1, -1, 1], dtype=torch.float64)])
    got = painter(views, faces, (24, 24))
    ref = rasterize(views, faces, (24, 24))
    assert torch.equal(got.tri_id, ref.tri_id)
    assert got.tri_id[0, 12, 12] == 0 and got.tri_id[1, 12, 12] == 1


def test_gradients_reach_the_positions_and_interpolate_accepts_it():
    pos, faces = intersecting_triangles()
    pos = pos.clone().requires_grad_(True)
    frags = painter(pos, faces, (24, 24))
    attr = torch.arange(12, dtype=torch.float64).view(6, 2)
    val = difftex.interpolate(attr, faces, frags)
    val.sum().backward()
    assert torch.isfinite(pos.grad).all() and pos.grad.abs().sum() > 0


def test_bad_input_raises():
    pos, faces = intersecting_triangles()
    with pytest.raises(ValueError, match=r"sort must be one of \('mean', 'farthest'\), got 'nearest'"):
        painter(pos, faces, RES, sort="nearest")
    with pytest.raises(ValueError, match=r"faces indices must lie in \[0, 5\]"):
        painter(pos, faces + 1, RES)
    with pytest.raises(ValueError, match=r"pos must have shape \[B, V, 4\]"):
        painter(pos[:, :3], faces, RES)
    with pytest.raises(ValueError, match="resolution must be positive"):
        painter(pos, faces, (0, 4))

"""displace and subdivide: each vertex moves by the sampled height along its normal; gradients; bad input."""
import pytest
import torch
import torch.nn.functional as F

from difftex import Mesh
from difftex.shading import displace, subdivide


def _square(dtype=torch.float64):
    """The unit square on z = 0 as two triangles whose uv are face-varying (a seam along the diagonal)."""
    pos = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=dtype)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uv = torch.tensor([[0, 1], [1, 1], [1, 0], [0, 1], [1, 0], [0, 0]], dtype=dtype)  # v = 1 - y
    return Mesh(pos, faces, uv, torch.tensor([[0, 1, 2], [3, 4, 5]]))


def test_subdivided_plane_moves_each_vertex_by_the_sampled_height():
    m = subdivide(_square(), 3)
    assert m.faces.shape == (2 * 4 ** 3, 3) and m.positions.shape == (81, 3)
    # Face-varying uv stay consistent with the positions corner by corner (uv = (x, 1 - y) on every face).
    torch.testing.assert_close(m.uv[m.uv_faces], torch.stack([m.positions[m.faces][..., 0],
                                                              1 - m.positions[m.faces][..., 1]], -1))
    pos, uv, faces = Mesh(m.positions, m.faces, m.uv, m.uv_faces).unified()
    g = torch.Generator().manual_seed(0)
    height = torch.rand(1, 1, 8, 8, dtype=torch.float64, generator=g)
    normals = torch.tensor([0, 0, 1.0], dtype=torch.float64).expand_as(pos)
    out = displace(pos, normals, height, uv, 0.3, wrap="clamp")
    # The reference: torch's grid_sample (align_corners=False, border padding is clamp).
    ref = F.grid_sample(height, (2 * uv - 1)[None, None], align_corners=False, padding_mode="border")[0, 0, 0]
    torch.testing.assert_close(out[0, :, 2], 0.3 * ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(out[0, :, :2], pos[:, :2], atol=0, rtol=0)
    # The corner (0, 0) reads the clamped corner texel: a hand value.
    corner = int(((pos - torch.tensor([0, 1.0, 0], dtype=torch.float64)).norm(dim=-1) < 1e-12).nonzero())
    assert float(out[0, corner, 2]) == pytest.approx(0.3 * float(height[0, 0, 0, 0]), abs=1e-12)


def test_displacement_along_tilted_normals_and_batches(device):
    f = dict(dtype=torch.float64, device=device)
    pos = torch.rand(5, 3, **f)
    n = torch.randn(2, 5, 3, **f)
    uv = torch.rand(5, 2, **f)
    h = torch.rand(2, 1, 4, 4, **f)
    scale = torch.tensor([[0.5], [2.0]], **f)
    out = displace(pos, n, h, uv, scale)
    for b in range(2):
        hv = F.grid_sample(h[b:b + 1], (2 * uv - 1)[None, None], align_corners=False)  # zeros never reached: wrap
        unit = n[b] / n[b].norm(dim=-1, keepdim=True)
        want = pos + scale[b] * hv[0, 0, 0, :, None] * unit
        inner = ((uv > 1 / 8) & (uv < 7 / 8)).all(-1)  # away from the edge, where repeat and zero padding differ
        torch.testing.assert_close(out[b][inner], want[inner], atol=1e-12, rtol=0)


def test_gradcheck_displace_and_subdivide():
    g = torch.Generator().manual_seed(1)
    r = lambda *s: torch.rand(*s, dtype=torch.float64, generator=g).requires_grad_()
    pos, n, h, uv, s = r(4, 3), r(4, 3), r(1, 1, 3, 3), r(4, 2), r(())
    assert torch.autograd.gradcheck(lambda *a: displace(*a, filter="bicubic"), (pos, n, h, uv, s))
    m = _square()
    p = m.positions.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p: subdivide(Mesh(p, m.faces, m.uv, m.uv_faces), 1).positions, (p,))


def test_bad_input():
    pos = torch.rand(4, 3)
    with pytest.raises(ValueError, match=r"height: expected one channel \[B, 1, H, W\]"):
        displace(pos, pos, torch.rand(1, 3, 4, 4), torch.rand(4, 2))
    with pytest.raises(ValueError, match=r"normals: expected one row per vertex of pos \(4\)"):
        displace(pos, torch.rand(5, 3), torch.rand(1, 1, 4, 4), torch.rand(4, 2))
    with pytest.raises(ValueError, match=r"uv: expected last dimension 2"):
        displace(pos, pos, torch.rand(1, 1, 4, 4), torch.rand(4, 3))
    with pytest.raises(TypeError, match=r"height: expected dtype torch.float32 like pos"):
        displace(pos, pos, torch.rand(1, 1, 4, 4, dtype=torch.float64), torch.rand(4, 2))
    with pytest.raises(ValueError, match=r"batch sizes do not match \(pos 2, normals 3"):
        displace(torch.rand(2, 4, 3), torch.rand(3, 4, 3), torch.rand(1, 1, 4, 4), torch.rand(4, 2))
    with pytest.raises(ValueError, match=r"iterations: expected an integer >= 0, got -1"):
        subdivide(_square(), -1)
    with pytest.raises(TypeError, match=r"mesh: expected a difftex.Mesh, got tuple"):
        subdivide((pos, None), 1)

"""tangent_frames: orthonormal, along the uv gradient on a plane and a sphere, seams and mirrored charts."""
import math

import pytest
import torch

import difftex
from difftex.shading import surface_frames, tangent_frames, vertex_normals
from tests.shading.helpers import grid_plane, uv_sphere


def _check_orthonormal(fr, tol=1e-12):
    t, w, n = fr.tangents[:, :3], fr.tangents[:, 3], fr.normals
    torch.testing.assert_close(t.norm(dim=-1), torch.ones_like(w), atol=tol, rtol=0)
    torch.testing.assert_close(n.norm(dim=-1), torch.ones_like(w), atol=tol, rtol=0)
    assert (t * n).sum(-1).abs().max() < tol
    assert set(w.tolist()) <= {-1.0, 1.0}


@pytest.mark.parametrize("A", [[[2.0, 0.5], [-0.3, 1.5]], [[0.0, -1.0], [1.0, 0.0]], [[-1.0, 0.2], [0.1, 3.0]]],
                         ids=["sheared", "rotated", "mirrored"])
def test_plane_frames_follow_the_uv_gradient(A):
    pos, faces = grid_plane(5)
    A = torch.tensor(A, dtype=torch.float64)
    uv = pos[:, :2] @ A.T + 0.25
    fr = tangent_frames(pos, faces, uv)
    _check_orthonormal(fr)
    # P(uv) = A^-1 (uv - 0.25): dP/du, dP/dv are the columns of A^-1 (in the plane z = 0).
    Ainv = torch.linalg.inv(A)
    dpdu = torch.cat([Ainv[:, 0], torch.zeros(1, dtype=torch.float64)])
    dpdv = torch.cat([Ainv[:, 1], torch.zeros(1, dtype=torch.float64)])
    torch.testing.assert_close(fr.normals, torch.tensor([0, 0, 1.0], dtype=torch.float64).expand_as(fr.normals))
    torch.testing.assert_close(fr.tangents[:, :3], (dpdu / dpdu.norm()).expand(len(fr.normals), 3))
    b = fr.tangents[:, 3:] * torch.cross(fr.normals, fr.tangents[:, :3], dim=-1)
    assert ((b @ dpdv) > 0).all()  # B on dP/dv's side: the handedness is right
    assert (fr.tangents[:, 3] == torch.sign(torch.det(A))).all()  # uv mirrored against (x, y): w = -1


def test_sphere_frames_follow_the_uv_gradient_across_the_seam():
    pos, faces, uv, uv_faces, ang = uv_sphere()
    fr = tangent_frames(pos, faces, uv, pos, uv_faces)  # exact normals
    _check_orthonormal(fr)
    # One frame per (position, uv) pair: the 14 seam positions and both poles' columns get extra rows.
    pairs = torch.unique(torch.stack([faces.reshape(-1), uv_faces.reshape(-1)], 1), dim=0)
    assert fr.tangents.shape[0] == pairs.shape[0]
    rows_pos = torch.zeros(fr.tangents.shape[0], dtype=torch.int64)
    rows_pos[fr.faces.reshape(-1)] = faces.reshape(-1)
    rows_uv = torch.zeros_like(rows_pos)
    rows_uv[fr.faces.reshape(-1)] = uv_faces.reshape(-1)
    th, ph = ang[rows_pos, 0], ang[rows_pos, 1]
    inner = (th > 0) & (th < math.pi)
    seam = (uv[rows_uv, 0] == 0) | (uv[rows_uv, 0] == 1)
    assert int((seam & inner).sum()) == 2 * 15  # both sides of the seam keep their own frame
    e_phi = torch.stack([-ph.sin(), ph.cos(), torch.zeros_like(ph)], -1)
    e_th = torch.stack([th.cos() * ph.cos(), th.cos() * ph.sin(), -th.sin()], -1)
    cos_t = (fr.tangents[:, :3] * e_phi).sum(-1)
    # Away from the seam the ring's symmetry makes the averaged chord tangents exact; on the seam each side
    # averages only its own triangles, whose chords lie up to half a column (180 / 32 degrees) off e_phi
    # (5.5 degrees next to the poles, 0 on the equator, where the chords above and below cancel).
    assert cos_t[inner & ~seam].min() > 1 - 1e-12
    half = math.radians(180 / 32)
    assert cos_t[inner & seam].min() > math.cos(half)
    assert cos_t[inner & seam].max() > 1 - 1e-9
    b = fr.tangents[:, 3:] * torch.cross(fr.normals, fr.tangents[:, :3], dim=-1)
    assert (b * e_th).sum(-1)[inner & ~seam].min() > 1 - 1e-12
    assert (b * e_th).sum(-1)[inner & seam].min() > math.cos(half) - 1e-3
    assert torch.isfinite(fr.tangents).all()


def test_vertex_normals_and_surface_frames():
    pos, faces, *_ = uv_sphere(8, 16)
    n = vertex_normals(pos, faces)
    assert ((n * pos).sum(-1) > 0.99).all()  # outward on a counter-clockwise sphere
    g = torch.Generator().manual_seed(1)
    t = torch.randn(2, 3, 4, dtype=torch.float64, generator=g)
    nn = torch.randn(2, 3, 3, dtype=torch.float64, generator=g)
    f = surface_frames(t, nn)
    eye = torch.eye(3, dtype=torch.float64).expand(2, 3, 3, 3)
    torch.testing.assert_close(f @ f.transpose(-1, -2), eye)
    torch.testing.assert_close(f[..., 2, :], nn / nn.norm(dim=-1, keepdim=True))
    assert ((torch.linalg.det(f) > 0) == (t[..., 3] >= 0)).all()  # rows T, B, N: det = sign(w)
    # Background pixels (zero tangent and normal) stay finite.
    assert torch.isfinite(surface_frames(torch.zeros(4), torch.zeros(3))).all()
    assert torch.autograd.gradcheck(surface_frames, (t.requires_grad_(), nn.requires_grad_()))


def test_frames_at_rasterized_pixels():
    pos, faces = grid_plane(3, torch.float32)
    uv = pos[:, :2] * torch.tensor([1.0, -1.0]) + torch.tensor([0.0, 1.0])  # v down as y goes up
    fr = tangent_frames(pos, faces, uv)
    clip = torch.cat([pos[:, :2] * 1.6 - 0.8, torch.zeros(len(pos), 1), torch.ones(len(pos), 1)], -1)
    frags = difftex.rasterize(clip[None], faces, (8, 8))
    frames = fr.at(frags, faces)
    inside = frags.tri_id[0] >= 0
    want = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]])
    torch.testing.assert_close(frames[0][inside], want.expand(int(inside.sum()), 3, 3))
    assert torch.isfinite(frames).all()


def test_bad_input():
    pos, faces = grid_plane(3)
    uv = pos[:, :2]
    with pytest.raises(ValueError, match=r"uv_faces: required when uv has 4 rows and pos 9"):
        tangent_frames(pos, faces, uv[:4])
    with pytest.raises(TypeError, match=r"uv: expected dtype torch.float64 like pos"):
        tangent_frames(pos, faces, uv.float())
    with pytest.raises(ValueError, match=r"faces indices must lie in \[0, 8\]"):
        tangent_frames(pos, faces + 1, uv)
    with pytest.raises(ValueError, match=r"uv_faces: expected one row per face"):
        tangent_frames(pos, faces, uv, uv_faces=faces[:3])
    with pytest.raises(ValueError, match=r"normals: expected last dimension 3"):
        tangent_frames(pos, faces, uv, torch.zeros(9, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"tangents \(2, 4\) and normals \(3, 3\) do not broadcast"):
        surface_frames(torch.zeros(2, 4), torch.zeros(3, 3))


def test_spot_frames_split_at_the_obj_seams_and_follow_each_face():
    from difftex.testing import spot_mesh

    m = spot_mesh().to(dtype=torch.float64)
    fr = tangent_frames(m.positions, m.faces, m.uv, m.normals, m.uv_faces, normal_faces=m.normal_faces)
    # The file has no normals: one frame per (position, uv) pair, Mesh.unified()'s 3225 (trimesh's count).
    assert m.normals is None and fr.tangents.shape == (3225, 4)
    _check_orthonormal(fr)
    p, uv = m.positions[m.faces], m.uv[m.uv_faces]
    e1, e2, d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = (d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1])[:, None]
    face_t = (e1 * d2[:, 1:] - e2 * d1[:, 1:]) / det
    face_b = (e2 * d1[:, :1] - e1 * d2[:, :1]) / det
    corner_t = fr.tangents[fr.faces]
    cos = (corner_t[..., :3] * (face_t / face_t.norm(dim=-1, keepdim=True))[:, None]).sum(-1)
    # Measured: median 0.996, 97% of corners above 0.9 (the rest sit where the chart bends sharply).
    assert cos.median() > 0.99 and (cos > 0.9).double().mean() > 0.95
    b = corner_t[..., 3:] * torch.cross(fr.normals[fr.faces], corner_t[..., :3], dim=-1)
    assert ((b * face_b[:, None]).sum(-1) > 0).double().mean() > 0.99  # handedness: B on dP/dv's side

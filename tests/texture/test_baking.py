"""Texture baking: surface points at texel centres, dilation across seams, ambient occlusion, baked solid textures."""
import numpy as np
import pytest
import torch

import difftex
from difftex import Mesh
from difftex.metrics import psnr
from difftex.testing.meshes import icosphere, spot_mesh
from difftex.testing.suite import spot_mvp
from difftex.texture.baking import ambient_occlusion, bake, occlusion, sphere_directions, vertex_normals
from difftex.texture.noise import marble


def _identity(points, normals):
    return points


def _plane(dtype=torch.float64, lo=0.25, hi=0.75):
    """A quad whose uv covers [lo, hi]^2, positions an affine map of uv (so the truth is closed form)."""
    uv = torch.tensor([[lo, lo], [hi, lo], [hi, hi], [lo, hi]], dtype=dtype)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return Mesh(_affine(uv), faces, uv, faces)


def _affine(uv):
    u, v = uv.unbind(-1)
    return torch.stack((3 * u - 1, 2 * v + 0.5 * u, 0.25 * u - v), -1)


def _texel_centres(H, W, dtype=torch.float64):
    i, j = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    return torch.stack(((j + 0.5) / W, (i + 0.5) / H), -1)


def test_plane_identity_is_the_surface_at_texel_centres(dtype):
    S = 16
    tex, mask = bake(_plane(dtype), _identity, S, dilate=0, return_mask=True)
    assert tex.shape == (3, S, S) and tex.dtype == dtype and mask.shape == (S, S)
    uv = _texel_centres(S, S, dtype)
    inside = ((uv > 0.25) & (uv < 0.75)).all(-1)
    assert torch.equal(mask, inside)  # texel centres exactly inside [0.25, 0.75]^2 (none on the edge)
    want = _affine(uv)[mask]
    err = (tex.permute(1, 2, 0)[mask] - want).norm(dim=-1)
    # Half a texel in object space is 0.5 / S times the longest axis of the Jacobian, here > 3 / (2 S).
    assert float(err.max()) < (1e-5 if dtype == torch.float32 else 1e-12)
    assert torch.all(tex[:, ~mask] == 0)
    # The texel difftex.sample reads at a texel centre is that texel.
    got = difftex.sample(tex.unsqueeze(0), uv.unsqueeze(0), filter="bilinear", wrap="clamp")[0]
    assert torch.allclose(got[:, mask], tex[:, mask], atol=1e-6 if dtype == torch.float32 else 1e-12)


def test_dilation_copies_the_nearest_covered_texel():
    S, N = 16, 2
    tex, have = bake(_plane(), _identity, S, dilate=N, return_mask=True)
    covered = bake(_plane(), _identity, S, dilate=0, return_mask=True)[1]
    ci, cj = torch.nonzero(covered, as_tuple=True)
    ring = have & ~covered
    assert int(ring.sum()) == (8 + 2 * N) ** 2 - 8 ** 2  # an 8x8 chart grown by N texels on every side
    # The affine map is invertible: recover the texel each dilated texel copied from its value.
    p = tex.permute(1, 2, 0)[ring]
    u = (p[:, 0] + 1) / 3
    v = (p[:, 1] - 0.5 * u) / 2
    src_j, src_i = torch.round(u * S - 0.5), torch.round(v * S - 0.5)
    ri, rj = torch.nonzero(ring, as_tuple=True)
    d_src = (src_i - ri) ** 2 + (src_j - rj) ** 2
    d_min = ((ci[None] - ri[:, None]) ** 2 + (cj[None] - rj[:, None]) ** 2).amin(1)
    assert torch.equal(d_src, d_min.double())
    assert covered[src_i.long(), src_j.long()].all()
    assert torch.all(tex[:, ~have] == 0)
    filled = bake(_plane(), _identity, S, dilate=N, fill=-7.0)
    assert torch.all(filled[:, ~have] == -7.0)


def test_spot_identity_against_ray_casting_in_uv():
    """trimesh casts rays through the uv layout at texel centres: its hit triangle and barycentrics give the truth."""
    trimesh = pytest.importorskip("trimesh")
    mesh = spot_mesh().to(dtype=torch.float64)
    S = 32
    tex, mask = bake(mesh, _identity, S, dilate=0, return_mask=True)
    uv, uvf = mesh.uv.numpy(), mesh.uv_faces.numpy()
    flat = trimesh.Trimesh(np.c_[uv, np.zeros(len(uv))], uvf, process=False)
    ii, jj = np.nonzero(mask.numpy())
    assert len(ii) > 0.4 * S * S
    org = np.c_[(jj + 0.5) / S, (ii + 0.5) / S, np.ones(len(ii))]
    loc, ray, tri = flat.ray.intersects_location(org, np.tile([0.0, 0.0, -1.0], (len(ii), 1)), multiple_hits=False)
    assert len(ray) >= len(ii) - 2  # every covered texel centre hits the layout (a ray may slip through an edge)
    bary = trimesh.triangles.points_to_barycentric(flat.triangles[tri], loc)
    corners = mesh.positions.numpy()[mesh.faces.numpy()[tri]]
    ref = (bary[:, :, None] * corners).sum(1)
    got = tex.numpy()[:, ii[ray], jj[ray]].T
    err = np.linalg.norm(got - ref, axis=1)
    # Half a texel in object space, per triangle: 0.5 / S times the largest singular value of d(position)/d(uv).
    tuv = flat.triangles[tri][:, :, :2]
    duv = np.stack((tuv[:, 1] - tuv[:, 0], tuv[:, 2] - tuv[:, 0]), -1)  # [n, 2, 2]
    dp = np.stack((corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), -1)  # [n, 3, 2]
    jac = dp @ np.linalg.inv(duv)
    half_texel = 0.5 / S * np.linalg.norm(jac, ord=2, axis=(1, 2))
    assert np.all(err < half_texel)
    assert err.max() < 1e-9  # in fact the same point to rounding
    # Dilation on spot's real seams: covered texels unchanged, every texel of the 2-texel ring copies a covered
    # texel at most 2 texels away (Chebyshev), and nothing beyond the ring is written.
    dil, have = bake(mesh, _identity, S, dilate=2, return_mask=True)
    assert torch.equal(dil[:, mask], tex[:, mask])
    near = torch.nn.functional.max_pool2d(mask[None, None].double(), 5, stride=1, padding=2)[0, 0] > 0
    assert torch.equal(have, near)
    windows = torch.nn.functional.unfold(tex[None], 5, padding=2).view(3, 25, S, S)  # covered values nearby
    covered = torch.nn.functional.unfold(mask[None, None].double(), 5, padding=2).view(25, S, S) > 0
    match = ((windows - dil[:, None]).abs().amax(0) == 0) & covered
    ring = have & ~mask
    assert int(ring.sum()) > 100 and match.any(0)[ring].all()


def test_normals_and_vertex_normals():
    pos, faces = icosphere(2, dtype=torch.float64)
    n = vertex_normals(pos, faces)
    assert torch.allclose(n.norm(dim=1), torch.ones(len(n), dtype=torch.float64))
    assert float((n * pos).sum(1).min()) > 0.995  # outward, nearly radial
    seen = []
    bake(_plane(), lambda p, nr: seen.append(nr) or p, 8)
    want = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([3.0, 0.5, 0.25]).double(),
                                                            torch.tensor([0.0, 2.0, -1.0]).double()), dim=0)
    assert torch.allclose(seen[0], want.expand_as(seen[0]), atol=1e-12)
    # A mesh with its own normals bakes those.
    m = _plane()
    m2 = Mesh(m.positions, m.faces, m.uv, m.uv_faces, -want.expand(4, 3).clone(), m.faces)
    seen.clear()
    bake(m2, lambda p, nr: seen.append(nr) or p, 8)
    assert torch.allclose(seen[0], -want.expand_as(seen[0]), atol=1e-12)


def test_gradients_reach_positions_and_fn_parameters():
    m = _plane()
    pos = m.positions.clone().requires_grad_()
    w = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64, requires_grad=True)

    def f(p, weights):
        return bake(Mesh(p, m.faces, m.uv, m.uv_faces), lambda x, n: (x * weights).sum(-1) + n[:, 2], 4, dilate=1)

    assert torch.autograd.gradcheck(f, (pos, w))


def _corner():
    """A floor [0, 2] x [0, 1] (z = 0, normal +z) and a wall x = 0 of height 1 (normal +x), two uv charts."""
    P = torch.tensor([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0], [0, 0, 1], [0, 1, 1]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 3, 5], [0, 5, 4]])
    uv = torch.tensor([[0, 0], [1, 0], [1, 0.5], [0, 0.5], [0, 0.55], [0.5, 0.55], [0.5, 1], [0, 1]],
                      dtype=torch.float64)
    return Mesh(P, faces, uv, torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]))


def test_occlusion_against_ray_casting_and_a_concavity():
    trimesh = pytest.importorskip("trimesh")
    m = _corner()
    pts = torch.tensor([[0.05, 0.5, 0], [0.3, 0.5, 0], [1.9, 0.5, 0], [1.0, 0.95, 0]], dtype=torch.float64)
    nrm = torch.tensor([[0, 0, 1.0]], dtype=torch.float64).expand(4, 3)
    d = sphere_directions(32, dtype=torch.float64)
    vis = occlusion(m.positions, m.faces, pts, nrm, directions=d, resolution=128)
    tm = trimesh.Trimesh(m.positions.numpy(), m.faces.numpy(), process=False)
    ref = []
    for p, n in zip(pts.numpy(), nrm.numpy()):
        c = d.numpy() @ n
        up = c > 0
        hit = tm.ray.intersects_any(np.tile(p + 1e-6 * n, (int(up.sum()), 1)), d.numpy()[up])
        ref.append((c[up] * ~hit).sum() / c[up].sum())
    ref = torch.tensor(ref, dtype=torch.float64)
    # A direction whose ray passes within a shadow texel of the wall's edge may flip: at most one per point here.
    one = float((d[:, 2] / d[:, 2].clamp(min=0).sum()).max())
    assert torch.all((vis - ref).abs() <= one + 1e-9), (vis, ref)
    assert float((vis - ref).abs().sum()) <= one + 1e-9
    # In the corner half the sky is the wall; far from it nearly none.
    assert vis[0] < 0.65 and vis[2] > 0.95 and vis[0] < vis[1] < vis[2]


def test_ambient_occlusion_map():
    m = _corner()
    S = 16
    ao = ambient_occlusion(m, S, directions=32, resolution=64)
    assert ao.shape == (1, S, S) and float(ao.min()) >= 0 and float(ao.max()) <= 1
    # Floor texels (v < 0.5): the column next to the wall (u near 0) is darker than the far end (u near 1).
    floor = ao[0, 1:7]
    assert float(floor[:, 0].mean()) < 0.8 and float(floor[:, -1].mean()) > 0.9
    # The wall's foot (v = 0.55 in its chart) is darker than its top (v = 1): the floor hides part of its sky.
    wall = ao[0, 9:15, :8]
    assert float(wall[0].mean()) < float(wall[-1].mean()) - 0.05
    # Every covered texel holds occlusion() at the surface point bake finds there.
    pts, mask = bake(m, _identity, S, dilate=0, return_mask=True)
    nrm = bake(m, lambda p, n: n, S, dilate=0)
    want = occlusion(m.positions, m.faces, pts[:, mask].t(), nrm[:, mask].t(), directions=32, resolution=64)
    assert torch.allclose(ao[0][mask], want, atol=1e-12)


def test_baked_marble_matches_the_solid_texture_on_spot():
    mesh = spot_mesh()
    pos_tex, mask = bake(mesh, _identity, 128, return_mask=True)
    tex = {S: bake(mesh, lambda p, n: marble(p), S) for S in (128, 256)}
    assert tex[128].shape == (3, 128, 128)
    assert torch.allclose(tex[128].permute(1, 2, 0)[mask], marble(pos_tex.permute(1, 2, 0)[mask]), atol=1e-6)
    # Rendered: the solid texture per pixel vs the baked texture read bilinearly at the pixel's uv; the baked
    # one converges to the solid one as the texture grows (28.4 and 36.6 dB measured at 128 and 256).
    clip = difftex.camera.transform(mesh.positions, spot_mvp(2.5, (1.0, 0.3, 1.0)).unsqueeze(0))
    frags = difftex.rasterize(clip, mesh.faces, (96, 96))
    p = difftex.interpolate(mesh.positions, mesh.faces, frags)
    uv = difftex.interpolate(mesh.uv, mesh.faces, frags, attr_faces=mesh.uv_faces)
    solid = marble(p).permute(0, 3, 1, 2)
    m = frags.mask.unsqueeze(1).expand_as(solid)
    score = {S: psnr(difftex.sample(t.unsqueeze(0), uv, filter="bilinear", wrap="clamp"), solid, mask=m)
             for S, t in tex.items()}
    assert score[256] > 34.0 and score[256] > score[128] + 6.0, score


def test_bad_input():
    m = _plane()
    with pytest.raises(TypeError, match=r"mesh: expected a difftex.Mesh, got tuple"):
        bake((m.positions, m.faces), _identity, 8)
    with pytest.raises(TypeError, match=r"size: expected an int or an \(H, W\) pair of ints, got 8.0"):
        bake(m, _identity, 8.0)
    with pytest.raises(ValueError, match=r"size: expected positive texture sizes, got 0"):
        bake(m, _identity, 0)
    with pytest.raises(ValueError, match=r"dilate: expected an int >= 0, got -1"):
        bake(m, _identity, 8, dilate=-1)
    with pytest.raises(TypeError, match=r"fill: expected a number, got str"):
        bake(m, _identity, 8, fill="0")
    with pytest.raises(TypeError, match=r"fn: expected a callable"):
        bake(m, None, 8)
    with pytest.raises(ValueError, match=r"fn: expected it to return \[N, C\] or \[N\] values for N = 16 points"):
        bake(m, lambda p, n: p[:3], 8)
    with pytest.raises(TypeError, match=r"fn: expected it to return a float tensor"):
        bake(m, lambda p, n: "x", 8)
    with pytest.raises(ValueError, match=r"normals: expected the shape of points \(2, 3\)"):
        occlusion(m.positions, m.faces, torch.zeros(2, 3, dtype=torch.float64), torch.zeros(3, 3,
                                                                                            dtype=torch.float64))
    with pytest.raises(ValueError, match=r"resolution: expected an int >= 2"):
        ambient_occlusion(m, 8, resolution=1)


def test_rectangular_size_and_float32():
    tex = bake(_plane(torch.float32), _identity, (8, 12))
    assert tex.shape == (3, 8, 12) and tex.dtype == torch.float32
    uv = _texel_centres(8, 12, torch.float32)
    inside = ((uv > 0.25) & (uv < 0.75)).all(-1)
    assert torch.allclose(tex.permute(1, 2, 0)[inside], _affine(uv)[inside], atol=1e-6)


def test_normals_without_normal_faces_are_the_meshs():
    # normals indexed like the positions (normal_faces None, as tangent_frames takes them) were ignored for the
    # area-weighted vertex normals of the positions.
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0.5], [0, 1, 0.5]])
    uv = torch.tensor([[0.0, 1], [1, 1], [1, 0], [0, 0]])
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    normals = torch.tensor([[0.0, 0, 1]]).expand(4, 3).clone()
    for nf in (None, f):
        baked = difftex.bake(Mesh(pos, f, uv, f, normals, nf), lambda p, n: n, 4)
        torch.testing.assert_close(baked[:, 2, 2], torch.tensor([0.0, 0, 1]), atol=1e-6, rtol=0)

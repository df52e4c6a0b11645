"""Tests for difftex.interpolate: perspective correctness, analytic pixel derivatives, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from difftex import camera, interpolate, rasterize

from difftex.testing import icosphere
from tests.geometry.raster_helpers import DEVICES, random_rotation


def _tilted_quad(tilt_deg=60.0, dist=2.2):
    """A unit quad tilted away from the camera, uv linear in world space."""
    a = math.radians(tilt_deg)
    local = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]], dtype=torch.float64)
    # rotate about x: y -> (y cos a, y sin a) in (y, z); push back along -z
    world = torch.stack(
        (local[:, 0], local[:, 1] * math.cos(a), -dist - local[:, 1] * math.sin(a)), dim=-1
    )
    uv = torch.stack(((local[:, 0] + 1) / 2, (1 - local[:, 1]) / 2), dim=-1)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return world, uv, faces, a, dist


def _ndc_grid(H, W, dtype=torch.float64):
    xs = (torch.arange(W, dtype=dtype) + 0.5) / W * 2 - 1
    ys = 1 - (torch.arange(H, dtype=dtype) + 0.5) / H * 2
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    return x, y


def test_perspective_correct_uv_on_tilted_quad():
    world, uv, faces, a, dist = _tilted_quad()
    H = W = 64
    proj = camera.perspective(60.0, 1.0, 0.1, 10.0, degrees=True, dtype=torch.float64)
    pos = camera.transform(world, proj)
    frags = rasterize(pos, faces, (H, W))
    got = interpolate(uv, faces, frags)[0]
    m = frags.tri_id[0] >= 0
    assert m.float().mean() > 0.2

    # Analytic reference: intersect each pixel ray with the quad's plane.
    x, y = _ndc_grid(H, W)
    t = 1 / math.tan(math.radians(30.0))
    d = torch.stack((x / t, y / t, -torch.ones_like(x)), -1)  # view ray directions
    n = torch.tensor([0.0, math.sin(a), math.cos(a)], dtype=torch.float64)  # plane normal
    p0 = torch.tensor([0.0, 0.0, -dist], dtype=torch.float64)
    s = (p0 @ n) / (d @ n)
    hit = s[..., None] * d
    ly = (hit - p0) @ torch.tensor([0.0, math.cos(a), -math.sin(a)], dtype=torch.float64)
    ref = torch.stack(((hit[..., 0] + 1) / 2, (1 - ly) / 2), -1)
    torch.testing.assert_close(got[m], ref[m], atol=1e-12, rtol=0)

    # Straight lines stay straight: the u = 0.5 checker boundary, located to
    # sub-pixel precision in every row, is a straight line in the image.
    # Screen-space (affine) interpolation bends it at the quad's diagonal.
    def boundary_cols(u, mask):
        rows, cols = [], []
        for r in range(u.shape[0]):
            ur = u[r]
            ok = mask[r, :-1] & mask[r, 1:]
            cross = ok & (ur[:-1] < 0.5) & (ur[1:] >= 0.5)
            for c in torch.nonzero(cross).flatten().tolist():
                rows.append(r)
                cols.append(c + float((0.5 - ur[c]) / (ur[c + 1] - ur[c])))
        return torch.tensor(rows, dtype=torch.float64), torch.tensor(cols, dtype=torch.float64)

    def line_residual(rows, cols):
        A = torch.stack((rows, torch.ones_like(rows)), -1)
        sol = torch.linalg.lstsq(A, cols[:, None]).solution
        return float((A @ sol - cols[:, None]).abs().max())

    rows, cols = boundary_cols(got[..., 0], m)
    assert len(rows) > 20
    assert line_residual(rows, cols) < 0.01  # pixels
    # the same check on v = const lines (columns)
    # the v = 0.5 line, found along image columns (transposed image)
    rows_v, cols_v = boundary_cols(got[..., 1].T.contiguous(), m.T.contiguous())
    assert len(rows_v) > 20 and line_residual(rows_v, cols_v) < 0.01

    # Affine interpolation (w forced to 1) visibly bends the line.
    flat = rasterize(pos / pos[:, 3:], faces, (H, W))
    u_aff = interpolate(uv, faces, flat)[0][..., 0]
    ra, ca = boundary_cols(u_aff, flat.tri_id[0] >= 0)
    assert line_residual(ra, ca) > 0.3


def test_uv_derivatives_units_and_signs_on_screen_aligned_quad():
    # Orthographic full-screen quad with uv (0, 0) at the top-left corner:
    # uv at pixel (r, c) is ((c + 0.5) / W, (r + 0.5) / H), so uv_dx = (1/W, 0)
    # and uv_dy = (0, 1/H) exactly (DESIGN.md conventions).
    H, W = 12, 20
    proj = camera.orthographic(-1.0, 1.0, -1.0, 1.0, 0.0, 2.0, dtype=torch.float64)
    world = torch.tensor([[-1, 1, -1], [1, 1, -1], [1, -1, -1], [-1, -1, -1]], dtype=torch.float64)
    uv = torch.tensor([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=torch.float64)
    faces = torch.tensor([[0, 2, 1], [0, 3, 2]])
    frags = rasterize(camera.transform(world, proj), faces, (H, W))
    assert (frags.tri_id >= 0).all()
    val, dx, dy = interpolate(uv, faces, frags, derivatives=True)
    r, c = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    torch.testing.assert_close(val[0], torch.stack(((c + 0.5) / W, (r + 0.5) / H), -1), atol=1e-14, rtol=0)
    torch.testing.assert_close(dx[0], torch.tensor([1 / W, 0.0], dtype=torch.float64).expand(H, W, 2), atol=1e-14, rtol=0)
    torch.testing.assert_close(dy[0], torch.tensor([0.0, 1 / H], dtype=torch.float64).expand(H, W, 2), atol=1e-14, rtol=0)


def _sphere_scene(seed=0, dtype=torch.float64, subdivisions=2):
    V, F = icosphere(subdivisions, dtype=torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = random_rotation(torch.Generator().manual_seed(seed))
    view[:3, 3] = torch.tensor([0.2, -0.1, -2.6], dtype=torch.float64)
    pos = camera.transform(V, camera.perspective(55.0, 1.25, 0.5, 10.0, degrees=True, dtype=torch.float64) @ view)
    # a smooth non-linear attribute: world position and a product term
    attr = torch.cat((V, (V[:, :1] * V[:, 1:2]), torch.sin(3 * V[:, 2:3])), -1)
    return pos.to(dtype), F, attr.to(dtype)


@pytest.mark.parametrize("delta", [1e-3, 0.25])
def test_analytic_derivatives_match_finite_differences_at_subpixel_offsets(delta):
    # Shifting clip x by 2 * delta / W * w moves every pixel's sample point by
    # +delta columns; likewise for rows. Central differences of the
    # interpolated attribute then estimate d/dcol and d/drow.
    pos, F, attr = _sphere_scene()
    H, W = 40, 50
    frags = rasterize(pos, F, (H, W))
    val, dx, dy = interpolate(attr, F, frags, derivatives=True)

    def shifted(dc, dr):
        p = pos.clone()
        p[:, 0] = p[:, 0] - 2 * dc / W * p[:, 3]
        p[:, 1] = p[:, 1] + 2 * dr / H * p[:, 3]
        fr = rasterize(p, F, (H, W))
        return fr.tri_id, interpolate(attr, F, fr)

    tp, vp = shifted(delta, 0)
    tm, vm = shifted(-delta, 0)
    ok = (frags.tri_id >= 0) & (tp == frags.tri_id) & (tm == frags.tri_id)
    fd_x = (vp - vm) / (2 * delta)
    tp, vp = shifted(0, delta)
    tm, vm = shifted(0, -delta)
    ok_y = (frags.tri_id >= 0) & (tp == frags.tri_id) & (tm == frags.tri_id)
    fd_y = (vp - vm) / (2 * delta)
    assert ok.sum() > 200 and ok_y.sum() > 200
    # Within one triangle the attribute is a ratio of affine functions of the
    # pixel position; the central difference error is O(delta^2), largest on
    # triangles seen at grazing angles.
    scale = float(dx[ok].abs().max())
    err_x = (fd_x[ok] - dx[ok]).abs()
    err_y = (fd_y[ok_y] - dy[ok_y]).abs()
    tol_max, tol_med = (1e-5, 1e-9) if delta < 0.01 else (2e-2, 2e-4)
    assert float(err_x.max()) <= tol_max * scale and float(err_y.max()) <= tol_max * scale
    assert float(err_x.median()) <= tol_med * scale and float(err_y.median()) <= tol_med * scale
    # derivatives are genuinely non-trivial in both directions
    assert float(dx[ok].abs().mean()) > 1e-3 and float(dy[ok_y].abs().mean()) > 1e-3


def test_gradcheck_interpolate_wrt_attr_and_pos():
    pos, F, attr = _sphere_scene(1, subdivisions=1)
    attr = attr[:, 2:5]  # keep the check quick: 42 vertices x 3 channels
    H = W = 10
    frags = rasterize(pos, F, (H, W))
    interior = (frags.tri_id >= 0) & (frags.bary.min(-1).values > 0.05)
    assert interior.sum() >= 8

    def fn(p, a):
        fr = rasterize(p, F, (H, W))
        assert torch.equal(fr.tri_id[interior], frags.tri_id[interior])
        v, dx, dy = interpolate(a, F, fr, derivatives=True)
        return v[interior], dx[interior], dy[interior]

    p = pos.clone().requires_grad_(True)
    a = attr.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (p, a), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_background_is_zero_with_zero_gradient():
    pos, F, attr = _sphere_scene(2)
    frags = rasterize(pos, F, (16, 16))
    bg = frags.tri_id < 0
    assert bg.any() and (~bg).any()
    a = attr.clone().requires_grad_(True)
    p = pos.clone().requires_grad_(True)
    fr = rasterize(p, F, (16, 16))
    val, dx, dy = interpolate(a, F, fr, derivatives=True)
    for t in (val, dx, dy):
        assert (t[bg] == 0).all()
    # gradient of a loss on background pixels only is exactly zero
    (val[bg].sum() + dx[bg].sum() + dy[bg].sum()).backward()
    assert (a.grad == 0).all() and (p.grad == 0).all()
    # attr rows not used by any visible triangle get no gradient
    a.grad = None
    interpolate(a, F, frags).sum().backward()
    used = torch.zeros(len(attr), dtype=torch.bool)
    used[F[frags.tri_id[~bg]].reshape(-1)] = True
    assert (a.grad[~used] == 0).all() and (a.grad[used] != 0).any()
    # the gradient w.r.t. an attribute row is the sum of its barycentric weights
    w = torch.zeros(len(attr), dtype=torch.float64)
    w.index_add_(0, F[frags.tri_id[~bg]].reshape(-1), frags.bary[~bg].reshape(-1))
    torch.testing.assert_close(a.grad[:, 0], w)


def test_face_varying_attributes():
    pos, F, attr = _sphere_scene(3)
    frags = rasterize(pos, F, (20, 20))
    # one uv per triangle corner, stored OBJ style in a separate array
    corner_attr = attr[F].reshape(-1, attr.shape[1])  # [3F, A]
    attr_faces = torch.arange(3 * len(F)).reshape(-1, 3)
    ref = interpolate(attr, F, frags, derivatives=True)
    got = interpolate(corner_attr, F, frags, derivatives=True, attr_faces=attr_faces)
    also = interpolate(corner_attr, attr_faces, frags, derivatives=True)  # index passed as faces
    for r, g, a in zip(ref, got, also):
        torch.testing.assert_close(g, r, atol=0, rtol=0)
        torch.testing.assert_close(a, r, atol=0, rtol=0)
    # a per-corner seam: the same vertex with different values per face
    seam = corner_attr.clone()
    seam[attr_faces[:, 0]] += 10.0
    v = interpolate(seam, F, frags, attr_faces=attr_faces)
    m = frags.tri_id >= 0
    torch.testing.assert_close(v[m] - ref[0][m], 10.0 * frags.bary[m][:, :1].expand(-1, attr.shape[1]))


def test_batched_attributes_and_broadcast():
    pos, F, attr = _sphere_scene(4)
    pos2 = torch.stack((pos, pos * torch.tensor([1.0, -1.0, 1.0, 1.0], dtype=torch.float64)))
    frags = rasterize(pos2, F, (16, 18))
    attr2 = torch.stack((attr, 2 * attr + 1))
    out = interpolate(attr2, F, frags)
    assert out.shape == (2, 16, 18, attr.shape[1])
    for b in range(2):
        single = rasterize(pos2[b], F, (16, 18))
        torch.testing.assert_close(out[b], interpolate(attr2[b], F, single)[0])
    # [V, A] broadcast over the batch, and [B, V, A] over a B = 1 raster
    shared = interpolate(attr, F, frags)
    torch.testing.assert_close(shared[1], interpolate(attr, F, rasterize(pos2[1], F, (16, 18)))[0])
    one = rasterize(pos, F, (16, 18))
    both = interpolate(attr2, F, one)
    assert both.shape[0] == 2
    torch.testing.assert_close(both[1], interpolate(attr2[1], F, one)[0])
    # float32 fragments with float64 attributes promote
    f32 = rasterize(pos.float(), F, (16, 18))
    assert interpolate(attr.float(), F, f32).dtype == torch.float32


def test_bad_input_errors_name_the_argument():
    pos, F, attr = _sphere_scene(5)
    frags = rasterize(pos, F, (8, 8))
    with pytest.raises(ValueError, match="attr.*\\[V, A\\]"):
        interpolate(attr[:, 0], F, frags)
    with pytest.raises(TypeError, match="attr.*floating"):
        interpolate(attr.long(), F, frags)
    with pytest.raises(ValueError, match="faces.*\\[0, 4\\]"):
        interpolate(attr[:5], F, frags)
    with pytest.raises(TypeError, match="faces.*integer"):
        interpolate(attr, F.float(), frags)
    with pytest.raises(ValueError, match="attr_faces.*one row per face"):
        interpolate(attr, F, frags, attr_faces=F[:3])
    with pytest.raises(ValueError, match="attr_faces.*\\[0, 2\\]"):
        interpolate(attr[:3], F, frags, attr_faces=F)
    with pytest.raises(ValueError, match="faces.*tri_id"):
        interpolate(attr, F[:3], frags)
    with pytest.raises(TypeError, match="frags"):
        interpolate(attr, F, frags.tri_id)
    with pytest.raises(ValueError, match="batch"):
        interpolate(torch.stack((attr, attr, attr)), F, rasterize(torch.stack((pos, pos)), F, (8, 8)))


@pytest.mark.parametrize("device", DEVICES)
def test_device(device):
    pos, F, attr = _sphere_scene(6)
    ref = interpolate(attr, F, rasterize(pos, F, (12, 12)), derivatives=True)
    got = interpolate(attr.to(device), F.to(device), rasterize(pos.to(device), F.to(device), (12, 12)), derivatives=True)
    for r, g in zip(ref, got):
        assert g.device.type == device
        torch.testing.assert_close(g.cpu(), r)

"""Tests for difftex.rasterize: trimesh parity, fill rule, clipping, gradients, bad input."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

import difftex
from difftex import camera, interpolate, rasterize
from difftex.geometry.raster import _coverage_count

from difftex.testing import icosphere
from tests.conftest import use_backend
from tests.geometry.raster_helpers import DEVICES, random_rotation, ray_cast, spot_trimesh, view_matrix


@pytest.fixture(autouse=True, params=["native", "reference"])
def raster_impl(request):
    """Every test on both implementations: the native CPU kernel and the torch path (the reference, CUDA's)."""
    with use_backend(request.param):
        yield request.param


def _boundary(ids: np.ndarray) -> np.ndarray:
    """Pixels whose 8-neighbourhood holds more than one id (triangle edges, silhouettes)."""
    p = np.pad(ids, 1, mode="edge")
    H, W = ids.shape
    out = np.zeros_like(ids, dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            out |= p[1 + dr:1 + dr + H, 1 + dc:1 + dc + W] != ids
    return out


# --------------------------------------------------------------------------
# reference: trimesh ray casting on spot


@functools.lru_cache(maxsize=None)
def _spot_reference(azim, elev, H, W):
    """(mvp, trimesh ids, hit points) of one view, cast once for both implementations."""
    mesh = spot_trimesh()
    center = tuple(((mesh.bounds[0] + mesh.bounds[1]) / 2).tolist())
    eye, view, proj = view_matrix(azim, elev, 2.6, center)
    mvp = proj @ view
    return (mvp, *ray_cast(mesh, mvp, H, W))


# Four views around the cow (trimesh's rtree ray casting is slowest for
# views whose rays run diagonally through the mesh's bounding box, so these
# stay near the axes to keep the suite fast).
@pytest.mark.parametrize(
    "azim,elev,dtype",
    [(0, 10, torch.float64), (90, 8, torch.float32), (180, -8, torch.float64), (270, 15, torch.float32)],
)
def test_matches_trimesh_ray_casting_on_spot(azim, elev, dtype):
    mesh = spot_trimesh()
    V = torch.tensor(mesh.vertices, dtype=torch.float64)
    F = torch.tensor(mesh.faces, dtype=torch.int64)
    size = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    H = W = 128
    mvp, ref_ids, ref_hits = _spot_reference(azim, elev, H, W)

    frags = rasterize(camera.transform(V, mvp).to(dtype), F, (H, W))
    ids = frags.tri_id[0].numpy()
    agree = (ids == ref_ids).mean()
    assert (ref_ids >= 0).mean() > 0.2  # the view actually shows the cow
    assert agree >= 0.995, f"only {agree:.4%} of pixels agree with trimesh"
    # Disagreements may only sit on triangle edges / silhouettes of the reference.
    bad = ids != ref_ids
    assert not (bad & ~_boundary(ref_ids)).any()

    # Hit points rebuilt from the barycentrics lie on trimesh's hits.
    both = (ids == ref_ids) & (ids >= 0)
    corners = V[F[frags.tri_id[0].clamp(min=0)]]  # [H, W, 3, 3]
    hits = (frags.bary[0].double()[..., None] * corners).sum(-2).numpy()
    err = np.abs(hits[both] - ref_hits[both]).max()
    assert err <= 1e-4 * size, f"hit points off by {err / size:.2e} of the mesh size"

    # Depth is the NDC z of that hit point.
    clip = camera.transform(torch.from_numpy(hits[both]), mvp)
    ndc_z = (clip[:, 2] / clip[:, 3]).numpy()
    tol = 1e-10 if dtype == torch.float64 else 1e-5
    np.testing.assert_allclose(frags.depth[0].double().numpy()[both], ndc_z, atol=tol, rtol=0)
    # Barycentrics are convex weights on covered pixels, zero elsewhere.
    b = frags.bary[0].double()
    np.testing.assert_allclose(b.sum(-1).numpy()[ids >= 0], 1.0, atol=1e-6)
    assert float(b.min()) > -1e-6
    assert float(b[frags.tri_id[0] < 0].abs().max()) == 0.0


# --------------------------------------------------------------------------
# fill rule / watertightness


def test_icosphere_is_watertight_from_many_views():
    from scipy import ndimage

    V, F = icosphere(3, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    proj = camera.perspective(40.0, 1.0, 0.5, 10.0, degrees=True, dtype=torch.float64)
    H = W = 64
    pos = []
    for _ in range(16):
        R = random_rotation(gen)
        t = torch.tensor([0.3, -0.2, -3.0], dtype=torch.float64) + 0.2 * torch.randn(3, generator=gen, dtype=torch.float64)
        view = torch.eye(4, dtype=torch.float64)
        view[:3, :3] = R
        view[:3, 3] = t
        pos.append(camera.transform(V, proj @ view))
    pos = torch.stack(pos)  # [16, V, 4] in one batched call
    for dtype in (torch.float64, torch.float32):
        p = pos.to(dtype)
        both = _coverage_count(p, F, (H, W))
        front = _coverage_count(p, F, (H, W), cull_backfaces=True)
        # Every pixel centre is inside exactly 0 or 2 triangles of a closed
        # convex mesh (front and back), exactly 0 or 1 front-facing one.
        assert set(both.unique().tolist()) <= {0, 2}
        assert set(front.unique().tolist()) <= {0, 1}
        assert torch.equal(both == 2, front == 1)
        mask = rasterize(p, F, (H, W)).tri_id >= 0
        assert torch.equal(mask, front == 1)
        for b in range(mask.shape[0]):
            m = mask[b].numpy()
            assert m.sum() > 300
            assert np.array_equal(ndimage.binary_fill_holes(m), m), "hole inside the silhouette"


def test_fill_rule_on_pixel_aligned_grid():
    # A grid whose vertices sit exactly on pixel centres (dyadic coordinates,
    # w = 1): many edges pass exactly through pixel centres, and vertices
    # coincide with them. Each centre must be covered exactly once.
    H = W = 16
    n = 9
    coords = (torch.arange(-1, n - 1, dtype=torch.float64) * 2 + 0.5) / W * 2 - 1  # every 2 pixels, beyond the edges
    coords = torch.cat((coords, torch.tensor([1.25])))
    gy, gx = torch.meshgrid(coords, coords, indexing="ij")
    k = len(coords)
    verts = torch.stack((gx, gy, torch.zeros_like(gx), torch.ones_like(gx)), -1).reshape(-1, 4)
    idx = torch.arange(k * k).reshape(k, k)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # alternate diagonals so both orientations of shared diagonal edges occur
    flip = ((torch.arange(k - 1)[:, None] + torch.arange(k - 1)[None, :]) % 2).bool()
    t1 = torch.where(flip[..., None], torch.stack((a, b, d), -1), torch.stack((a, b, c), -1))
    t2 = torch.where(flip[..., None], torch.stack((a, d, c), -1), torch.stack((b, d, c), -1))
    faces = torch.cat((t1.reshape(-1, 3), t2.reshape(-1, 3)))
    for dtype in (torch.float64, torch.float32):
        count = _coverage_count(verts.to(dtype), faces, (H, W))
        assert torch.equal(count, torch.ones_like(count))
        # also with the vertices scaled by a per-vertex w (same NDC position)
        w = 1 + torch.rand(len(verts), 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        w = torch.round(w * 8) / 8  # dyadic so NDC positions stay exact
        count = _coverage_count((verts * w).to(dtype), faces, (H, W))
        assert torch.equal(count, torch.ones_like(count))


def _grid_mesh(n: int, lo: float, hi: float, dtype: torch.dtype, w: torch.Tensor | None = None):
    t = torch.linspace(lo, hi, n + 1, dtype=torch.float64)
    gy, gx = torch.meshgrid(t, t, indexing="ij")
    pos = torch.stack((gx, gy, torch.zeros_like(gx), torch.ones_like(gx)), -1).reshape(-1, 4)
    if w is not None:
        pos = pos * w
    i = torch.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = i[:-1, :-1], i[:-1, 1:], i[1:, :-1], i[1:, 1:]
    faces = torch.cat((torch.stack((a, b, c), -1).reshape(-1, 3), torch.stack((b, d, c), -1).reshape(-1, 3)))
    return pos.to(dtype), faces


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_vertices_on_non_dyadic_pixel_centres_leave_no_holes(dtype):
    # A screen-covering grid whose vertices land on pixel centres only up to
    # rounding (0.05 steps, 60 pixels): each edge is consistent between its
    # two triangles, but the edges meeting at a vertex are each rounded
    # their own way, so without an exact test there a centre could be owned
    # by no triangle (holes) or by two or three.
    for n, res, w in ((48, 60, None), (48, 60, 1.7), (30, 75, None), (40, 100, 0.3)):
        pos, faces = _grid_mesh(n, -1.2, 1.2, dtype, None if w is None else torch.tensor(w, dtype=torch.float64))
        count = _coverage_count(pos, faces, (res, res))
        assert torch.equal(count, torch.ones_like(count)), (n, res, w, (count != 1).nonzero().tolist()[:5])
    # Perspective: the same grid tilted, vertices at arbitrary positions.
    pos, faces = _grid_mesh(24, -1.5, 1.5, torch.float64)
    ang = torch.tensor(0.4, dtype=torch.float64)
    rot = torch.tensor([[1, 0, 0], [0, torch.cos(ang), -torch.sin(ang)], [0, torch.sin(ang), torch.cos(ang)]],
                       dtype=torch.float64)
    p3 = pos[:, :3] @ rot.T + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    clip = torch.stack((p3[:, 0] * 2, p3[:, 1] * 2, p3[:, 2] * 0.5 - 1, p3[:, 2]), -1)
    count = _coverage_count(clip.to(dtype), faces, (64, 48))
    covered = count > 0
    assert count.max() <= 1
    # every pixel between covered pixels in its row is covered (a convex silhouette)
    for row in covered[0]:
        cols = row.nonzero().flatten()
        if len(cols):
            assert row[cols[0]:cols[-1] + 1].all()


def test_pixel_centre_and_row_convention():
    H, W = 4, 8
    # A small triangle around the centre of pixel (row 0, col 1): NDC x =
    # (1.5 / 8) * 2 - 1 = -0.625, y = 1 - 0.5 / 4 * 2 = 0.75.
    cx, cy, r = -0.625, 0.75, 0.05
    pos = torch.tensor([[cx - r, cy - r, 0.0, 1.0], [cx + r, cy - r, 0.0, 1.0], [cx, cy + r, 0.0, 1.0]])
    frags = rasterize(pos, torch.tensor([[0, 1, 2]]), (H, W))
    expected = torch.full((1, H, W), -1, dtype=torch.int64)
    expected[0, 0, 1] = 0
    assert torch.equal(frags.tri_id, expected)
    assert frags.tri_id.dtype == torch.int64
    assert frags.resolution == (H, W)
    # the pixel centre (cx, cy) is halfway up the triangle, on its axis
    b = frags.bary[0, 0, 1]
    torch.testing.assert_close(b, torch.tensor([0.25, 0.25, 0.5]), atol=1e-6, rtol=0)


# --------------------------------------------------------------------------
# depth test


def test_nearest_surface_wins_and_ties_are_deterministic():
    H = W = 8
    quad = torch.tensor([[-1.5, -1.5], [1.5, -1.5], [0.0, 1.5]], dtype=torch.float64)
    def tri(z):
        return torch.cat((quad, torch.full((3, 1), z, dtype=torch.float64), torch.ones(3, 1, dtype=torch.float64)), 1)
    pos = torch.cat((tri(0.5), tri(-0.25), tri(0.75), tri(-0.25)))  # tris 1 and 3 tie, nearest
    faces = torch.arange(12).reshape(4, 3)
    frags = rasterize(pos, faces, (H, W))
    covered = frags.tri_id[0] >= 0
    assert covered.sum() > 20
    assert (frags.tri_id[0][covered] == 1).all()  # lowest id of the tied pair
    assert torch.allclose(frags.depth[0][covered], torch.tensor(-0.25, dtype=torch.float64))
    # any face order picks the same surface
    # reordered faces: new ids 0 and 3 are the old tied pair 3 and 1; the
    # tie again goes to the lowest (new) id
    perm = torch.tensor([3, 2, 0, 1])
    frags2 = rasterize(pos, faces[perm], (H, W))
    assert torch.equal(frags2.tri_id[0] >= 0, covered)
    assert (frags2.tri_id[0][covered] == 0).all()


def test_near_and_far_planes_clip_per_pixel():
    # One triangle crossing the near plane, seen by an orthographic camera:
    # z runs from -2 (beyond near) to 0 across x, so only x > -ish survives.
    H, W = 4, 16
    pos = torch.tensor([[-1.5, -1.5, -3.0, 1.0], [1.5, -1.5, 1.0, 1.0], [0.0, 4.0, -1.0, 1.0]], dtype=torch.float64)
    frags = rasterize(pos, torch.tensor([[0, 1, 2]]), (H, W))
    d = frags.depth[0]
    m = frags.tri_id[0] >= 0
    assert m.any() and (~m).any()
    assert (d[m] >= -1).all() and (d[m] <= 1).all()
    # z = a x + b y + c exactly on this affine triangle: check every pixel
    xs = (torch.arange(W, dtype=torch.float64) + 0.5) / W * 2 - 1
    ys = 1 - (torch.arange(H, dtype=torch.float64) + 0.5) / H * 2
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    A = torch.tensor([[-1.5, -1.5, 1.0], [1.5, -1.5, 1.0], [0.0, 4.0, 1.0]], dtype=torch.float64)
    coef = torch.linalg.solve(A, pos[:, 2])
    z = coef[0] * x + coef[1] * y + coef[2]
    torch.testing.assert_close(d[m], z[m])
    # clipped exactly where z leaves [-1, 1]: every pixel of the triangle's
    # footprint with z in range is covered, and no other
    inside = (torch.stack([x, y, torch.ones_like(x)], -1) @ torch.linalg.inv(A)).min(-1).values >= 0
    assert torch.equal(m, inside & (z >= -1) & (z <= 1))
    assert (inside & (z < -1)).any()  # the near plane did cut something


def test_triangle_through_eye_plane_matches_ray_plane_reference():
    # A ground plane made of two huge triangles reaching behind the camera
    # (w < 0 at some corners): ids, hit points and coverage against an
    # analytic ray / plane intersection.
    H = W = 48
    s = 50.0
    verts = torch.tensor([[-s, -1.0, -s], [s, -1.0, -s], [s, -1.0, s], [-s, -1.0, s]], dtype=torch.float64)
    faces = torch.tensor([[0, 2, 1], [0, 3, 2]])
    eye = torch.tensor([0.3, 0.0, 2.0], dtype=torch.float64)
    view = camera.look_at(eye, torch.tensor([0.0, -0.6, 0.0], dtype=torch.float64), (0.0, 1.0, 0.0))
    proj = camera.perspective(70.0, 1.0, 0.05, 20.0, degrees=True, dtype=torch.float64)
    mvp = proj @ view
    pos = camera.transform(verts, mvp)
    assert (pos[:, 3] < 0).any() and (pos[:, 3] > 0).any()
    frags = rasterize(pos, faces, (H, W))

    inv = torch.linalg.inv(mvp)
    xs = (torch.arange(W, dtype=torch.float64) + 0.5) / W * 2 - 1
    ys = 1 - (torch.arange(H, dtype=torch.float64) + 0.5) / H * 2
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    def unproject(z):
        p = torch.stack((x, y, torch.full_like(x, z), torch.ones_like(x)), -1) @ inv.T
        return p[..., :3] / p[..., 3:]
    o, f = unproject(-1.0), unproject(1.0)
    d = f - o
    t = (-1.0 - o[..., 1]) / d[..., 1]
    hit = o + t[..., None] * d
    ok = (t >= 0) & (t <= 1) & (hit[..., 0].abs() <= s) & (hit[..., 2].abs() <= s)
    ids = frags.tri_id[0]
    corners = verts[faces[ids.clamp(min=0)]]
    rebuilt = (frags.bary[0][..., None] * corners).sum(-2)
    assert torch.equal(ids >= 0, ok)
    assert ok.float().mean() > 0.3 and (~ok).any()
    torch.testing.assert_close(rebuilt[ok], hit[ok], atol=1e-9, rtol=0)
    assert torch.isfinite(frags.bary).all() and torch.isfinite(frags.depth).all()
    assert torch.isfinite(frags.bary_dx).all() and torch.isfinite(frags.bary_dy).all()
    # every covered pixel lies inside the triangle it names (bary >= 0), and
    # both triangles show up
    assert float(frags.bary[0][ok].min()) >= -1e-12
    assert (ids == 0).any() and (ids == 1).any()


# --------------------------------------------------------------------------
# culling, batch, dtype


def test_backface_culling_and_winding():
    ccw = torch.tensor([[-0.9, -0.9, 0, 1], [0.9, -0.9, 0, 1], [0, 0.9, 0, 1]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2]])
    assert (rasterize(ccw, faces, (8, 8), cull_backfaces=True).tri_id >= 0).sum() > 10
    cw = faces[:, [0, 2, 1]]
    assert (rasterize(ccw, cw, (8, 8), cull_backfaces=True).tri_id >= 0).sum() == 0
    assert (rasterize(ccw, cw, (8, 8)).tri_id >= 0).sum() > 10


def test_batch_matches_single_calls_and_broadcast():
    V, F = icosphere(1, dtype=torch.float64)
    gen = torch.Generator().manual_seed(3)
    proj = camera.perspective(50.0, 1.5, 0.5, 10.0, degrees=True, dtype=torch.float64)
    mats = []
    for _ in range(3):
        view = torch.eye(4, dtype=torch.float64)
        view[:3, :3] = random_rotation(gen)
        view[2, 3] = -3.0
        mats.append(proj @ view)
    pos = torch.stack([camera.transform(V, m) for m in mats])
    H, W = 20, 30
    fb = rasterize(pos, F, (H, W))
    assert fb.tri_id.shape == (3, H, W) and fb.bary.shape == (3, H, W, 3) and fb.depth.shape == (3, H, W)
    for b in range(3):
        fs = rasterize(pos[b], F, (H, W))
        assert torch.equal(fs.tri_id[0], fb.tri_id[b])
        torch.testing.assert_close(fs.bary[0], fb.bary[b])
        torch.testing.assert_close(fs.bary_dx[0], fb.bary_dx[b])
        torch.testing.assert_close(fs.depth[0], fb.depth[b])
    # float32 agrees with float64 except possibly at a handful of edge pixels
    f32 = rasterize(pos.float(), F, (H, W))
    assert (f32.tri_id == fb.tri_id).float().mean() > 0.99
    assert f32.bary.dtype == torch.float32


def test_empty_and_offscreen_inputs():
    pos = torch.tensor([[3.0, 3.0, 0.0, 1.0], [4.0, 3.0, 0.0, 1.0], [3.0, 4.0, 0.0, 1.0]])
    f = rasterize(pos, torch.tensor([[0, 1, 2]]), (5, 7))
    assert (f.tri_id == -1).all() and (f.bary == 0).all()
    f = rasterize(pos, torch.zeros(0, 3, dtype=torch.int64), (5, 7))
    assert (f.tri_id == -1).all()
    # entirely behind the camera (w < 0)
    back = torch.tensor([[0.0, 0.0, 0.5, -1.0], [1.0, 0.0, 0.5, -1.0], [0.0, 1.0, 0.5, -1.0]])
    assert (rasterize(back, torch.tensor([[0, 1, 2]]), (5, 7)).tri_id == -1).all()


def test_large_triangle_is_split_without_gaps(monkeypatch):
    # Force tiny blocks / chunks so that the row-band splitting and chunking
    # code paths run on a small image, and compare with the default path.
    import difftex.geometry.raster as R

    V, F = icosphere(2, dtype=torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    view[2, 3] = -1.6
    pos = camera.transform(V, camera.perspective(60.0, 1.0, 0.1, 10.0, degrees=True, dtype=torch.float64) @ view)
    ref = rasterize(pos, F, (40, 56))
    monkeypatch.setattr(R, "_MAX_BLOCK", 16)
    monkeypatch.setattr(R, "_CHUNK_CANDIDATES", 64)
    monkeypatch.setattr(R, "_MIN_BIN", 1000)
    got = rasterize(pos, F, (40, 56))
    assert torch.equal(ref.tri_id, got.tri_id)
    assert torch.equal(ref.bary, got.bary)


# --------------------------------------------------------------------------
# gradients


def _scene64(seed=0):
    V, F = icosphere(1, dtype=torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = random_rotation(torch.Generator().manual_seed(seed))
    view[2, 3] = -2.5
    pos = camera.transform(V, camera.perspective(50.0, 1.0, 0.5, 10.0, degrees=True, dtype=torch.float64) @ view)
    return pos, F


def test_gradcheck_bary_depth_and_derivatives_wrt_pos():
    pos, F = _scene64()
    H = W = 12
    frags = rasterize(pos, F, (H, W))
    # pixels well inside their triangle, so a 1e-6 nudge keeps visibility
    interior = (frags.tri_id >= 0) & (frags.bary.min(-1).values > 0.05)
    assert interior.sum() >= 10

    def fn(p):
        fr = rasterize(p, F, (H, W))
        assert torch.equal(fr.tri_id[interior], frags.tri_id[interior])
        return fr.bary[interior], fr.depth[interior], fr.bary_dx[interior], fr.bary_dy[interior]

    p = pos.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (p,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradients_only_reach_visible_vertices_and_background_is_zero():
    pos, F = _scene64(1)
    p = pos.clone().requires_grad_(True)
    frags = rasterize(p, F, (16, 16))
    (frags.bary.sum() + frags.depth.sum() + frags.bary_dx.abs().sum()).backward()
    g = p.grad
    assert torch.isfinite(g).all()
    visible = torch.zeros(len(pos), dtype=torch.bool)
    visible[F[frags.tri_id[frags.tri_id >= 0]].reshape(-1)] = True
    assert (g[~visible] == 0).all()
    assert (g[visible].abs().sum(-1) > 0).any()


# --------------------------------------------------------------------------
# degenerate input


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_behind_camera_and_huge_inputs_stay_finite(dtype):
    proj = camera.perspective(60.0, 1.0, 0.1, 100.0, degrees=True, dtype=torch.float64)
    world = torch.tensor(
        [
            # zero-area: repeated vertex, and collinear
            [0.0, 0.0, -2.0], [0.0, 0.0, -2.0], [0.5, 0.2, -2.0],
            [-0.5, -0.5, -2.0], [0.0, 0.0, -2.0], [0.5, 0.5, -2.0],
            # one corner behind the camera, one exactly in the eye plane
            [-0.4, -0.3, -1.0], [0.6, -0.3, -1.5], [0.1, 0.4, 3.0],
            [-0.4, 0.3, -1.0], [0.5, 0.3, 0.0], [0.0, -0.6, -1.2],
            # huge
            [-1e15, -1e15, -3.0], [1e15, -1e15, -3.0], [0.0, 1e15, -3.0],
        ],
        dtype=torch.float64,
    )
    pos = camera.transform(world, proj).to(dtype)
    pos = torch.cat((pos, torch.tensor([[1e30, 1e30, 1e30, 1e30], [-1e30, 1e30, 0.0, 1e30], [0.0, -1e30, 0.0, 1e30]], dtype=dtype)))
    faces = torch.arange(len(pos)).reshape(-1, 3)
    p = pos.clone().requires_grad_(True)
    frags = rasterize(p, faces, (24, 24))
    for t in (frags.bary, frags.depth, frags.bary_dx, frags.bary_dy):
        assert torch.isfinite(t).all()
    assert not ((frags.tri_id == 0) | (frags.tri_id == 1)).any()  # zero area covers nothing
    assert (frags.tri_id >= 0).float().mean() > 0.5
    (frags.bary.sum() + frags.depth.sum() + frags.bary_dx.sum() + frags.bary_dy.sum()).backward()
    assert torch.isfinite(p.grad).all()


# --------------------------------------------------------------------------
# bad input


def test_bad_input_errors_name_the_argument():
    pos = torch.rand(5, 4)
    faces = torch.tensor([[0, 1, 2], [2, 3, 4]])
    with pytest.raises(ValueError, match="faces.*\\[0, 4\\].*\\[0, 5\\]"):
        rasterize(pos, torch.tensor([[0, 1, 5]]), (4, 4))
    with pytest.raises(ValueError, match="faces"):
        rasterize(pos, torch.tensor([[0, -1, 2]]), (4, 4))
    with pytest.raises(ValueError, match="faces.*\\[F, 3\\]"):
        rasterize(pos, torch.tensor([0, 1, 2]), (4, 4))
    with pytest.raises(TypeError, match="faces.*integer"):
        rasterize(pos, faces.float(), (4, 4))
    with pytest.raises(ValueError, match="pos.*\\[B, V, 4\\]"):
        rasterize(torch.rand(5, 3), faces, (4, 4))
    with pytest.raises(ValueError, match="pos"):
        rasterize(torch.rand(1, 1, 5, 4), faces, (4, 4))
    with pytest.raises(TypeError, match="pos.*float32 or float64"):
        rasterize(pos.half(), faces, (4, 4))
    with pytest.raises(TypeError, match="pos.*float32 or float64"):
        rasterize(torch.ones(5, 4, dtype=torch.int64), faces, (4, 4))
    with pytest.raises(TypeError, match="pos"):
        rasterize(pos.numpy(), faces, (4, 4))
    bad = pos.clone()
    bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match="pos.*non-finite"):
        rasterize(bad, faces, (4, 4))
    bad[2, 1] = float("inf")
    with pytest.raises(ValueError, match="pos.*non-finite"):
        rasterize(bad, faces, (4, 4))
    with pytest.raises(ValueError, match="resolution"):
        rasterize(pos, faces, (0, 4))
    with pytest.raises(ValueError, match="resolution"):
        rasterize(pos, faces, 16)
    with pytest.raises(TypeError, match="resolution"):
        rasterize(pos, faces, (4.5, 4))
    with pytest.raises(TypeError, match=r"resolution must hold two ints, got \(inf, 4\)"):
        rasterize(pos, faces, (float("inf"), 4))


def test_public_api():
    assert difftex.rasterize is rasterize
    assert difftex.Fragments.__name__ == "Fragments"


# --------------------------------------------------------------------------
# devices


@pytest.mark.parametrize("device", DEVICES)
def test_same_result_on_every_device(device):
    pos, F = _scene64(2)
    ref = rasterize(pos, F, (24, 24))
    got = rasterize(pos.to(device), F.to(device), (24, 24))
    assert torch.equal(got.tri_id.cpu(), ref.tri_id)
    torch.testing.assert_close(got.bary.cpu(), ref.bary)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_float32_watertight():
    V, F = icosphere(3, dtype=torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    view[2, 3] = -3.0
    pos = camera.transform(V, camera.perspective(40.0, 1.0, 0.5, 10.0, degrees=True, dtype=torch.float64) @ view)
    count = _coverage_count(pos.float().cuda(), F.cuda(), (96, 96))
    assert set(count.unique().tolist()) <= {0, 2}


def _one_triangle(B=1, dtype=torch.float32):
    pos = torch.tensor([[-0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, 1.0], [0.0, 0.5, 0.0, 1.0]], dtype=dtype)
    return pos.expand(B, 3, 4), torch.tensor([[0, 1, 2]])


def test_memory_limit_names_resolution_and_batch(monkeypatch):
    # Under a 1 MiB limit: 64 x 64 (56 bytes a float32 pixel: 224 KiB) renders, 256 x 256 (3.5 MiB) and a
    # batch of 8 at 128 x 128 (7 MiB) raise before allocating anything; float64 pixels take 96 bytes.
    import difftex.geometry.raster as R
    monkeypatch.setattr(R, "MAX_BYTES", 1 << 20, raising=False)
    pos, faces = _one_triangle()
    assert rasterize(pos, faces, (64, 64)).mask.sum() > 0
    with pytest.raises(ValueError, match=r"resolution 256x256 with batch 1 needs at least 0\.0 GiB .*\(56 bytes a "
                                         r"pixel\), over the limit difftex\.geometry\.raster\.MAX_BYTES = 0\.0 GiB"):
        rasterize(pos, faces, (256, 256))
    with pytest.raises(ValueError, match=r"resolution 128x128 with batch 8 needs .*\(56 bytes a pixel\)"):
        rasterize(*_one_triangle(8), (128, 128))
    assert rasterize(pos, faces, (128, 128)).mask.sum() > 0  # 896 KiB in float32, 1.5 MiB in float64
    with pytest.raises(ValueError, match=r"resolution 128x128 with batch 1 .*\(96 bytes a pixel\)"):
        rasterize(*_one_triangle(1, torch.float64), (128, 128))


@pytest.mark.parametrize("resolution,B,gib", [((40000, 40000), 1, 83.4), ((1, 2**31 - 1), 1, 112.0),
                                              ((1024, 1024), 4096, 224.0)])
def test_default_memory_limit_refuses_what_cannot_fit(resolution, B, gib):
    # Under the 2**31-pixel guard but tens of GiB: these asked the allocator for 7-34 GB and failed
    # there, without naming the resolution; the default limit is 16 GiB.
    import difftex.geometry.raster as R
    assert R.MAX_BYTES == 16 << 30
    H, W = resolution
    with pytest.raises(ValueError, match=rf"resolution {H}x{W} with batch {B} needs at least {gib:.1f} GiB .*"
                                         r"MAX_BYTES = 16\.0 GiB"):
        rasterize(*_one_triangle(B), resolution)


@pytest.mark.parametrize("name", ["native", "reference"])
def test_bad_values_named_on_both_paths(name):
    # On the native path rasterize leaves the finiteness and index-range
    # passes to the kernel (which reads every vertex and triangle anyway)
    # and names the problem when it reports one: the same errors as the
    # torch path, also for a bad value in the second batch item and for a
    # bad index far past the kernel's first chunk of triangles.
    V, F = icosphere(4)
    pos = camera.transform(V, camera.perspective(45.0, 1.0, 0.1, 10.0, degrees=True)
                           @ camera.look_at(torch.tensor([0.0, 0.0, 3.0]), torch.zeros(3)))
    faces = torch.cat([F] * 4)  # 20,480 triangles: several chunks
    with use_backend(name):
        assert (rasterize(pos, faces, (16, 16)).tri_id >= 0).any()
        bad_faces = faces.clone()
        bad_faces[-1, 2] = len(pos)
        with pytest.raises(ValueError, match=f"faces indices must lie in \\[0, {len(pos) - 1}\\]"):
            rasterize(pos, bad_faces, (16, 16))
        bad_faces[-1, 2] = -3
        with pytest.raises(ValueError, match="faces indices must lie in .* got values in \\[-3, "):
            difftex.depth_peel(pos, bad_faces, (16, 16), 2)
        batch = torch.stack([pos, pos])
        batch[1, -1, 3] = float("nan")
        with pytest.raises(ValueError, match="pos contains non-finite"):
            rasterize(batch, faces, (16, 16))


def test_an_empty_batch_gives_empty_fragments():
    # The native kernel signals bad input with an empty result, which an empty batch also is.
    fr = difftex.rasterize(torch.zeros(0, 3, 4), torch.tensor([[0, 1, 2]]), (4, 5))
    assert fr.tri_id.shape == (0, 4, 5) and fr.bary.shape == (0, 4, 5, 3)


@pytest.mark.parametrize("dtype, scale", [(torch.float32, 1e-40), (torch.float64, 1e-310)])
def test_subnormal_corners_give_the_unit_triangles_values(dtype, scale):
    # 2^-e for a subnormal coordinate overflowed to inf, and inf * 0 made the barycentrics NaN.
    faces = torch.tensor([[0, 1, 2]])
    unit = torch.tensor([[[-1.0, -1, 0.5, 1], [1, -1, 0.5, 1], [0, 1, 0.5, 1]]], dtype=dtype)
    ref = difftex.rasterize(unit, faces, (4, 4))
    got = difftex.rasterize(unit * scale, faces, (4, 4))
    assert torch.equal(got.tri_id, ref.tri_id) and int((got.tri_id >= 0).sum()) == 8
    for name in ("bary", "bary_dx", "bary_dy", "depth"):
        torch.testing.assert_close(getattr(got, name), getattr(ref, name), rtol=0, atol=1e-6, msg=name)


def test_without_derivatives_same_values_and_gradients():
    # derivatives=False skips bary_dx / bary_dy (None) and changes nothing else, gradients included.
    pos, F = _scene64(2)
    p1 = pos.clone().requires_grad_(True)
    p2 = pos.clone().requires_grad_(True)
    full = rasterize(p1, F, (16, 16))
    lean = rasterize(p2, F, (16, 16), derivatives=False)
    assert lean.bary_dx is None and lean.bary_dy is None
    assert torch.equal(full.tri_id, lean.tri_id)
    assert torch.equal(full.bary, lean.bary) and torch.equal(full.depth, lean.depth)
    uv = torch.rand(pos.shape[0], 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    (full.bary.square().sum() + full.depth.sum() + interpolate(uv, F, full).sum()).backward()
    (lean.bary.square().sum() + lean.depth.sum() + interpolate(uv, F, lean).sum()).backward()
    torch.testing.assert_close(p2.grad, p1.grad, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="derivatives=True"):
        interpolate(uv, F, lean, derivatives=True)
    with pytest.raises(TypeError, match="derivatives must be a bool"):
        rasterize(pos, F, (4, 4), derivatives=1)

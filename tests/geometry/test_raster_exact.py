"""The exact rasterizer (issue 16): watertightness as a property, the native kernel against the torch path,
triangle ids against a float64 ray cast, depth peeling."""

from __future__ import annotations

import functools
import itertools

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import difftex
from difftex import camera, depth_peel, rasterize
from difftex.geometry.raster import SUBPIXEL_BITS, _coverage_count
from difftex.testing import icosphere
from difftex.testing.raycast import edge_distance, exact_bary, exact_bary_at, plane_depth, ray_cast
from tests.conftest import use_backend
from tests.geometry.raster_helpers import random_rotation

IMPLS = ("native", "reference")  # the C++ kernel and the torch path


def _camera(gen: torch.Generator, dist: float, fov: float, aspect: float = 1.0) -> torch.Tensor:
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = random_rotation(gen)
    view[:3, 3] = torch.tensor([0.0, 0.0, -dist], dtype=torch.float64) + 0.15 * torch.randn(
        3, generator=gen, dtype=torch.float64)
    return camera.perspective(fov, aspect, 0.05, 50.0, degrees=True, dtype=torch.float64) @ view


def _snap_to_centres(pos: torch.Tensor, H: int, W: int, frac: float, gen: torch.Generator) -> torch.Tensor:
    """Move a fraction of the vertices (in screen space, keeping w) onto the nearest pixel centre."""
    ndc = pos[:, :2] / pos[:, 3:]
    col = torch.round((ndc[:, 0] + 1) * W / 2 - 0.5)
    row = torch.round((1 - ndc[:, 1]) * H / 2 - 0.5)
    cx = (col + 0.5) / W * 2 - 1
    cy = 1 - (row + 0.5) / H * 2
    pick = torch.rand(len(pos), generator=gen, dtype=torch.float64) < frac
    out = pos.clone()
    out[pick, 0] = (cx * pos[:, 3])[pick]
    out[pick, 1] = (cy * pos[:, 3])[pick]
    return out


# --------------------------------------------------------------------------
# watertightness


@pytest.mark.parametrize("impl", IMPLS)
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1), sub=st.integers(1, 2), bumps=st.floats(0.0, 0.35),
       H=st.integers(9, 41), W=st.integers(9, 41), frac=st.floats(0.2, 1.0),
       dtype=st.sampled_from([torch.float32, torch.float64]))
def test_closed_mesh_covers_every_centre_once_per_layer(impl, seed, sub, bumps, H, W, frac, dtype):
    # A closed, possibly non-convex mesh (a bumpy icosphere) from a random
    # camera, with vertices moved exactly onto pixel centres on purpose
    # (edges and vertices then meet at centres). For any closed oriented
    # surface a generic ray enters as often as it leaves, and the fill rule
    # makes every centre a generic point: front-facing and back-facing
    # coverage counts are equal at every pixel (no hole: a missing fragment
    # breaks the balance; no double coverage: an extra one does).
    gen = torch.Generator().manual_seed(seed)
    V, F = icosphere(sub, dtype=torch.float64)
    V = V * (1 + bumps * torch.rand(len(V), 1, generator=gen, dtype=torch.float64))
    mvp = _camera(gen, 3.0, 35.0 + 20 * float(torch.rand(1, generator=gen)), W / H)
    pos = _snap_to_centres(camera.transform(V, mvp), H, W, frac, gen).to(dtype)
    with use_backend(impl):
        both = _coverage_count(pos, F, (H, W))[0]
        front = _coverage_count(pos, F, (H, W), cull_backfaces=True)[0]
        ids = rasterize(pos, F, (H, W)).tri_id[0]
    back = both - front
    assert torch.equal(front, back), f"{int((front != back).sum())} unbalanced pixels"
    assert front.sum() > 10
    # (No "at most once" even for bumps = 0: moving vertices onto centres can fold a coarse sphere over itself.)
    # The z-buffer shows a triangle exactly where something covers the centre.
    assert torch.equal(ids >= 0, front > 0)


@pytest.mark.parametrize("impl", IMPLS)
def test_quad_fan_meeting_at_one_centre(impl):
    # Eight triangles around a vertex placed exactly on a pixel centre, with
    # edges running exactly through other centres: each centre once.
    H = W = 7
    c = torch.tensor([[0.0, 0.0]], dtype=torch.float64)  # NDC of centre (3, 3)
    ring = torch.tensor([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1]],
                        dtype=torch.float64) * (6 / 7)  # vertices on centres 3 pixels away
    xy = torch.cat((c, ring))
    pos = torch.cat((xy, torch.zeros(9, 1, dtype=torch.float64), torch.ones(9, 1, dtype=torch.float64)), 1)
    faces = torch.tensor([[0, 1 + i, 1 + (i + 1) % 8] for i in range(8)])
    with use_backend(impl):
        for dtype in (torch.float32, torch.float64):
            count = _coverage_count(pos.to(dtype), faces, (H, W))[0]
            # The square spans centres 0..6: its interior ones exactly once, its
            # border ones (on the outer edges) 0 or 1 by the fill rule.
            assert (count[1:6, 1:6] == 1).all()
            assert int(count.max()) == 1


# --------------------------------------------------------------------------
# the two implementations agree


def _mixed_scene():
    """A sphere, a ground plane reaching behind the camera (float path) and coplanar ties."""
    V, F = icosphere(3, dtype=torch.float64)
    s = 40.0
    ground = torch.tensor([[-s, -1.0, -s], [s, -1.0, -s], [s, -1.0, s], [-s, -1.0, s]], dtype=torch.float64)
    gf = torch.tensor([[0, 2, 1], [0, 3, 2]]) + len(V)
    V = torch.cat((V, ground))
    F = torch.cat((F, gf))
    # a duplicate of the first 30 faces: exact depth ties, decided by id
    F = torch.cat((F, F[:30]))
    eye = torch.tensor([0.4, 0.3, 2.6], dtype=torch.float64)
    view = camera.look_at(eye, torch.tensor([0.0, -0.4, 0.0], dtype=torch.float64), (0.0, 1.0, 0.0))
    mvp = camera.perspective(70.0, 1.3, 0.05, 30.0, degrees=True, dtype=torch.float64) @ view
    pos = camera.transform(V, mvp)
    assert (pos[:, 3] < 0).any()
    return pos, F


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_native_kernel_matches_torch_path(dtype, cull):
    from difftex.geometry.raster import _visibility

    pos, F = _mixed_scene()
    pos = torch.stack((pos, pos * 1.5)).to(dtype)  # a batch of two (same NDC)
    H, W = 45, 61
    out = {}
    for impl in IMPLS:
        with use_backend(impl):
            ids, z = _visibility(pos, F, H, W, cull)
            ids2, z2 = _visibility(pos, F, H, W, cull, (z, torch.where(ids.reshape(-1) >= 0, ids.reshape(-1),
                                                                       torch.iinfo(torch.int64).max)))
            out[impl] = (ids, z, ids2, z2, _coverage_count(pos, F, (H, W), cull_backfaces=cull))
    for a, b in zip(out["native"], out["reference"]):
        assert torch.equal(a, b)
    ids = out["native"][0]
    assert (ids >= len(F) - 30).sum() == 0  # duplicates lose every tie to the lower id
    assert (ids == 1280).any() or (ids == 1281).any()  # the ground plane (float path) shows
    # Big triangles (the kernel solves each row's span instead of testing pixels), vertices on centres.
    V, F = icosphere(1, dtype=torch.float64)
    gen = torch.Generator().manual_seed(9)
    big = _snap_to_centres(camera.transform(V, _camera(gen, 1.8, 60.0, W / H)), H, W, 0.5, gen).to(dtype)[None]
    got = []
    for impl in IMPLS:
        with use_backend(impl):
            got.append((_visibility(big, F, H, W, cull), _coverage_count(big, F, (H, W), cull_backfaces=cull)))
    assert torch.equal(got[0][0][0], got[1][0][0]) and torch.equal(got[0][0][1], got[1][0][1])
    assert torch.equal(got[0][1], got[1][1])
    assert int((got[0][1] > 0).sum()) > H * W // 3


# --------------------------------------------------------------------------
# triangle ids against a float64 ray cast


# Issue 40's bounds on max_i |bary_i - exact_i| (median, 99.9 %, max) where the ids agree. float32: Mitsuba 3's
# float32 ray caster on icosphere(8) at 512^2 measured 1.1e-5 / 4.0e-4 / 6.5e-3 (spot: 1.7e-6 / 3.6e-5 / 6.3e-4);
# computed in float64 and rounded once, difftex's error is that rounding, at most half an ulp of 1 (6e-8), where
# the expanded edge functions gave 3e-4 / 4e-2 / 1.1. float64: near float64 exactness.
_BARY_BOUNDS = {torch.float32: (3e-8, 6e-8, 1.2e-7), torch.float64: (1e-14, 1e-12, 1e-11)}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("impl", IMPLS)
def test_barycentrics_match_a_float64_reference_on_subpixel_triangles(impl, dtype):
    # icosphere(6) at 128^2: 81,920 triangles of ~0.25 px each, seen from
    # 2.4 radii, where the edge functions a x + b y + c of the pixel cancel
    # to a few digits in float32.
    H = W = 128
    V, F = icosphere(6, dtype=torch.float64)
    gen = torch.Generator().manual_seed(7)
    pos = camera.transform(V, _camera(gen, 2.4, 50.0)).to(dtype)
    ref, _ = ray_cast(pos, F, (H, W))
    with use_backend(impl):
        fr = rasterize(pos, F, (H, W))
    ok = (fr.tri_id[0] == ref) & (ref >= 0)
    assert ok.sum() >= 0.99 * (ref >= 0).sum() and ok.sum() > 5000
    exact = exact_bary(pos, F, torch.where(ok, ref, -1), (H, W))
    err = (fr.bary[0].double() - exact).abs().amax(-1)[ok].sort().values
    med, q999, mx = float(err[(len(err) - 1) // 2]), float(err[int(0.999 * len(err))]), float(err[-1])
    bmed, bq, bmax = _BARY_BOUNDS[dtype]
    assert med <= bmed and q999 <= bq and mx <= bmax, f"median {med:.2e}, 99.9% {q999:.2e}, max {mx:.2e}"
    # The analytic screen-space derivatives agree with a central difference of the exact barycentrics (1e-3 px
    # either side; its truncation error is O(h^2) times the curvature of the perspective division).
    if dtype == torch.float64:
        rows, cols = torch.nonzero(ok, as_tuple=True)
        tri = ref[rows, cols]
        x = (cols.double() + 0.5) / W * 2 - 1
        y = 1 - (rows.double() + 0.5) / H * 2
        h = 1e-3  # pixels
        for d, (ux, uy) in ((fr.bary_dx[0], (2 / W, 0.0)), (fr.bary_dy[0], (0.0, -2 / H))):
            fd = (exact_bary_at(pos, F, tri, x + h * ux, y + h * uy)
                  - exact_bary_at(pos, F, tri, x - h * ux, y - h * uy)) / (2 * h)
            torch.testing.assert_close(d[rows, cols], fd, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("impl", IMPLS)
def test_ids_agree_with_float64_ray_cast(impl):
    # CI size: icosphere(6) (81,920 triangles, ~0.9 px each) at 256^2, in
    # float32 (float64 arithmetic inside). The size, icosphere(8) at
    # 512^2, is measured by experiments/studies/raster_accuracy.py (its
    # figure is in the README).
    H = W = 256
    V, F = icosphere(6, dtype=torch.float64)
    gen = torch.Generator().manual_seed(5)
    pos = camera.transform(V, _camera(gen, 2.4, 50.0)).float()
    ref, _ = ray_cast(pos, F, (H, W))
    with use_backend(impl):
        ids = rasterize(pos, F, (H, W)).tri_id[0]
    bad = torch.nonzero(ids != ref)
    agree = 1 - len(bad) / (H * W)
    assert agree >= 0.99995, f"{agree:.5%} agree"
    r, c = bad[:, 0], bad[:, 1]
    a, b = ids[r, c], ref[r, c]
    both = (a >= 0) & (b >= 0)
    # Both hit: the two triangles are at the same depth there (a shared edge
    # decided the other way by the snap), never a back face in front.
    za = plane_depth(pos, F, a[both], r[both], c[both], (H, W))
    zb = plane_depth(pos, F, b[both], r[both], c[both], (H, W))
    assert (za - zb).abs().max() <= 1e-6 if both.any() else True
    # One misses: the centre lies within the snap's reach of the hit triangle's edge.
    one = ~both
    hit = torch.where(a[one] >= 0, a[one], b[one])
    d = edge_distance(pos, F, hit, r[one], c[one], (H, W))
    assert (d <= 2.0 ** -SUBPIXEL_BITS).all() if one.any() else True


# --------------------------------------------------------------------------
# depth peeling


def _quads(depths, dtype=torch.float64):
    """Overlapping screen-aligned quads at the given NDC depths, each shifted right by 2 pixels of 16."""
    pos, faces = [], []
    for i, z in enumerate(depths):
        x0, x1 = -0.9 + 0.25 * i, 0.3 + 0.25 * i
        q = torch.tensor([[x0, -0.8], [x1, -0.8], [x1, 0.8], [x0, 0.8]], dtype=torch.float64)
        pos.append(torch.cat((q, torch.full((4, 1), z, dtype=torch.float64), torch.ones(4, 1, dtype=torch.float64)), 1))
        faces.append(torch.tensor([[0, 1, 2], [0, 2, 3]]) + 4 * i)
    return torch.cat(pos).to(dtype), torch.cat(faces)


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_depth_peel_layers_of_overlapping_quads(impl, dtype):
    depths = [0.3, -0.2, 0.6, 0.3]  # quads 0 and 3 coplanar: the lower id peels first
    pos, faces = _quads(depths, dtype)
    H, W = 8, 16
    with use_backend(impl):
        layers = depth_peel(pos, faces, (H, W), 5)
        first = rasterize(pos, faces, (H, W))
    assert len(layers) == 5
    for name in ("tri_id", "bary", "depth", "bary_dx", "bary_dy"):
        assert torch.equal(getattr(layers[0], name), getattr(first, name))
    # By hand: quad i covers columns [2i + 1, 2i + 9] (x from -0.9 + 0.25 i to
    # 0.3 + 0.25 i); every pixel lists the covering quads by (depth, id).
    xs = (torch.arange(W, dtype=torch.float64) + 0.5) / W * 2 - 1
    quad = [torch.div(layer.tri_id[0], 2, rounding_mode="floor").where(layer.tri_id[0] >= 0, -1) for layer in layers]
    for c in range(W):
        cover = [i for i in range(4) if -0.9 + 0.25 * i <= xs[c] <= 0.3 + 0.25 * i]
        order = sorted(cover, key=lambda i: (depths[i], i))
        for k in range(5):
            want = order[k] if k < len(order) else -1
            assert (quad[k][1:7, c] == want).all(), (c, k, quad[k][:, c].tolist(), order)
    for k, layer in enumerate(layers):
        m = layer.tri_id[0] >= 0
        zq = torch.tensor(depths, dtype=dtype)[torch.div(layer.tri_id[0][m], 2, rounding_mode="floor")]
        torch.testing.assert_close(layer.depth[0][m], zq)
    assert (layers[4].tri_id == -1).all()


@pytest.mark.parametrize("impl", IMPLS)
def test_depth_peel_of_a_sphere_and_its_gradients(impl):
    V, F = icosphere(2, dtype=torch.float64)
    gen = torch.Generator().manual_seed(2)
    pos = camera.transform(V, _camera(gen, 3.0, 40.0))
    H = W = 14
    with use_backend(impl):
        layers = depth_peel(pos, F, (H, W), 3)
        front = rasterize(pos, F, (H, W), cull_backfaces=True).tri_id
        back = rasterize(pos, F[:, [0, 2, 1]], (H, W), cull_backfaces=True).tri_id
    # A convex closed surface: layer 0 the front, layer 1 the back, layer 2 empty.
    assert torch.equal(layers[0].tri_id, front)
    assert torch.equal(layers[1].tri_id, back)
    assert (layers[2].tri_id == -1).all()
    assert bool((layers[1].depth[layers[1].mask] > layers[0].depth[layers[1].mask]).all())
    interior = layers[1].mask & (layers[1].bary.min(-1).values > 0.05)
    assert interior.sum() >= 5
    keep = interior.flatten().nonzero()[:4].flatten()  # a few pixels: gradcheck cost grows with the corners used
    interior = torch.zeros(interior.numel(), dtype=torch.bool).index_fill_(0, keep, True).view(interior.shape)

    # gradcheck over the corners of the back layer's triangles at those pixels only (fewer inputs)
    used = torch.unique(F[layers[1].tri_id[interior]])

    def fn(sub):
        p = pos.index_put((used,), sub)
        with use_backend(impl):
            fr = depth_peel(p, F, (H, W), 2)[1]
        assert torch.equal(fr.tri_id[interior], layers[1].tri_id[interior])
        return fr.bary[interior], fr.depth[interior], fr.bary_dx[interior]

    assert torch.autograd.gradcheck(fn, (pos[used].clone().requires_grad_(True),), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_depth_peel_bad_layers():
    pos, faces = _quads([0.0])
    with pytest.raises(ValueError, match="depth_peel: layers must be >= 1, got 0"):
        depth_peel(pos, faces, (4, 4), 0)
    with pytest.raises(TypeError, match="depth_peel: layers must be an int, got float"):
        depth_peel(pos, faces, (4, 4), 2.0)
    with pytest.raises(ValueError, match="resolution"):
        depth_peel(pos, faces, (0, 4), 2)
    assert difftex.depth_peel is depth_peel


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_native_barycentrics_and_gradients_match_torch_path(dtype):
    # The native forward of the differentiable pass against the torch formula,
    # and the kernel's hand-written adjoint against the torch formula
    # differentiated by autograd (first order; double backward is the torch
    # formula's in both). In float32 the two sum in different orders, so each
    # float32 gradient is held against the float64 one.
    pos, F = _mixed_scene()
    H, W = 33, 47
    res = {}
    for impl, dt in (("native", dtype), ("reference", dtype), ("reference", torch.float64)):
        p = pos.to(dt).clone().requires_grad_(True)
        with use_backend(impl):
            fr = rasterize(p, F, (H, W))
            val = difftex.interpolate(p[:, :2].square(), F, fr, derivatives=True)
        loss = sum((t * torch.linspace(0.5, 1.5, t.numel(), dtype=dt).view(t.shape)).sum()
                   for t in (fr.bary, fr.depth, fr.bary_dx, fr.bary_dy, *val))
        loss.backward()
        res[impl, dt] = (fr, p.grad)
    (a, ga), (b, gb) = res["native", dtype], res["reference", dtype]
    assert torch.equal(a.tri_id, b.tri_id)
    tol = dict(atol=1e-5, rtol=1e-5) if dtype == torch.float32 else dict(atol=1e-12, rtol=1e-12)
    for name in ("bary", "depth", "bary_dx", "bary_dy"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), **tol)
    if dtype == torch.float64:
        torch.testing.assert_close(ga, gb, **tol)
    else:
        exact = res["reference", torch.float64][1]
        err_native = (ga.double() - exact).abs().max()
        err_torch = (gb.double() - exact).abs().max()
        assert err_native <= 2 * err_torch + 1e-6 * exact.abs().max(), (err_native, err_torch)
        torch.testing.assert_close(ga.double(), exact, atol=1e-4 * exact.abs().max(), rtol=1e-3)
    assert ga.abs().sum() > 0


@pytest.mark.parametrize("impl", IMPLS)
def test_second_order_gradients_through_the_barycentric_pass(impl):
    pos = torch.tensor([[-0.7, -0.6, 0.1, 1.0], [0.8, -0.5, 0.3, 1.2], [0.1, 0.7, -0.2, 0.9]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    with use_backend(impl):
        m = rasterize(pos, faces, (6, 6)).bary.min(-1).values > 0.05
        assert m.sum() >= 4

        def fn(p):
            fr = rasterize(p, faces, (6, 6))
            return fr.bary[m], fr.depth[m], fr.bary_dx[m]

        assert torch.autograd.gradgradcheck(fn, (pos.clone().requires_grad_(True),), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_subpixel_bits_and_ray_cast_checks():
    from difftex.geometry.raster import _subpixel_bits

    # 16 bits up to 4096 pixels a side, then fewer so that pixel centres stay within 2**27 units, none past 2**28.
    assert [_subpixel_bits(1, n) for n in (1, 4096, 4097, 8192, 2**27, 2**28 + 1)] == [16, 16, 15, 15, 1, 0]
    pos = torch.tensor([[0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, -1.0], [0.0, 1.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="ray_cast: every vertex needs w > 0"):
        ray_cast(pos, torch.tensor([[0, 1, 2]]), (4, 4))


@pytest.mark.parametrize("cull", [False, True])
def test_kbuffer_layers_equal_layer_by_layer_peeling(cull):
    # depth_peel on the kernel keeps each pixel's K nearest fragments in one
    # pass (a k-buffer); the torch path peels one layer a pass behind a floor.
    # The ids must be the same, ties included (the mixed scene duplicates 30
    # faces: equal depths, decided by id, one per layer), also when the
    # k-buffer's layers are followed by floor-peeled ones.
    from difftex.geometry.raster import fragments_of, visible_layers

    pos, F = _mixed_scene()
    pos = torch.stack((pos, pos * 1.5)).float()
    H, W, K = 29, 37, 5
    with use_backend("reference"):
        ref_fr = depth_peel(pos, F, (H, W), K, cull_backfaces=cull)
    with use_backend("native"):
        got_fr = depth_peel(pos, F, (H, W), K, cull_backfaces=cull)
    ref, got = [fr.tri_id for fr in ref_fr], [fr.tri_id for fr in got_fr]
    # the values too: dense layers and mostly-background ones (zero-filled outputs)
    for a, b in zip(got_fr, ref_fr):
        for name in ("bary", "depth", "bary_dx", "bary_dy"):
            torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=2e-5, rtol=1e-5)
        mixed = [fr.tri_id for fr in itertools.islice(
            visible_layers(pos, F, (H, W), cull, fragments_of, at_once=2), K)]
    for k in range(K):
        assert torch.equal(got[k], ref[k]), k
        assert torch.equal(mixed[k], ref[k]), k
    assert (ref[1 if cull else 2] >= 0).sum() > 50  # deep layers are not empty (culled: sphere / twin, ground)
    assert (ref[0] >= 0).float().mean() > 0.5 > (ref[-1] >= 0).float().mean()  # both output strategies
    # a duplicated face (id 1282 + i duplicates i) comes right behind its twin
    twin = (ref[0] >= 0) & (ref[0] < 30)
    assert twin.any() and torch.equal(ref[1][twin], ref[0][twin] + len(F) - 30)


# --------------------------------------------------------------------------
# the triangle pass's eight-triangle AVX2 filter against its scalar tests


def _dense_scene(dtype):
    """Sub-pixel triangles (icosphere(5) at 40 x 52, half the corners on pixel centres: the fill rule decides),
    a second sphere reaching past the image border and through the near plane, and degenerate faces; and the
    first sphere in full view (farther away) on its own."""
    H, W = 40, 52
    V, F = icosphere(5, dtype=torch.float64)
    gen = torch.Generator().manual_seed(11)
    pos = _snap_to_centres(camera.transform(V, _camera(gen, 2.6, 50.0, W / H)), H, W, 0.5, gen)
    proj = camera.perspective(50.0, W / H, 0.05, 50.0, degrees=True, dtype=torch.float64)
    near = camera.transform(V * 1.2 + torch.tensor([0.6, 0.3, -1.0], dtype=torch.float64), proj)  # eye space
    assert (near[:, 3] < 0).any() and (near[:, 3] > 0).any()
    F2 = F + len(V)
    degenerate = torch.cat((F[:64, [0, 0, 1]], F[64:128, [1, 2, 2]]))  # a repeated corner: zero area
    # Vertices outside the vertex pass's exponent-bit scaling (zero; float64: subnormal, huge), among others
    # that are not: the four-vertex groups holding them take the scalar record.
    tiny = 1e-310 if dtype == torch.float64 else 0.0
    huge = 6e307 if dtype == torch.float64 else 1e30  # >= 2^1022, also doubled
    odd = torch.tensor([[0.0, 0.0, 0.0, 0.0], [tiny, -tiny, tiny, 2 * tiny], [0.1, 0.2, 0.5, 1.0],
                        [huge, 0.5 * huge, 0.1 * huge, huge]], dtype=torch.float64)
    base = 2 * len(V)
    odd_faces = torch.tensor([[0, 2, 3], [1, 2, 3], [0, 1, 2]]) + base
    inview = _snap_to_centres(camera.transform(V, _camera(gen, 4.5, 50.0, W / H)), H, W, 0.5, gen)
    return torch.cat((pos, near, odd)).to(dtype), torch.cat((F, F2, degenerate, odd_faces)), H, W, (inview.to(dtype), F)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_eight_triangle_filter_matches_scalar_path(dtype, cull):
    # raster.cpp dropped8 drops or lists most triangles of a dense mesh on
    # its own (outcodes, empty boxes, small boxes whose centres the exact
    # edge functions miss); both paths must give the same bits, in every
    # mode of the kernel (z-buffer, floor, count, k-buffer), and the torch
    # path's ids.
    from difftex.geometry.raster import _subpixel_bits, _visibility
    from difftex import _native as native

    kernel = native.load()
    if kernel is None:
        pytest.skip("the native kernel is unavailable")
    pos, F, H, W, (sphere_pos, sphere_F) = _dense_scene(dtype)
    pos = torch.stack((pos, pos * 2.0))  # a batch of two (same NDC)
    got = {}
    for simd in (True, False):
        before = kernel.set_simd(simd)
        try:
            with use_backend("native"):
                ids, z = _visibility(pos, F, H, W, cull)
                floor = (z, torch.where(ids.reshape(-1) >= 0, ids.reshape(-1), torch.iinfo(torch.int64).max))
                ids2, z2 = _visibility(pos, F, H, W, cull, floor)
                count = _coverage_count(pos, F, (H, W), cull_backfaces=cull)
                layers, zk = kernel.raster(pos, F, H, W, cull, _subpixel_bits(H, W), torch.empty(0, dtype=torch.float64),
                                           torch.empty(0, dtype=torch.int64), layers=3)
            got[simd] = (ids, z, ids2, z2, count, layers, zk)
        finally:
            kernel.set_simd(before)
    for a, b in zip(got[True], got[False]):
        assert torch.equal(a, b)
    # Chunks and vertex blocks are handed out to the threads as they come: the same bits on one or three.
    threads = torch.get_num_threads()
    try:
        for n in (1, 3):
            torch.set_num_threads(n)
            with use_backend("native"):
                ids_n, z_n = _visibility(pos, F, H, W, cull)
            assert torch.equal(ids_n, got[True][0]) and torch.equal(z_n, got[True][1])
    finally:
        torch.set_num_threads(threads)
    # The dense sphere alone is in full view: the filter then skips the outcodes (every vertex snapped, inside).
    sphere_pos = torch.stack((sphere_pos, 2 * sphere_pos))
    assert (sphere_pos[..., :3].abs() < sphere_pos[..., 3:]).all()
    alone = []
    for simd in (True, False):
        before = kernel.set_simd(simd)
        try:
            with use_backend("native"):
                alone.append(_visibility(sphere_pos, sphere_F, H, W, cull))
        finally:
            kernel.set_simd(before)
    assert torch.equal(alone[0][0], alone[1][0]) and torch.equal(alone[0][1], alone[1][1])
    assert (alone[0][0] >= 0).sum() > H * W // 5
    # A non-finite coordinate in a group of four is reported on both paths.
    bad = pos.clone()
    bad[1, 5, 2] = float("nan")
    for simd in (True, False):
        before = kernel.set_simd(simd)
        try:
            with use_backend("native"), pytest.raises(ValueError, match="pos.*non-finite"):
                rasterize(bad, F, (H, W))
        finally:
            kernel.set_simd(before)
    with use_backend("reference"):
        ref, zref = _visibility(pos, F, H, W, cull)
    assert torch.equal(got[True][0], ref) and torch.equal(got[True][1], zref)
    ids, count = got[True][0], got[True][4]
    assert (ids[0] >= 0).sum() > H * W // 3 and (count >= 2).sum() > H * W // 4  # the spheres cover much, in layers
    assert ((ids >= 0) & (ids < 20480)).sum() > H * W // 3  # the dense sphere (sub-pixel triangles) shows


@pytest.mark.parametrize("impl", IMPLS)
def test_depth_peel_and_peel_without_derivatives(impl):
    # derivatives=False leaves every layer's bary_dx / bary_dy None and changes nothing else, gradients included.
    pos, faces = _quads([0.3, -0.2, 0.6, 0.3])
    p1, p2, p3 = (pos.clone().requires_grad_(True) for _ in range(3))
    with use_backend(impl):
        full = depth_peel(p1, faces, (8, 16), 3)
        lean = depth_peel(p2, faces, (8, 16), 3, derivatives=False)
        lazy = list(itertools.islice(difftex.geometry.peel(p3, faces, (8, 16), derivatives=False), 3))
    for f, a, b in zip(full, lean, lazy):
        assert a.bary_dx is None and a.bary_dy is None and b.bary_dx is None and b.bary_dy is None
        for name in ("tri_id", "bary", "depth"):
            assert torch.equal(getattr(a, name), getattr(f, name)) and torch.equal(getattr(b, name), getattr(f, name))
    for p, layers in ((p1, full), (p2, lean), (p3, lazy)):
        sum(fr.bary.square().sum() + fr.depth.sum() for fr in layers).backward()
    torch.testing.assert_close(p2.grad, p1.grad, rtol=0, atol=1e-15)
    # peel's layers are separate autograd nodes: their gradients are summed in another order.
    torch.testing.assert_close(p3.grad, p1.grad, rtol=1e-14, atol=1e-15)
    with pytest.raises(TypeError, match="depth_peel: derivatives must be a bool"):
        depth_peel(pos, faces, (4, 4), 2, derivatives=1)
    with pytest.raises(TypeError, match="peel: derivatives must be a bool"):
        difftex.geometry.peel(pos, faces, (4, 4), derivatives=None)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_four_pixel_row_loop_matches_scalar_path(dtype, cull):
    # The z-buffer's AVX2 row loop (raster.cpp exact_row_avx2): the same ids and float64 depths as the scalar
    # loop and the torch path, on big triangles (spans solved per row), small ones (boxes tested per centre),
    # odd widths (masked lanes past the last column) and coplanar overlaps (ties go to the lowest id).
    from difftex.geometry.raster import _visibility
    from difftex import _native as native

    kernel = native.load()
    if kernel is None:
        pytest.skip("the native kernel is unavailable")
    gen = torch.Generator().manual_seed(5)
    V, F = icosphere(3, dtype=torch.float64)
    sphere = camera.transform(V, _camera(gen, 2.2, 50.0))
    quads, qf = _quads([0.3, -0.2, 0.6, 0.3], torch.float64)
    pos = torch.cat((sphere, quads)).to(dtype)
    faces = torch.cat((F, qf + V.shape[0]))
    for H, W in ((37, 53), (16, 16), (9, 130)):
        got = []
        for simd in (True, False):
            before = kernel.set_simd(simd)
            try:
                with use_backend("native"):
                    got.append(_visibility(pos[None], faces, H, W, cull))
                    got.append(rasterize(pos, faces, (H, W), cull_backfaces=cull))
            finally:
                kernel.set_simd(before)
        with use_backend("reference"):
            ref = _visibility(pos[None], faces, H, W, cull)
        assert torch.equal(got[0][0], got[2][0]) and torch.equal(got[0][1], got[2][1])
        assert torch.equal(got[0][0], ref[0]) and torch.equal(got[0][1], ref[1])
        for name in ("tri_id", "bary", "depth", "bary_dx", "bary_dy"):
            assert torch.equal(getattr(got[1], name), getattr(got[3], name)), name
        assert (got[0][0] >= 0).sum() > H * W // 4


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("derivatives", [True, False])
def test_fused_pass_matches_the_two_passes(dtype, derivatives):
    # rasterize on the kernel runs raster_fused (each band's fragments right after its z-buffer): the same ids,
    # values, compact copies and gradients as the visibility pass followed by fragments_of, on a batch of two.
    from difftex.geometry import raster as R

    gen = torch.Generator().manual_seed(7)
    V, F = icosphere(3, dtype=torch.float64)
    sphere = camera.transform(V, _camera(gen, 2.2, 50.0))
    quads, qf = _quads([0.3, -0.2, 0.6, 0.3], torch.float64)
    pos = torch.stack((torch.cat((sphere, quads)), 1.5 * torch.cat((quads.flip(0), sphere)))).to(dtype)
    faces = torch.cat((F, qf + V.shape[0]))
    H, W = 29, 35
    p1, p2 = pos.clone().requires_grad_(True), pos.clone().requires_grad_(True)
    with use_backend("native"):
        fused = rasterize(p1, faces, (H, W), derivatives=derivatives)
        two = next(R.visible_layers(p2, faces, (H, W), False, functools.partial(R.fragments_of,
                                                                              derivatives=derivatives)))
    for name in ("tri_id", "bary", "depth", "bary_dx", "bary_dy"):
        a, b = getattr(fused, name), getattr(two, name)
        assert (a is None and b is None) or torch.equal(a, b), name
    for a, b in zip(fused._compact, two._compact):
        assert (a is None and b is None) or torch.equal(a, b)
    uv = torch.rand(pos.shape[1], 2, generator=gen, dtype=dtype)
    for fr, p in ((fused, p1), (two, p2)):
        loss = fr.bary.square().sum() + fr.depth.sum() + difftex.interpolate(uv, faces, fr).square().sum()
        if derivatives:
            loss = loss + fr.bary_dx.abs().sum() + fr.bary_dy.square().sum()
        loss.backward()
    assert torch.equal(p1.grad, p2.grad)
    # The kernel's own input checks still name the problem.
    bad = pos.clone()
    bad[1, 3, 0] = float("nan")
    with use_backend("native"), pytest.raises(ValueError, match="pos.*non-finite"):
        rasterize(bad, faces, (H, W), derivatives=derivatives)
    with use_backend("native"), pytest.raises(ValueError, match="faces"):
        rasterize(pos, torch.cat((faces, torch.tensor([[0, 1, 10**6]]))), (H, W), derivatives=derivatives)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_depth_peel_matches_the_separate_passes(dtype):
    # depth_peel on the kernel: the k-buffer and every layer's fragments in one raster_fused call; the same
    # layers as the k-buffer visibility pass followed by fragments_of per layer, gradients included.
    from difftex.geometry import raster as R

    gen = torch.Generator().manual_seed(9)
    V, F = icosphere(3, dtype=torch.float64)
    sphere = camera.transform(V, _camera(gen, 2.2, 50.0))
    quads, qf = _quads([0.3, -0.2, 0.6, 0.3], torch.float64)
    pos = torch.stack((torch.cat((sphere, quads)), torch.cat((quads.flip(0), sphere)))).to(dtype)
    faces = torch.cat((F, qf + V.shape[0]))
    H, W, K = 21, 30, 4
    p1, p2 = pos.clone().requires_grad_(True), pos.clone().requires_grad_(True)
    with use_backend("native"):
        fused = depth_peel(p1, faces, (H, W), K)
        sep = list(itertools.islice(R.visible_layers(p2, faces, (H, W), False, R.fragments_of, at_once=K), K))
    assert (fused[2].tri_id >= 0).any()
    for a, b in zip(fused, sep):
        for name in ("tri_id", "bary", "depth", "bary_dx", "bary_dy"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        for x, y in zip(a._compact, b._compact):
            assert torch.equal(x, y)
    for layers, p in ((fused, p1), (sep, p2)):
        sum(fr.bary.square().sum() + fr.depth.sum() + fr.bary_dx.abs().sum() for fr in layers).backward()
    # The layers' gradients are summed in another order (float32: its rounding).
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(p1.grad, p2.grad, rtol=tol, atol=tol)

"""difftex.nvdiffrast against difftex's own ops through the convention changes (rows, NHWC, ids, barycentric order)."""
from __future__ import annotations

import math
import re

import pytest
import torch

import difftex
import difftex.nvdiffrast as dr
from difftex import camera
from difftex.testing.meshes import icosphere


def _scene(B: int = 2, dtype=torch.float32, subdivisions: int = 2):
    """Clip-space positions [B, V, 4] of an icosphere seen from B cameras, its faces int32, uv per vertex."""
    verts, faces = icosphere(subdivisions, dtype=torch.float64)
    proj = camera.perspective(40.0, 1.0, 0.5, 10.0, degrees=True, dtype=torch.float64)
    mats = []
    for b in range(B):
        a = 0.7 * b + 0.3
        eye = (3.2 * math.sin(a), 0.6 + 0.3 * b, 3.2 * math.cos(a))
        mats.append(proj @ camera.look_at(eye, dtype=torch.float64))
    pos = camera.transform(verts, torch.stack(mats)).to(dtype)
    uv = torch.stack([0.5 + 0.5 * torch.atan2(verts[:, 0], verts[:, 2]) / math.pi,
                      0.5 - 0.5 * verts[:, 1]], -1).to(dtype)
    return pos, faces.to(torch.int32), uv


CTX = dr.RasterizeCudaContext()


def test_rasterize_matches_difftex_with_nvdiffrast_conventions():
    pos, tri, _ = _scene(dtype=torch.float64)
    rast, db = dr.rasterize(CTX, pos, tri, (40, 48))
    frags = difftex.rasterize(pos, tri.long(), (40, 48))
    r = rast.flip(1)  # nvdiffrast row 0 is the bottom of the image
    found = frags.tri_id >= 0
    assert rast.shape == (2, 40, 48, 4) and db.shape == (2, 40, 48, 4)
    assert 0.2 < found.float().mean() < 0.9
    assert torch.equal(r[..., 3], torch.where(found, frags.tri_id + 1, 0).float())
    # rast comes from clip space mirrored in y, so the floats round differently (not the ids): float64.
    close = dict(atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(r[..., :2], frags.bary[..., :2], **close)
    torch.testing.assert_close(r[..., 2], frags.depth, **close)
    assert torch.equal(r[~found], torch.zeros_like(r[~found]))
    d = db.flip(1)
    torch.testing.assert_close(d[..., 0::2], frags.bary_dx[..., :2], **close)
    torch.testing.assert_close(d[..., 1::2], -frags.bary_dy[..., :2], **close)


def test_rast_bottom_row_is_ndc_y_minus_one():
    # A triangle covering only the lower half of NDC lands in rast's first rows.
    pos = torch.tensor([[[-1.0, -1.0, 0.0, 1.0], [1.0, -1.0, 0.0, 1.0], [0.0, -0.1, 0.0, 1.0]]])
    rast, _ = dr.rasterize(CTX, pos, torch.tensor([[0, 1, 2]], dtype=torch.int32), (8, 8))
    rows = (rast[0, :, :, 3] > 0).any(1)
    assert rows.tolist() == [True] * 3 + [False] * 5
    # First vertex (1, 0), second (0, 1): u weighs the left corner, v the right one.
    left, right = rast[0, 0, 1], rast[0, 0, 6]
    assert left[0] > 0.5 > left[1] and right[1] > 0.5 > right[0]


def test_range_mode_equals_instanced_pieces_with_global_ids():
    pos, tri, _ = _scene(B=1)
    half = tri.shape[0] // 2
    ranges = torch.tensor([[0, half], [half, tri.shape[0] - half]], dtype=torch.int32)
    rast, db = dr.rasterize(CTX, pos[0], tri, (32, 32), ranges=ranges)
    a, da = dr.rasterize(CTX, pos, tri[:half], (32, 32))
    b, dbb = dr.rasterize(CTX, pos, tri[half:], (32, 32))
    assert torch.equal(rast[0], a[0]) and torch.equal(db[0], da[0])
    shifted = torch.where(b[..., 3] > 0, b[..., 3] + half, 0)
    assert torch.equal(rast[1, ..., :3], b[0, ..., :3]) and torch.equal(rast[1, ..., 3], shifted[0])
    assert torch.equal(db[1], dbb[0])


def test_output_db_false_and_grad_db():
    pos, tri, _ = _scene(B=1)
    _, db = dr.rasterize(dr.RasterizeGLContext(output_db=False), pos, tri, (16, 16))
    assert db.shape == (1, 16, 16, 0)
    p = pos.clone().requires_grad_()
    _, db = dr.rasterize(CTX, p, tri, (16, 16), grad_db=False)
    assert not db.requires_grad
    rast, db = dr.rasterize(CTX, p, tri, (16, 16))
    assert db.requires_grad and rast.requires_grad


def test_interpolate_matches_difftex_values_and_derivatives():
    pos, tri, uv = _scene(dtype=torch.float64)
    attr = torch.cat([uv, torch.randn(uv.shape[0], 1, generator=torch.Generator().manual_seed(0), dtype=uv.dtype)], -1)
    rast, db = dr.rasterize(CTX, pos, tri, (36, 36))
    out, da = dr.interpolate(attr, rast, tri, rast_db=db, diff_attrs="all")
    frags = difftex.rasterize(pos, tri.long(), (36, 36))
    ref, rdx, rdy = difftex.interpolate(attr, tri.long(), frags, derivatives=True)
    torch.testing.assert_close(out.flip(1), ref, atol=1e-12, rtol=0)
    got = da.flip(1).view(2, 36, 36, 3, 2)
    torch.testing.assert_close(got[..., 0], rdx, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(got[..., 1], -rdy, atol=1e-12, rtol=1e-10)
    sel, sda = dr.interpolate(attr, rast, tri, rast_db=db, diff_attrs=[2])
    assert sda.shape == (2, 36, 36, 2) and torch.equal(sda, da[..., 4:6])
    _, none = dr.interpolate(attr, rast, tri)
    assert none.shape == (2, 36, 36, 0)


def test_interpolate_position_gradients_match_difftex():
    pos, tri, uv = _scene(B=1)
    w = torch.randn(1, 20, 20, 2, generator=torch.Generator().manual_seed(1))
    grads = []
    for compat in (True, False):
        p = pos.clone().requires_grad_()
        if compat:
            rast, db = dr.rasterize(CTX, p, tri, (20, 20))
            out, da = dr.interpolate(uv, rast, tri, db, "all")
            out, dxs = out.flip(1), da.flip(1)[..., [0, 2]]
        else:
            frags = difftex.rasterize(p, tri.long(), (20, 20))
            out, dxs, _ = difftex.interpolate(uv, tri.long(), frags, derivatives=True)
        (out * w).sum().add((dxs * w).sum() * 5).backward()
        grads.append(p.grad)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-5, rtol=1e-4)


def test_interpolate_gradcheck_float64():
    pos, tri, uv = _scene(B=1, dtype=torch.float64, subdivisions=1)
    rast, db = dr.rasterize(CTX, pos, tri, (10, 10))
    rast = rast.detach()
    uvr = rast[..., :2].clone().requires_grad_()
    attr = uv.clone().requires_grad_()
    dbr = db.detach().clone().requires_grad_()

    def f(a, u, d):
        r = torch.cat([u, rast[..., 2:]], -1)
        out, da = dr.interpolate(a, r, tri, d, "all")
        return out, da

    assert torch.autograd.gradcheck(f, (attr, uvr, dbr))


@pytest.mark.parametrize("mode,boundary", [("nearest", "wrap"), ("linear", "wrap"), ("linear", "clamp"),
                                           ("linear", "zero"), ("linear", ("mirror", "clamp"))])
def test_texture_single_level_matches_sample(mode, boundary):
    g = torch.Generator().manual_seed(2)
    tex = torch.rand(2, 16, 12, 3, generator=g)
    uv = torch.rand(2, 5, 7, 2, generator=g) * 1.6 - 0.3
    got = dr.texture(tex, uv, filter_mode=mode, boundary_mode=boundary)
    wrap = {"wrap": "repeat", "clamp": "clamp", "zero": "border", "mirror": "mirror"}
    pair = (boundary, boundary) if isinstance(boundary, str) else boundary
    ref = difftex.sample(tex.permute(0, 3, 1, 2), uv, filter={"nearest": "nearest", "linear": "bilinear"}[mode],
                         wrap=tuple(wrap[b] for b in pair))
    torch.testing.assert_close(got, ref.permute(0, 2, 3, 1), atol=0, rtol=0)


def test_zero_boundary_reads_zero_outside_and_clamp_holds_edge_centres():
    tex = torch.ones(1, 4, 4, 1)
    uv = torch.tensor([[[[-0.5, 0.5], [0.5, 0.5]]]])
    z = dr.texture(tex, uv, filter_mode="linear", boundary_mode="zero")
    c = dr.texture(tex * torch.arange(4.0).view(1, 1, 4, 1), torch.tensor([[[[-3.0, 0.5], [0.1, 0.5]]]]),
                   filter_mode="linear", boundary_mode="clamp")
    assert z.flatten().tolist() == [0.0, 1.0]
    assert c.flatten().tolist() == [0.0, 0.0]  # u = 0.1 lies left of texel 0's centre (0.125): clamped to it


@pytest.mark.parametrize("mode", ["linear-mipmap-linear", "linear-mipmap-nearest", "anisotropic"])
def test_texture_mip_filters_match_sample_with_uv_da(mode):
    g = torch.Generator().manual_seed(3)
    tex = torch.rand(1, 32, 16, 2, generator=g)
    uv = torch.rand(2, 6, 6, 2, generator=g)
    uv_da = torch.randn(2, 6, 6, 4, generator=g) * 0.05
    bias = torch.randn(2, 6, 6, generator=g) * 0.3
    got = dr.texture(tex, uv, uv_da, bias, filter_mode=mode)
    filt = {"linear-mipmap-linear": "trilinear", "linear-mipmap-nearest": "nearest-mip"}.get(mode, mode)
    ref = difftex.sample(tex.permute(0, 3, 1, 2), uv, filter=filt, uv_dx=uv_da[..., [0, 2]],
                         uv_dy=uv_da[..., [1, 3]], lod_bias=bias)
    torch.testing.assert_close(got, ref.permute(0, 2, 3, 1), atol=1e-6, rtol=0)
    # 'auto' with derivatives is linear-mipmap-linear, without them linear.
    if mode == "linear-mipmap-linear":
        torch.testing.assert_close(dr.texture(tex, uv, uv_da, bias), got, atol=0, rtol=0)
        torch.testing.assert_close(dr.texture(tex, uv), dr.texture(tex, uv, filter_mode="linear"), atol=0, rtol=0)


def test_mip_level_bias_alone_selects_the_level():
    g = torch.Generator().manual_seed(4)
    tex = torch.rand(1, 16, 16, 3, generator=g)
    uv = torch.rand(1, 4, 4, 2, generator=g)
    levels = difftex.mipmap(tex.permute(0, 3, 1, 2)).levels
    for lv in (0.0, 1.0, 2.0, 9.0):
        got = dr.texture(tex, uv, mip_level_bias=torch.full((1, 4, 4), lv), filter_mode="linear-mipmap-linear")
        ref = difftex.sample(levels[min(int(lv), 4)], uv, filter="bilinear")
        torch.testing.assert_close(got, ref.permute(0, 2, 3, 1), atol=1e-6, rtol=0)
    half = dr.texture(tex, uv, mip_level_bias=torch.full((1, 4, 4), 1.5))
    ref = 0.5 * (difftex.sample(levels[1], uv) + difftex.sample(levels[2], uv))
    torch.testing.assert_close(half, ref.permute(0, 2, 3, 1), atol=1e-6, rtol=0)


def test_construct_mip_custom_stack_and_max_mip_level():
    g = torch.Generator().manual_seed(5)
    tex = torch.rand(1, 16, 16, 1, generator=g)
    uv = torch.rand(1, 4, 4, 2, generator=g)
    bias = torch.full((1, 4, 4), 3.0)
    built = dr.texture(tex, uv, mip=dr.texture_construct_mip(tex), mip_level_bias=bias)
    torch.testing.assert_close(built, dr.texture(tex, uv, mip_level_bias=bias), atol=1e-7, rtol=0)
    capped = dr.texture(tex, uv, mip_level_bias=bias, max_mip_level=1)
    torch.testing.assert_close(capped, dr.texture(tex, uv, mip_level_bias=torch.ones(1, 4, 4)), atol=1e-7, rtol=0)
    # A custom stack: its tensors get their own gradient, the base none from them.
    t = tex.clone().requires_grad_()
    custom = [torch.full((1, 8, 8, 1), 0.25, requires_grad=True), torch.full((1, 4, 4, 1), 0.75, requires_grad=True)]
    out = dr.texture(t, uv, mip=custom, mip_level_bias=torch.full((1, 4, 4), 2.0))
    torch.testing.assert_close(out, torch.full_like(out, 0.75), atol=1e-7, rtol=0)
    out.sum().backward()
    assert custom[1].grad.sum().item() == pytest.approx(16.0)
    assert custom[0].grad is None or custom[0].grad.abs().sum() == 0
    assert t.grad is None or t.grad.abs().sum() == 0


def test_texture_gradcheck_float64():
    g = torch.Generator().manual_seed(6)
    tex = torch.rand(1, 8, 8, 2, generator=g, dtype=torch.float64, requires_grad=True)
    uv = (torch.rand(1, 3, 3, 2, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    da = (torch.randn(1, 3, 3, 4, generator=g, dtype=torch.float64) * 0.2).requires_grad_()
    assert torch.autograd.gradcheck(lambda t, u, d: dr.texture(t, u, d, filter_mode="linear-mipmap-linear"),
                                    (tex, uv, da))


def test_cube_texture_matches_cubemap():
    g = torch.Generator().manual_seed(7)
    cube = torch.rand(1, 6, 8, 8, 3, generator=g)
    dirs = torch.randn(2, 5, 5, 3, generator=g)
    got = dr.texture(cube, dirs, filter_mode="linear", boundary_mode="cube")
    ref = difftex.envmap.cubemap(cube.permute(0, 1, 4, 2, 3), dirs, filter="bilinear")
    torch.testing.assert_close(got, ref.permute(0, 2, 3, 1), atol=0, rtol=0)
    da = torch.randn(2, 5, 5, 6, generator=g) * 0.1
    got = dr.texture(cube, dirs, da, boundary_mode="cube")
    ref = difftex.envmap.cubemap(cube.permute(0, 1, 4, 2, 3), dirs, filter="trilinear",
                                 dirs_dx=da[..., 0::2], dirs_dy=da[..., 1::2])
    torch.testing.assert_close(got, ref.permute(0, 2, 3, 1), atol=1e-6, rtol=0)
    zero = dr.texture(cube, torch.zeros(1, 1, 1, 3), boundary_mode="cube")
    assert zero.abs().sum() == 0


def test_cube_bias_alone_reads_that_level():
    g = torch.Generator().manual_seed(8)
    cube = torch.rand(1, 6, 8, 8, 1, generator=g)
    dirs = torch.randn(1, 6, 6, 3, generator=g)
    levels = difftex.envmap.cube_mipmap(cube.permute(0, 1, 4, 2, 3)).levels
    got = dr.texture(cube, dirs, mip_level_bias=torch.full((1, 6, 6), 1.0), boundary_mode="cube")
    ref = difftex.envmap.cubemap(levels[1], dirs, filter="bilinear")
    torch.testing.assert_close(got, ref.permute(0, 2, 3, 1), atol=1e-6, rtol=0)
    bias = torch.full((1, 6, 6), 1.25, requires_grad=True)
    got = dr.texture(cube, dirs, mip_level_bias=bias, boundary_mode="cube")
    ref = 0.75 * ref + 0.25 * difftex.envmap.cubemap(levels[2], dirs, filter="bilinear")
    torch.testing.assert_close(got, ref.permute(0, 2, 3, 1), atol=1e-6, rtol=0)
    got.sum().backward()
    assert bias.grad.abs().sum() > 0


@pytest.mark.parametrize("call,exc,match", [
    (lambda p, t: dr.rasterize(CTX, p, t.long(), (8, 8)), TypeError, r"tri: expected dtype torch.int32"),
    (lambda p, t: dr.rasterize(None, p, t, (8, 8)), TypeError, r"glctx: expected a RasterizeCudaContext"),
    (lambda p, t: dr.rasterize(CTX, p[0], t, (8, 8)), ValueError, r"ranges: required in range mode"),
    (lambda p, t: dr.rasterize(CTX, p[..., :3], t, (8, 8)), ValueError, r"pos: expected last dimension 4"),
    (lambda p, t: dr.rasterize(CTX, p, t + 1000, (8, 8)), ValueError, r"tri: indices must lie in"),
    (lambda p, t: dr.rasterize(CTX, p[0], t, (8, 8), ranges=torch.tensor([[0, 10**6]], dtype=torch.int32)),
     ValueError, r"ranges: range \(start 0, count 1000000\)"),
    (lambda p, t: dr.texture(torch.rand(1, 4, 4, 1), torch.rand(1, 2, 2, 2), filter_mode="cubic"),
     ValueError, r"filter_mode: expected one of"),
    (lambda p, t: dr.texture(torch.rand(1, 4, 4, 1), torch.rand(1, 2, 2, 2), boundary_mode="border"),
     ValueError, r"boundary_mode: expected"),
    (lambda p, t: dr.texture(torch.rand(1, 4, 4, 1), torch.rand(1, 2, 2, 2), filter_mode="linear-mipmap-linear"),
     ValueError, r"uv_da: filter_mode 'linear-mipmap-linear' needs uv_da or mip_level_bias"),
    (lambda p, t: dr.texture(torch.rand(1, 4, 4, 1), torch.rand(1, 2, 2, 2), torch.rand(1, 2, 2, 2)),
     ValueError, r"uv_da: expected shape \[1, 2, 2, 4\]"),
    (lambda p, t: dr.texture(torch.rand(1, 6, 4, 4, 1), torch.rand(1, 2, 2, 3)), ValueError, r"tex: expected 4-D"),
    (lambda p, t: dr.texture(torch.rand(1, 6, 4, 5, 1), torch.rand(1, 2, 2, 3), boundary_mode="cube"),
     ValueError, r"tex: a cube map needs 6 square faces"),
    (lambda p, t: dr.interpolate(torch.rand(5, 2), torch.zeros(1, 4, 4, 4), t), ValueError,
     r"tri: indices must lie in \[0, 4\]"),
    (lambda p, t: dr.interpolate(torch.rand(162, 2), torch.zeros(1, 4, 4, 4), t, torch.zeros(1, 4, 4, 4), [7]),
     ValueError, r"diff_attrs: indices must lie in \[0, 1\]"),
    (lambda p, t: dr.set_log_level("info"), TypeError, r"level: expected an int"),
])
def test_bad_input_raises_naming_the_argument(call, exc, match):
    pos, tri, _ = _scene(B=1)
    with pytest.raises(exc, match=match):
        call(pos, tri)


def test_interpolate_rejects_ids_past_tri():
    rast = torch.zeros(1, 2, 2, 4)
    rast[0, 0, 0, 3] = 50.0
    with pytest.raises(ValueError, match=r"rast: triangle id 50 exceeds tri's 2 triangles"):
        dr.interpolate(torch.rand(4, 2), rast, torch.tensor([[0, 1, 2], [1, 2, 3]], dtype=torch.int32))


def test_log_level_and_contexts():
    old = dr.get_log_level()
    assert old == 1
    dr.set_log_level(2)
    assert dr.get_log_level() == 2
    dr.set_log_level(old)
    ctx = dr.RasterizeGLContext(mode="manual", device="cpu")
    ctx.set_context()
    ctx.release_context()
    assert ctx.device == torch.device("cpu") and ctx.output_db
    with pytest.raises(ValueError, match="mode: expected 'automatic' or 'manual'"):
        dr.RasterizeGLContext(mode="other")


def test_public_names_are_nvdiffrasts_eleven():
    assert sorted(dr.__all__) == sorted([
        "RasterizeCudaContext", "RasterizeGLContext", "rasterize", "DepthPeeler", "interpolate", "texture",
        "texture_construct_mip", "antialias", "antialias_construct_topology_hash", "get_log_level",
        "set_log_level"])
    assert all(callable(getattr(dr, n)) for n in dr.__all__)


def test_port_script_in_nvdiffrast_style_trains():
    # Written the way nvdiffrast scripts are (NHWC, int32 tri, rast[..., -1:] as the coverage mask);
    # only the import and the device differ.
    device = "cuda" if torch.cuda.is_available() else "cpu"
    glctx = dr.RasterizeCudaContext(device=device)
    pos, tri, uv = _scene(B=4)
    pos, tri, uv = pos.to(device), tri.to(device), uv.to(device)
    s = torch.linspace(0, 1, 32, device=device)
    tex_ref = torch.stack([torch.sin(12 * s)[:, None] * torch.cos(9 * s)[None, :] * 0.5 + 0.5,
                           (s[:, None] + s[None, :]) / 2,
                           torch.cos(7 * s)[:, None].expand(32, 32) * 0.5 + 0.5], -1)[None]

    def render(tex):
        rast, rast_db = dr.rasterize(glctx, pos, tri, resolution=[48, 48])
        texc, texd = dr.interpolate(uv[None, ...], rast, tri, rast_db=rast_db, diff_attrs="all")
        color = dr.texture(tex, texc, texd, filter_mode="linear-mipmap-linear", max_mip_level=3)
        color = color * torch.clamp(rast[..., -1:], 0, 1)
        return dr.antialias(color, rast, pos, tri)

    target = render(tex_ref)
    tex = torch.full_like(tex_ref, 0.5, requires_grad=True)
    opt = torch.optim.Adam([tex], lr=0.05)
    losses = []
    for _ in range(60):
        loss = torch.mean((render(tex) - target) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


def test_antialias_matches_difftex_and_passes_position_gradients():
    pos, tri, uv = _scene(B=2)
    g = torch.Generator().manual_seed(9)
    rast, _ = dr.rasterize(CTX, pos, tri, (32, 32))
    color = torch.rand(2, 32, 32, 3, generator=g)
    p = pos.clone().requires_grad_()
    got = dr.antialias(color, rast, p, tri, topology_hash=dr.antialias_construct_topology_hash(tri))
    frags = difftex.rasterize(pos, tri.long(), (32, 32))
    q = pos.clone().requires_grad_()
    ref = difftex.antialias(color.flip(1).permute(0, 3, 1, 2), frags, q, tri.long())
    torch.testing.assert_close(got, ref.permute(0, 2, 3, 1).flip(1), atol=1e-6, rtol=0)
    assert (got - color).abs().amax() > 0.05  # silhouettes were blended
    w = torch.rand(2, 32, 32, 3, generator=g)
    (got * w).sum().backward()
    (ref.permute(0, 2, 3, 1).flip(1) * w).sum().backward()
    torch.testing.assert_close(p.grad, q.grad, atol=1e-5, rtol=1e-4)
    assert p.grad.abs().sum() > 0
    boosted = pos.clone().requires_grad_()
    (dr.antialias(color, rast, boosted, tri, pos_gradient_boost=3.0) * w).sum().backward()
    torch.testing.assert_close(boosted.grad, 3 * q.grad, atol=1e-5, rtol=1e-4)


def test_depth_peeler_layers_match_depth_peel():
    pos, tri, _ = _scene(B=2, subdivisions=1, dtype=torch.float64)
    ref = difftex.depth_peel(pos, tri.long(), (24, 24), 3)
    with dr.DepthPeeler(CTX, pos, tri, (24, 24)) as peeler:
        layers = [peeler.rasterize_next_layer() for _ in range(4)]
    first, _ = dr.rasterize(CTX, pos, tri, (24, 24))
    assert torch.equal(layers[0][0], first)
    for (rast, db), frags in zip(layers, ref):
        r = rast.flip(1)
        assert torch.equal(r[..., 3], torch.where(frags.tri_id >= 0, frags.tri_id + 1, 0).float())
        torch.testing.assert_close(r[..., :2], frags.bary[..., :2], atol=1e-12, rtol=1e-10)
    assert (layers[1][0][..., 3] > 0).sum() > 0.5 * (layers[0][0][..., 3] > 0).sum()  # a sphere: back faces
    assert layers[3][0].abs().sum() == 0  # a closed convex mesh has two layers
    with pytest.raises(RuntimeError, match="inside `with DepthPeeler"):
        peeler.rasterize_next_layer()
    # Range mode peels each range on its own and offsets its ids.
    half = tri.shape[0] // 2
    ranges = torch.tensor([[0, half], [half, tri.shape[0] - half]], dtype=torch.int32)
    with dr.DepthPeeler(CTX, pos[0], tri, (24, 24), ranges=ranges) as peeler:
        peeler.rasterize_next_layer()
        second, _ = peeler.rasterize_next_layer()
    one = difftex.depth_peel(pos[:1], tri[half:].long(), (24, 24), 2)[1]
    assert torch.equal(second[1].flip(0)[..., 3], torch.where(one.tri_id[0] >= 0, one.tri_id[0] + 1 + half, 0).float())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_native_packed_pass_matches_the_torch_path(dtype):
    # rasterize / DepthPeeler write nvdiffrast's layout straight from the native
    # kernel on the CPU; the torch path packs difftex fragments. Both must give
    # the same (rast, rast_db), range offsets, peeled layers and gradients.
    from tests.conftest import use_backend

    pos, tri, _ = _scene(B=3, dtype=dtype)
    flat = pos[0]
    ranges = torch.tensor([[0, 200], [150, 170]], dtype=torch.int32)
    res = {}
    for impl in ("native", "reference"):
        p = pos.clone().requires_grad_(True)
        q = flat.clone().requires_grad_(True)
        with use_backend(impl):
            outs = list(dr.rasterize(CTX, p, tri, (37, 29)))
            outs += dr.rasterize(CTX, q, tri, (21, 26), ranges=ranges)
            with dr.DepthPeeler(CTX, p, tri, (19, 23)) as peeler:
                for _ in range(2):
                    outs += peeler.rasterize_next_layer()
        w = [torch.linspace(-1, 1, t.numel(), dtype=dtype).view(t.shape) for t in outs]
        loss = sum((t * k).sum() for t, k in zip(outs, w))
        gp, gq = torch.autograd.grad(loss, (p, q), create_graph=True)
        # second order: a gradient of the gradient's norm
        gg, = torch.autograd.grad(gp.square().sum(), p)
        res[impl] = (outs, gp, gq, gg)
    tol = dict(atol=2e-5, rtol=1e-5) if dtype == torch.float32 else dict(atol=1e-12, rtol=1e-10)
    (a, *ga), (b, *gb) = res["native"], res["reference"]
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, **tol)
    for x, y in zip(a[0::2], b[0::2]):  # rast: the ids exactly
        assert torch.equal(x[..., 3], y[..., 3])
    ids = a[2][..., 3]  # range mode: ids index the whole tri (range 1 starts at 150)
    assert 0 < ids[0][ids[0] > 0].min() and ids[0].max() <= 200
    assert 150 < ids[1][ids[1] > 0].min() and ids[1].max() <= 320
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, **tol)
        assert x.abs().sum() > 0


def test_interpolate_reuses_rasterize_coverage_only_while_rast_is_unchanged():
    # rasterize hands interpolate its covered pixels; an in-place change of
    # rast (version counter) or a copy must fall back to reading rast's ids.
    pos, tri, uv = _scene()
    rast, db = dr.rasterize(CTX, pos, tri, (24, 28))
    fresh = rast.clone()  # no cached coverage
    a, _ = dr.interpolate(uv, rast, tri)
    b, _ = dr.interpolate(uv, fresh, tri)
    assert torch.equal(a, b) and a.abs().sum() > 0
    with torch.no_grad():
        rast[:, :12, :, 3] = 0  # drop the lower half's triangles
    c, _ = dr.interpolate(uv, rast, tri)
    assert torch.equal(c[:, :12], torch.zeros_like(c[:, :12]))
    assert torch.equal(c[:, 12:], a[:, 12:])
    with torch.inference_mode():  # no version counter there: no cache, the same values
        r, _ = dr.rasterize(CTX, pos, tri, (24, 28))
        d, _ = dr.interpolate(uv, r, tri)
    assert torch.equal(d, a)


def test_empty_diff_attrs_and_empty_ranges():
    # nvdiffrast takes diff_attrs=[] as None; ranges [0, 2] is a minibatch of none.
    pos = torch.tensor([[-0.8, -0.8, 0.0, 1.0], [0.8, -0.8, 0.0, 1.0], [0.0, 0.8, 0.0, 1.0]])
    tri = torch.tensor([[0, 1, 2]], dtype=torch.int32)
    rast, db = dr.rasterize(CTX, pos[None], tri, (4, 4))
    out, da = dr.interpolate(torch.rand(3, 2), rast, tri, db, diff_attrs=[])
    assert out.shape == (1, 4, 4, 2) and da.shape == (1, 4, 4, 0)
    rast, db = dr.rasterize(CTX, pos, tri, (4, 4), ranges=torch.zeros(0, 2, dtype=torch.int32))
    assert rast.shape == (0, 4, 4, 4) and db.shape == (0, 4, 4, 4)


def test_cube_mip_nearest_rounds_half_levels_as_2d():
    # The cube path once rounded half to even (level 0.5 -> 0), the 2D path half up (-> 1).
    from difftex.envmap.cube import cube_mipmap
    g = torch.Generator().manual_seed(13)
    cube = torch.rand(1, 6, 16, 16, 1, generator=g, dtype=torch.float64)
    d = torch.tensor([[[[0.31, -0.17, -1.0]]]], dtype=torch.float64)
    levels = cube_mipmap(cube.permute(0, 1, 4, 2, 3)).levels
    for bias, k in ((0.5, 1), (1.49, 1), (2.5, 3)):
        got = dr.texture(cube, d, mip_level_bias=torch.full((1, 1, 1), bias, dtype=torch.float64),
                         filter_mode="linear-mipmap-nearest", boundary_mode="cube")
        ref = dr.texture(levels[k].permute(0, 1, 3, 4, 2).contiguous(), d, filter_mode="linear", boundary_mode="cube")
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)


def test_cube_bias_gradient_is_the_derivative_from_below():
    # The tent weights were differentiated at their kinks: 0 at an integer level unless another pixel read the
    # neighbouring levels (then about v_(k+1) - v_(k-1)), and v_1 at level 0. DESIGN.md: v_k - v_(k-1), 0 at 0.
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(1, 6, 8, 8, 3, generator=g, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(1, 1, 2, 3, generator=g, dtype=torch.float64), dim=-1)
    f = lambda b: dr.texture(tex, d, mip_level_bias=b, filter_mode="linear-mipmap-linear", boundary_mode="cube")
    for bias in ([1.0, 1.0], [1.0, 2.5], [0.0, 1.5], [1.5, 3.0]):
        b = torch.tensor(bias, dtype=torch.float64).view(1, 1, 2).requires_grad_()
        f(b)[..., 0].sum().backward()
        below = (f(b.detach()) - f(b.detach() - 1e-6))[..., 0].flatten() / 1e-6
        torch.testing.assert_close(b.grad.flatten(), below, atol=1e-6, rtol=0, msg=str(bias))
        assert bias[0] > 0 or b.grad.flatten()[0] == 0


def test_a_custom_mip_level_of_the_wrong_shape_is_named_in_its_layout():
    tex = torch.rand(1, 8, 8, 3)
    uv = torch.rand(1, 2, 2, 2)
    for bad in (torch.rand(1, 3, 4, 3), torch.rand(1, 4, 4, 2)):
        with pytest.raises(ValueError, match=r"mip\[0\]: level 1 must be \[1, 4, 4, 3\] \(the layout of tex\), got "
                                             + re.escape(f"shape {tuple(bad.shape)}")):
            dr.texture(tex, uv, mip=[bad], mip_level_bias=torch.ones(1, 2, 2), filter_mode="linear-mipmap-linear")

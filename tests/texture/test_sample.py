"""difftex.sample with the single-level filters: values and gradients against
grid_sample and kornia, gradcheck, wrap modes per axis, bad input, NaN."""

import kornia
import pytest
import torch
import torch.nn.functional as F

import difftex
from tests.conftest import use_backend
from difftex.texture.options import FILTERS, MIP_FILTERS

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
GS_MODE = {"nearest": "nearest", "bilinear": "bilinear", "bicubic": "bicubic"}
# difftex wrap mode -> grid_sample padding_mode (align_corners=False)
GS_PAD = {"border": "zeros", "clamp": "border", "mirror": "reflection"}
SIZES = [(7, 10), (8, 8), (5, 1), (1, 6)]


@pytest.fixture(params=["grid_sample", "reference"], autouse=True)
def impl(request):
    """Every test runs on the grid_sample-based fast path and on the gather
    reference (``difftex.backend``); double backward always uses the reference."""
    with use_backend(request.param):
        yield request.param


def _rand_case(seed, tex_hw, B=2, C=3, out_hw=(6, 5), lo=-1.5, hi=2.5, dtype=torch.float64, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    tex = torch.rand(B, C, *tex_hw, generator=g, dtype=dtype).to(device)
    uv = (torch.rand(B, *out_hw, 2, generator=g, dtype=dtype) * (hi - lo) + lo).to(device)
    return tex, uv


def _grads(fn, tex, uv):
    tex = tex.clone().requires_grad_()
    uv = uv.clone().requires_grad_()
    out = fn(tex, uv)
    g = torch.randn(out.shape, dtype=out.dtype, device=out.device)  # not randn_like: it follows strides
    gt, gu = torch.autograd.grad(out, (tex, uv), g, allow_unused=True)
    return out, gt, gu if gu is not None else torch.zeros_like(uv)


def _repeat_reference(tex, uv, mode):
    """grid_sample on the texture tiled 5x5 with uv reduced into the middle tile.

    3x3 tiles suffice for textures of 2 or more texels a side; bicubic's reach
    of 2 texels needs 5x5 when a side is 1 texel.
    """
    tiled = tex.repeat(1, 1, 5, 5)
    uv_mid = (uv - torch.floor(uv) + 2) / 5  # the fractional part, in tile (2, 2)
    return F.grid_sample(tiled, 2 * uv_mid - 1, mode=GS_MODE[mode], padding_mode="zeros", align_corners=False)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("tex_hw", SIZES)
@pytest.mark.parametrize("wrap", ["border", "clamp", "mirror"])
@pytest.mark.parametrize("filt", ["nearest", "bilinear", "bicubic"])
def test_values_and_grads_match_grid_sample(filt, wrap, tex_hw, device):
    tex, uv = _rand_case(1, tex_hw, device=device)
    gs = lambda t, u: F.grid_sample(t, 2 * u - 1, mode=GS_MODE[filt], padding_mode=GS_PAD[wrap], align_corners=False)
    ours = lambda t, u: difftex.sample(t, u, filter=filt, wrap=wrap)
    torch.manual_seed(0)
    o1, gt1, gu1 = _grads(ours, tex, uv)
    torch.manual_seed(0)
    o2, gt2, gu2 = _grads(gs, tex, uv)
    assert o1.shape == o2.shape
    torch.testing.assert_close(o1, o2, atol=1e-6, rtol=0)
    torch.testing.assert_close(gt1, gt2, atol=1e-6, rtol=0)
    torch.testing.assert_close(gu1, gu2, atol=1e-6, rtol=0)


@pytest.mark.parametrize("tex_hw", SIZES)
@pytest.mark.parametrize("filt", ["nearest", "bilinear", "bicubic"])
def test_repeat_matches_tiled_grid_sample(filt, tex_hw):
    # uv spans several periods; the reference reduces it to the middle tile,
    # whose neighbours hold every tap of the kernel.
    tex, uv = _rand_case(2, tex_hw, lo=-3.0, hi=4.0)
    torch.manual_seed(0)
    o1, gt1, gu1 = _grads(lambda t, u: difftex.sample(t, u, filter=filt, wrap="repeat"), tex, uv)
    torch.manual_seed(0)
    o2, gt2, gu2 = _grads(lambda t, u: _repeat_reference(t, u, filt), tex, uv)
    torch.testing.assert_close(o1, o2, atol=1e-6, rtol=0)
    torch.testing.assert_close(gt1, gt2, atol=1e-6, rtol=0)
    torch.testing.assert_close(gu1, gu2, atol=1e-6, rtol=0)


def test_repeat_is_periodic_far_from_origin():
    tex, uv = _rand_case(3, (6, 9))
    a = difftex.sample(tex, uv, filter="bicubic", wrap="repeat")
    b = difftex.sample(tex, uv + torch.tensor([1000.0, -2000.0], dtype=uv.dtype), filter="bicubic", wrap="repeat")
    torch.testing.assert_close(a, b, atol=1e-9, rtol=0)


@pytest.mark.parametrize("filt,mode", [("bilinear", "bilinear"), ("nearest", "nearest")])
@pytest.mark.parametrize("wrap", ["border", "clamp", "mirror"])
def test_values_match_kornia_remap(filt, mode, wrap):
    # kornia's remap with pixel coordinates normalises them corner-aligned
    # while sampling with align_corners=False (kornia issue 4504); normalised
    # coordinates go to grid_sample untouched, which is the convention we need.
    tex, uv = _rand_case(4, (9, 12), dtype=torch.float32)
    grid = 2 * uv - 1
    ref = kornia.geometry.transform.remap(tex, grid[..., 0], grid[..., 1], mode=mode, padding_mode=GS_PAD[wrap],
                                          align_corners=False, normalized_coordinates=True)
    ours = difftex.sample(tex, uv, filter=filt, wrap=wrap)
    torch.testing.assert_close(ours, ref, atol=1e-5, rtol=0)


def _away_from_kinks(uv, tex_hw, margin=0.05):
    """Move uv off texel centres, where bilinear / nearest are not differentiable."""
    H, W = tex_hw
    size = torch.tensor([W, H], dtype=uv.dtype)
    x = uv * size - 0.5
    frac = x - torch.floor(x)
    frac = frac.clamp(margin, 1 - margin)
    return (torch.floor(x) + frac + 0.5) / size


@pytest.mark.parametrize("wrap", ["repeat", "clamp", "mirror", "border", ("repeat", "clamp")])
@pytest.mark.parametrize("filt", ["bilinear", "bicubic", "nearest"])
def test_gradcheck(filt, wrap):
    tex, uv = _rand_case(5, (4, 5), B=2, C=2, out_hw=(3, 2))
    uv = _away_from_kinks(uv, (4, 5))
    if filt == "nearest":
        # nearest jumps between texels; keep uv off the half-way points too.
        uv = (torch.floor(uv * torch.tensor([5, 4.0], dtype=uv.dtype)) + 0.3) / torch.tensor([5, 4.0], dtype=uv.dtype)
    tex.requires_grad_()
    uv.requires_grad_()
    fn = lambda t, u: difftex.sample(t, u, filter=filt, wrap=wrap, border_value=0.25)
    assert torch.autograd.gradcheck(fn, (tex, uv))


@pytest.mark.parametrize("wrap", ["repeat", "mirror", "border"])
def test_gradgradcheck_bilinear(wrap):
    tex, uv = _rand_case(6, (4, 5), B=1, C=2, out_hw=(3, 3))
    uv = _away_from_kinks(uv, (4, 5)).requires_grad_()
    tex.requires_grad_()
    fn = lambda t, u: difftex.sample(t, u, filter="bilinear", wrap=wrap)
    assert torch.autograd.gradgradcheck(fn, (tex, uv))


def test_per_axis_wrap_repeat_u_clamp_v():
    # 2x3 texture with distinct texel values 0..5 (row-major).
    tex = torch.arange(6, dtype=torch.float64).view(1, 1, 2, 3)
    # texel (i, j) centre: ((j + .5) / 3, (i + .5) / 2); step one period right in u
    # (repeat: same column) and far below in v (clamp: last row).
    uv = torch.tensor([[[[(0 + 0.5) / 3 + 1, (1 + 0.5) / 2 + 5],   # -> row 1, col 0 -> 3
                         [(2 + 0.5) / 3 - 2, (0 + 0.5) / 2 - 7],   # -> row 0, col 2 -> 2
                         [(1 + 0.5) / 3 + 3, (1 + 0.5) / 2]]]],    # -> row 1, col 1 -> 4
                      dtype=torch.float64)
    for filt in ("nearest", "bilinear", "bicubic"):
        out = difftex.sample(tex, uv, filter=filt, wrap=("repeat", "clamp"))
        torch.testing.assert_close(out.flatten(), torch.tensor([3.0, 2.0, 4.0], dtype=torch.float64),
                                   atol=1e-12, rtol=0)
    # The other way round: u clamps (to columns 2, 0, 2), v repeats (rows 1, 0, 1).
    out = difftex.sample(tex, uv, filter="nearest", wrap=("clamp", "repeat"))
    torch.testing.assert_close(out.flatten(), torch.tensor([5.0, 0.0, 5.0], dtype=torch.float64))


def test_mirror_and_border_constant():
    tex = torch.arange(3, dtype=torch.float64).view(1, 1, 1, 3)
    # u = -1/6 is the centre of the mirrored texel "-1", which reads texel 0;
    # u = 1 + 1/6 reads texel 2; u = -3/6 ("-2") reads texel 1.
    uv = torch.tensor([[[[-1 / 6, 0.5], [7 / 6, 0.5], [-3 / 6, 0.5]]]], dtype=torch.float64)
    out = difftex.sample(tex, uv, filter="bilinear", wrap="mirror")
    torch.testing.assert_close(out.flatten(), torch.tensor([0.0, 2.0, 1.0], dtype=torch.float64))
    out = difftex.sample(tex, uv, filter="bilinear", wrap="border", border_value=7.0)
    torch.testing.assert_close(out.flatten(), torch.tensor([7.0, 7.0, 7.0], dtype=torch.float64))


def test_texel_centres_reproduce_texture():
    tex, _ = _rand_case(7, (5, 6), B=1)
    H, W = 5, 6
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    uv = torch.stack(((xs + 0.5) / W, (ys + 0.5) / H), -1)[None]
    for filt in ("nearest", "bilinear", "bicubic"):
        torch.testing.assert_close(difftex.sample(tex, uv, filter=filt, wrap="clamp"), tex, atol=1e-12, rtol=0)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batch_broadcast_dtype_device(dtype, device):
    tex, uv = _rand_case(8, (6, 7), B=3, dtype=dtype, device=device)
    full = difftex.sample(tex, uv)
    assert full.dtype == dtype and full.device.type == device and full.shape == (3, 3, 6, 5)
    # texture batch 1 broadcasts over the uv batch
    one = difftex.sample(tex[:1], uv)
    for b in range(3):
        torch.testing.assert_close(one[b], difftex.sample(tex[:1], uv[b:b + 1])[0])
    # uv batch 1 broadcasts over the texture batch
    one_uv = difftex.sample(tex, uv[:1])
    for b in range(3):
        torch.testing.assert_close(one_uv[b], difftex.sample(tex[b:b + 1], uv[:1])[0])
    # gradients of the broadcast texture sum over the batch
    t = tex[:1].clone().requires_grad_()
    difftex.sample(t, uv).sum().backward()
    parts = []
    for b in range(3):
        tb = tex[:1].clone().requires_grad_()
        difftex.sample(tb, uv[b:b + 1]).sum().backward()
        parts.append(tb.grad)
    torch.testing.assert_close(t.grad, sum(parts))


def test_many_channels_and_float32_matches_grid_sample():
    tex, uv = _rand_case(9, (16, 16), B=2, C=17, dtype=torch.float32)
    ref = F.grid_sample(tex, 2 * uv - 1, mode="bilinear", padding_mode="border", align_corners=False)
    torch.testing.assert_close(difftex.sample(tex, uv, wrap="clamp"), ref, atol=2e-6, rtol=0)


@pytest.mark.parametrize("filt", ["nearest", "bilinear", "bicubic"])
@pytest.mark.parametrize("wrap", ["repeat", "clamp", "mirror", "border"])
def test_nan_uv_stays_in_its_pixel(filt, wrap):
    tex, uv = _rand_case(10, (5, 5), B=1, C=2, out_hw=(4, 4))
    uv = uv.clone()
    uv[0, 1, 2, 0] = float("nan")
    uv[0, 3, 3, 1] = float("inf")
    tex.requires_grad_()
    out = difftex.sample(tex, uv, filter=filt, wrap=wrap)
    bad = torch.zeros(4, 4, dtype=torch.bool)
    bad[1, 2] = bad[3, 3] = True
    assert torch.isnan(out[0, :, bad]).all()
    assert torch.isfinite(out[0, :, ~bad]).all()
    # A loss that masks the bad pixels gives finite texture gradients.
    loss = torch.where(bad, 0.0, out).sum()
    loss.backward()
    assert torch.isfinite(tex.grad).all()


@pytest.mark.parametrize("filt", ["bilinear", "bicubic", "trilinear"])
def test_a_nan_uv_passes_no_gradient_back(filt):
    # The reference backend gave its NaN pixel a NaN (or a stray finite) uv gradient, which reaches the
    # mesh's shared vertex uv; the other backends give 0.
    tex, uv = _rand_case(10, (5, 5), B=1, C=2, out_hw=(2, 2))
    uv = uv.clone()
    uv[0, 1, 0, 0] = float("nan")
    uv[0, 1, 1, 1] = float("inf")
    uv.requires_grad_()
    kw = {"uv_dx": torch.full_like(uv, 0.1), "uv_dy": torch.full_like(uv, 0.1)} if filt == "trilinear" else {}
    difftex.sample(tex, uv, filter=filt, wrap="repeat", **kw).sum().backward()
    assert torch.equal(uv.grad[0, 1], torch.zeros(2, 2, dtype=uv.dtype))
    assert (uv.grad[0, 0].abs() > 0).all()
    if filt != "trilinear":  # double backward (the reference's): no NaN into the texture's second order either
        t = tex.clone().requires_grad_()
        g, = torch.autograd.grad(difftex.sample(t, uv, filter=filt, wrap="repeat").sum(), uv, create_graph=True)
        gt, gu = torch.autograd.grad(g.sum(), (t, uv))
        assert torch.isfinite(gt).all() and torch.isfinite(gu).all()


@pytest.mark.parametrize("filt", ["nearest", "bilinear", "bicubic", "trilinear", "nearest-mip", "anisotropic",
                                  "ewa", "auto"])
def test_empty_image(filt):
    # An image with no pixels (Ho = 0) or no views (B = 0): an empty result in the graph.
    tex = torch.rand(1, 3, 8, 8, requires_grad=True)
    for shape in ((1, 0, 5, 2), (0, 4, 5, 2)):
        uv = torch.rand(shape)
        kw = dict(uv_dx=torch.full(shape, 0.1), uv_dy=torch.full(shape, 0.1)) if filt not in (
            "nearest", "bilinear", "bicubic") else {}
        out = difftex.sample(tex, uv, filter=filt, **kw)
        assert out.shape == (shape[0], 3, shape[1], shape[2])
        out.sum().backward()
        assert torch.equal(tex.grad, torch.zeros_like(tex))


@pytest.mark.parametrize("points", [5, 33])
@pytest.mark.parametrize("wrap", ["border", "clamp", "mirror", "repeat"])
def test_nearest_ties_round_like_grid_sample(wrap, points):
    # u = k / 32 on 16 texels: every other point is an exact tie between two
    # texels, rounded half to even as grid_sample does. 5 points take the
    # gather path, 33 (more points than the 32 texels) the padded-texture one.
    tex = torch.arange(32.0).view(1, 1, 2, 16)
    u = torch.arange(33.0)[torch.linspace(0, 32, points).long()] / 32
    uv = torch.stack((u, torch.full_like(u, 0.25)), -1).view(1, 1, points, 2)
    out = difftex.sample(tex, uv, filter="nearest", wrap=wrap)
    if wrap == "repeat":  # u = 1 is u = 0; inside [0, 1) no tap leaves the texture
        uv_ref, pad = uv.clone(), "border"
        uv_ref[..., 0] = torch.where(u == 1, 0.0, u)
    else:
        uv_ref, pad = uv, GS_PAD[wrap]
    ref = F.grid_sample(tex, 2 * uv_ref - 1, mode="nearest", padding_mode=pad, align_corners=False)
    torch.testing.assert_close(out, ref, rtol=0, atol=0)


def test_huge_uv_is_finite():
    tex, uv = _rand_case(11, (8, 8), B=1, C=1, dtype=torch.float32)
    uv = uv * 1e30
    for wrap in ("repeat", "clamp", "mirror", "border"):
        out = difftex.sample(tex, uv, filter="bicubic", wrap=wrap)
        assert torch.isfinite(out).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("filt", ["nearest", "bilinear", "bicubic"])
def test_finite_uv_whose_texel_coordinate_overflows(filt, dtype):
    # u = max / 2 is finite but u * W is inf: the texel coordinate was inf and
    # its fraction inf - floor(inf) NaN (border: every filter; clamp: bicubic;
    # the reference: every mode). u = +-max / 2 is an even whole number, so
    # repeat and mirror read it as u = 0; clamp and border read it as any
    # point far outside, here 20 textures away. Values and both gradients must
    # be those of the moderate coordinate, under each implementation (impl).
    big = torch.finfo(dtype).max / 2
    tex, _ = _rand_case(13, (5, 6), B=1, C=2, dtype=dtype)
    pts = [(big, 0.3), (-big, 0.7), (0.6, big), (0.4, -big), (big, -big)]
    uv = torch.tensor(pts, dtype=dtype).view(1, 1, len(pts), 2)
    tol = dict(atol=1e-5, rtol=0) if dtype == torch.float32 else dict(atol=1e-12, rtol=0)
    for wrap in difftex.WRAP_MODES:
        near = 0.0 if wrap in ("repeat", "mirror") else 20.0
        uv_ref = torch.where(uv.abs() == big, near * torch.sign(uv), uv)
        fn = lambda t, u: difftex.sample(t, u, filter=filt, wrap=wrap, border_value=0.3)
        torch.manual_seed(0)
        got = _grads(fn, tex, uv)
        torch.manual_seed(0)
        want = _grads(fn, tex, uv_ref)
        for name, a, b in zip(("value", "texture gradient", "uv gradient"), got, want):
            assert torch.isfinite(a).all(), f"{wrap}: {name} not finite"
            torch.testing.assert_close(a, b, **tol, msg=f"{wrap}: {name}")


@pytest.mark.parametrize("kwargs,exc,match", [
    (dict(texture=torch.rand(3, 4, 4)), ValueError, r"texture: expected 4-D \[B, C, H, W\], got shape \(3, 4, 4\)"),
    (dict(texture=torch.zeros(1, 3, 4, 4, dtype=torch.int64)), TypeError, r"texture: expected a floating-point"),
    (dict(uv=torch.rand(1, 4, 4, 3)), ValueError, r"uv: expected last dimension 2 \[B, Ho, Wo, 2\]"),
    (dict(uv=torch.rand(4, 4, 2)), ValueError, r"uv: expected 4-D"),
    (dict(uv=torch.rand(1, 4, 4, 2, dtype=torch.float64)), TypeError, r"uv: expected dtype torch.float32 like texture"),
    (dict(uv=[[0.5, 0.5]]), TypeError, r"uv: expected a float tensor"),
    (dict(texture=torch.rand(2, 3, 4, 4), uv=torch.rand(3, 4, 4, 2)), ValueError,
     r"batch sizes do not match \(texture 2, uv 3\)"),
    (dict(filter="trilinearr"), ValueError, r"filter: unknown filter 'trilinearr'"),
    (dict(wrap="wrap"), ValueError, r"wrap: unknown mode 'wrap'"),
    (dict(wrap=("repeat",)), ValueError, r"wrap: expected one mode or a pair"),
    (dict(wrap=3), TypeError, r"wrap: expected a str"),
    (dict(texture=torch.rand(1, 3, 0, 4)), ValueError, r"texture: expected C, H, W >= 1"),
    (dict(border_value=torch.ones(3)), TypeError, r"border_value: expected a number, got Tensor"),
    (dict(border_value="0.5"), TypeError, r"border_value: expected a number, got str"),
    (dict(border_value=True), TypeError, r"border_value: expected a number, got bool"),
    (dict(border_value=float("nan")), ValueError, r"border_value: expected a finite number, got nan"),
])
def test_bad_input(kwargs, exc, match):
    args = dict(texture=torch.rand(1, 3, 4, 4), uv=torch.rand(1, 4, 4, 2))
    args.update(kwargs)
    texture, uv = args.pop("texture"), args.pop("uv")
    with pytest.raises(exc, match=match):
        difftex.sample(texture, uv, **args)


def test_different_devices_rejected():
    # The meta device stands in for a second device on a CPU-only machine.
    with pytest.raises(ValueError, match=r"uv: expected device cpu like texture, got shape \(1, 4, 4, 2\)"):
        difftex.sample(torch.rand(1, 3, 4, 4), torch.rand(1, 4, 4, 2, device="meta"))


def _assert_impls_agree(filt, tex, uv):
    """Values and both gradients of the fast path equal the reference's, for all 16 wrap pairs."""
    for wu in difftex.WRAP_MODES:
        for wv in difftex.WRAP_MODES:
            fn = lambda t, u: difftex.sample(t, u, filter=filt, wrap=(wu, wv), border_value=0.3)
            results = []
            for impl in ("grid_sample", "reference"):
                with use_backend(impl):
                    torch.manual_seed(0)
                    results.append(_grads(fn, tex, uv))
            for a, b in zip(*results):
                torch.testing.assert_close(a, b, atol=1e-9, rtol=0, msg=f"{filt} {wu}/{wv}")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_nearest_ties_pick_the_same_texel_on_every_backend(dtype):
    # u = k / n puts x = u n - 0.5 on a tie; the grid_sample path folded u before rounding, which moves a tie
    # across a mirror (or an odd number of texels) and picked the other texel (mirror at u = -0.25 with n = 4).
    for n in (3, 4, 5):
        tex = torch.arange(float(n), dtype=dtype).view(1, 1, 1, n)
        uv = torch.tensor([[[[k / n, 0.5] for k in range(-3 * n, 4 * n)]]], dtype=dtype)
        for wrap in difftex.WRAP_MODES:
            got = []
            for impl in ("native", "grid_sample", "reference"):
                with use_backend(impl):
                    got.append(difftex.sample(tex, uv, filter="nearest", wrap=(wrap, "clamp")))
            assert torch.equal(got[0], got[2]) and torch.equal(got[1], got[2]), (n, wrap)


@pytest.mark.parametrize("filt", ["nearest", "bilinear", "bicubic"])
def test_fast_path_equals_reference_for_every_mode_pair(filt):
    tex, uv = _rand_case(12, (5, 4), lo=-4.0, hi=5.0)
    _assert_impls_agree(filt, tex, uv)


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("filt", ["nearest", "bilinear", "bicubic"])
@pytest.mark.parametrize("impl", ["grid_sample"], indirect=True)
def test_many_points_split_over_threads(filt, threads):
    # Enough points of one view for the fast path to lay them out as several
    # row blocks (one per thread) of the texture: values and gradients must
    # not depend on the split.
    tex, uv = _rand_case(13, (9, 14), B=1, out_hw=(41, 37), lo=-1.0, hi=2.0)
    n = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        torch.manual_seed(0)
        got = _grads(lambda t, u: difftex.sample(t, u, filter=filt, wrap="clamp"), tex[:1], uv)
    finally:
        torch.set_num_threads(n)
    gs = lambda t, u: F.grid_sample(t.expand(u.shape[0], -1, -1, -1), 2 * u - 1, mode=GS_MODE[filt],
                                    padding_mode="border", align_corners=False)
    torch.manual_seed(0)
    ref = _grads(gs, tex[:1], uv)
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=0)


@pytest.mark.parametrize("filt", ["nearest", "bilinear", "bicubic"])
def test_fast_path_large_texture_few_points(filt):
    # A texture with more texels than points: the fast path reads it unpadded
    # and sends the points whose taps cross an edge to the gather reference.
    # uv sits on and near the edges of several periods to hit that split.
    g = torch.Generator().manual_seed(14)
    tex = torch.rand(1, 2, 23, 40, generator=g, dtype=torch.float64)
    # (Not on exact texel boundaries: nearest's round-half-to-even tie there
    # depends on which period the coordinate is expressed in.)
    edge = torch.tensor([0.05, 0.2, 0.6, 1.6, 20.3, 40 - 1.6, 40 - 0.6, 40 - 0.2]) / 40
    u = (edge.view(-1, 1) + torch.arange(-2, 3).view(1, -1)).flatten()[:36]
    v = torch.rand(36, generator=g) * 4 - 1.5
    uv = torch.stack((u.to(torch.float64), v.to(torch.float64)), -1).view(2, 3, 6, 2)
    uv = torch.cat((uv, uv.flip(-1)), 2)  # the same edges along v
    _assert_impls_agree(filt, tex, uv)


@pytest.mark.parametrize("filter", FILTERS)
def test_float16_runs_every_filter(filter):
    # Regression: the gather's index cap (2**52) overflowed float16, and the
    # fast path hands a large texture's edge points to the gather.
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(1, 3, 64, 48, generator=g).half()
    uv = (torch.rand(1, 3, 5, 2, generator=g) * 3 - 1).half()
    d = (torch.randn(1, 3, 5, 2, generator=g) * 0.1).half()
    kw = {"uv_dx": d, "uv_dy": d * 0.3} if filter in MIP_FILTERS else {}
    out = difftex.sample(tex, uv, filter=filter, wrap=("repeat", "border"), **kw)
    ref = difftex.sample(tex.double(), uv.double(), filter=filter, wrap=("repeat", "border"),
                         **{k: v.double() for k, v in kw.items()})
    assert out.dtype == torch.float16
    torch.testing.assert_close(out.double(), ref, atol=0.02, rtol=0)


@pytest.mark.parametrize("filter", FILTERS)
def test_one_texture_over_a_uv_batch_gives_a_contiguous_output(backend, filter):
    # DESIGN.md: outputs are contiguous [B, C, H, W]; one texture shared by two views came back [C, B]-major.
    g = torch.Generator().manual_seed(2)
    tex, uv = torch.rand(1, 3, 8, 8, generator=g), torch.rand(2, 4, 5, 2, generator=g)
    kw = {"uv_dx": torch.full_like(uv, 0.05), "uv_dy": torch.full_like(uv, 0.02)} if filter in MIP_FILTERS else {}
    out = difftex.sample(tex, uv, filter=filter, **kw)
    assert out.shape == (2, 3, 4, 5) and out.is_contiguous()
    one = difftex.sample(tex, uv[1:], filter=filter, **{k: v[1:] for k, v in kw.items()})
    torch.testing.assert_close(out[1], one[0])

"""The native single-level reads (csrc/single.cpp) and the threaded taps backward, against the gather reference.

Nearest / bilinear / bicubic, every wrap mode on each axis, float32 and
float64: values and the gradients of texture and uv equal to the reference
(``difftex.backend("reference")``) within 1e-5 (float32) and 1e-12
(float64), relative to the largest entry for the texture gradient, which
sums many terms. The texture gradient's scatter by bands of rows
(csrc/bands.h) runs a class of bands threaded from 1024 points on: cases with more points
than that check it against the reference, and that one and two threads
give bit-identical gradients.

float32 bilinear / bicubic reads take an eight-point AVX2 path where the
CPU has it (``set_simd``), and their forward a sixteen-point AVX-512 one
where it has that (``set_wide``; outputs of 1 MB or more written with
non-temporal stores, ``set_stream``, held to the cached stores' bits); the
float32 tests run on each and on the scalar loop (the ``path`` fixture), and one test holds the three to each
other on the points the vector paths treat specially (group tails,
non-finite points inside a group, huge and edge coordinates). A
channels_last texture is read in place and gives the planar read's bits.
"""
from __future__ import annotations

import itertools

import pytest
import torch

import difftex
from difftex import _native as native
from difftex.texture.filters import gather
from difftex.texture.wrap import WRAP_CODES
from tests.conftest import use_backend

f32, f64 = torch.float32, torch.float64
BUILT = native.load() is not None
pytestmark = pytest.mark.skipif(not BUILT, reason="native kernel not built here (no compiler or ninja)")
WRAPS = ("repeat", "clamp", "mirror", "border")
TOL = {f32: 1e-5, f64: 1e-12}
SIMD = BUILT and native.load().simd_available()
WIDE = BUILT and native.load().wide_available()


def _set_path(kernel, name: str) -> tuple[bool, bool]:
    """Selects the sixteen-point ("wide"), eight-point ("simd") or scalar path; returns the previous switches."""
    return kernel.set_simd(name != "scalar"), kernel.set_wide(name == "wide")


def _restore_path(kernel, before: tuple[bool, bool]) -> None:
    kernel.set_simd(before[0])
    kernel.set_wide(before[1])


@pytest.fixture(params=["wide", "simd", "scalar"])
def path(request):
    """Runs a test on the AVX-512 and AVX2 paths (where the CPU has them) and on the scalar loop."""
    if request.param == "simd" and not SIMD:
        pytest.skip("this CPU has no AVX2 / FMA: the scalar loop serves")
    if request.param == "wide" and not WIDE:
        pytest.skip("this CPU has no AVX-512: the eight-point path serves")
    kernel = native.load()
    before = _set_path(kernel, request.param)
    yield request.param
    _restore_path(kernel, before)


def _inputs(dtype, B=1, Bt=1, C=3, H=7, W=10, Ho=9, Wo=11, seed=0, spread=4.0):
    g = torch.Generator().manual_seed(seed)
    tex = torch.rand(Bt, C, H, W, generator=g, dtype=dtype)
    uv = torch.rand(B, Ho, Wo, 2, generator=g, dtype=dtype) * spread - (spread - 1) / 2  # past every edge
    return tex, uv


def _read(backend, tex, uv, filter, wrap, border=0.25):
    """Values and (texture, uv) gradients of one read under ``backend``, for a fixed random output weight."""
    t, u = tex.detach().clone().requires_grad_(), uv.detach().clone().requires_grad_()
    with use_backend(backend):
        out = difftex.sample(t, u, filter=filter, wrap=wrap, border_value=border)
        w = torch.randn(out.shape, generator=torch.Generator().manual_seed(7), dtype=out.dtype)
        gt, gu = torch.autograd.grad((out * w).sum(), (t, u))
    return out.detach(), gt, gu


def _assert_matches(tex, uv, filter, wrap, tol):
    out, gt, gu = _read("native", tex, uv, filter, wrap)
    ref, rt, ru = _read("reference", tex, uv, filter, wrap)
    torch.testing.assert_close(out, ref, atol=tol, rtol=tol, equal_nan=True)
    s = max(1.0, rt.abs().max().item())
    torch.testing.assert_close(gt, rt, atol=tol * s, rtol=tol, msg=lambda m: f"texture gradient: {m}")
    s = max(1.0, ru.abs().max().item())
    torch.testing.assert_close(gu, ru, atol=tol * s, rtol=tol, msg=lambda m: f"uv gradient: {m}")


@pytest.mark.parametrize("dtype", [f32, f64], ids=["float32", "float64"])
@pytest.mark.parametrize("wrap", list(itertools.product(WRAPS, WRAPS)), ids="-".join)
@pytest.mark.parametrize("filter", ["nearest", "bilinear", "bicubic"])
def test_the_kernel_gives_the_reference_values_and_gradients(filter, wrap, dtype, path):
    tex, uv = _inputs(dtype, seed=hash((filter, wrap)) % 1000)
    _assert_matches(tex, uv, filter, wrap, TOL[dtype])


@pytest.mark.parametrize("C", [1, 2, 4])  # 1 and 4 fixed at compile time, 2 at run time
@pytest.mark.parametrize("B, Bt", [(2, 2), (3, 1)])
@pytest.mark.parametrize("dtype", [f32, f64], ids=["float32", "float64"])
def test_batches_channels_and_non_contiguous_inputs(B, Bt, C, dtype, path):
    tex, uv = _inputs(dtype, B=B, Bt=Bt, C=C, H=6, W=5)
    tex = tex.transpose(2, 3).contiguous().transpose(2, 3)
    uv = uv.transpose(1, 2).contiguous().transpose(1, 2)
    assert not tex.is_contiguous() and not uv.is_contiguous()
    for filter in ("bilinear", "bicubic"):
        _assert_matches(tex, uv, filter, ("mirror", "border"), TOL[dtype])


@pytest.mark.parametrize("dtype", [f32, f64], ids=["float32", "float64"])
def test_the_kernel_reads_any_pixel_shape_in_place(dtype, path):
    # uv [B, *S, 2] -> [B, C, *S]: difftex.sample's calls without a graph pass [B, Ho, Wo, 2] as it is (no
    # reshape or view a call); the values and the backward are the flat list's, bit for bit.
    kernel = native.load()
    tex, uv = _inputs(dtype, B=2, Bt=1, C=3, H=6, W=5, Ho=4, Wo=7)
    opts = kernel.ReadOptions(wrap_u=WRAP_CODES["repeat"], wrap_v=WRAP_CODES["mirror"], border=0.0)
    flat = uv.reshape(2, -1, 2)
    for kind in (1, 2):
        out = kernel.sample(tex, uv, kind, opts)
        assert out.shape == (2, 3, 4, 7)
        assert torch.equal(out, kernel.sample(tex, flat, kind, opts).view(2, 3, 4, 7))
        g = torch.randn(out.shape, generator=torch.Generator().manual_seed(3), dtype=dtype)
        gt, gu = kernel.sample_backward(tex, uv, g, kind, opts, need_texture=True, need_uv=True)
        ft, fu = kernel.sample_backward(tex, flat, g.view(2, 3, -1), kind, opts, need_texture=True, need_uv=True)
        assert torch.equal(gt, ft) and torch.equal(gu, fu.view(uv.shape))
    with pytest.raises(RuntimeError, match=r"grad must be \[B, C, \*S\] of uv's dtype for uv \[B, \*S, 2\]"):
        kernel.sample_backward(tex, uv, g.view(2, 3, -1), 1, opts, need_texture=True, need_uv=True)
    with pytest.raises(RuntimeError, match=r"uv must be contiguous \[B, \*S, 2\]"):
        kernel.sample(tex, uv[..., :1].contiguous(), 1, opts)
    with torch.no_grad():
        plain = difftex.sample(tex, uv, filter="bicubic", wrap=("repeat", "mirror"))
    graph = difftex.sample(tex.requires_grad_(), uv, filter="bicubic", wrap=("repeat", "mirror"))
    assert torch.equal(plain, graph.detach())


@pytest.mark.parametrize("S", [(19, 45), (8, 32), (3, 100), (40, 31), (1, 70), (2, 3, 33), (45, 100)], ids=str)
@pytest.mark.parametrize("B, Bt", [(2, 2), (3, 1)])
def test_a_two_d_pixel_shape_read_tile_by_tile_gives_the_points_in_order(S, B, Bt, path):
    # The vector forwards read [B, ..., Ho, Wo, 2] in tiles of 8 rows by 32 points (csrc/single.cpp, Tiles):
    # here heights and widths that are not multiples of the tile, a width under 32 and a single row (read in
    # order), a 3-D pixel shape, and (45, 100): 180 segments an entry, which three threads split inside a band
    # (each thread's walk decodes its first segment, then counts). Every point is written once, with the flat
    # list's bits; a NaN stays in its pixel; the values are the reference's.
    kernel = native.load()
    g = torch.Generator().manual_seed(sum(S))
    tex = torch.rand(Bt, 3, 37, 29, generator=g)
    uv = torch.rand(B, *S, 2, generator=g) * 3 - 1
    uv.view(B, -1, 2)[B - 1, uv[0].numel() // 4 - 3, 1] = float("nan")
    opts = kernel.ReadOptions(wrap_u=WRAP_CODES["mirror"], wrap_v=WRAP_CODES["clamp"], border=0.0)
    for kind, filter in ((1, "bilinear"), (2, "bicubic")):
        out = _threads(3, lambda: kernel.sample(tex, uv, kind, opts))
        flat = kernel.sample(tex, uv.reshape(B, -1, 2), kind, opts)
        torch.testing.assert_close(out.reshape(flat.shape), flat, rtol=0, atol=0, equal_nan=True)  # same bits
        nan = out.isnan()
        assert nan.sum() == 3 and nan.reshape(B, 3, -1)[B - 1, :, uv[0].numel() // 4 - 3].all()
        with use_backend("reference"), torch.no_grad():
            ref = difftex.sample(tex, uv.reshape(B, -1, S[-1], 2), filter=filter, wrap=("mirror", "clamp"))
        torch.testing.assert_close(out, ref.reshape(out.shape), atol=1e-5, rtol=1e-5, equal_nan=True)


@pytest.mark.parametrize("C", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("B, Bt", [(2, 2), (2, 1)])
@pytest.mark.parametrize("dtype", [f32, f64], ids=["float32", "float64"])
def test_a_channels_last_texture_is_read_in_place_with_the_planar_bits(B, Bt, C, dtype, path):
    # The kernel reads a channels_last texture interleaved (no copy) and scatters its gradient into a
    # channels_last buffer; texels, weights and the order of every sum are the planar read's, so values and
    # gradients are equal bit for bit. 1,300 points a batch entry: the banded scatter runs threaded. The
    # first four rows keep every tap inside the texture, in order, and clamp or mirror in u repeat or
    # reverse a lane's taps at the edges: the sixteen-point forward reads 3 and 4 interleaved channels as
    # runs of pairs of floats there (pair_taps16). The planar backward adds a row's taps as one run of
    # floats where they are adjacent texels (single.cpp run_lanes8), the interleaved one float by float:
    # rows 4-7 step 0.65, 1, 1.3 and 2.6 texels a point along one texel row, so that runs overlap the runs
    # of the points before them in part, exactly and not at all.
    tex, uv = _inputs(dtype, B=B, Bt=Bt, C=C, H=23, W=17, Ho=26, Wo=50, seed=C)
    uv[:, :4] = uv[:, :4].remainder(1.0) * 0.7 + 0.15
    for row, step in zip(range(4, 8), (0.65, 1.0, 1.3, 2.6)):
        uv[:, row, :, 0] = (0.3 + step * torch.arange(50, dtype=dtype)) / 17
        uv[:, row, :, 1] = (row + 0.4) / 23
    interleaved = tex.contiguous(memory_format=torch.channels_last)
    assert C == 1 or not interleaved.is_contiguous()
    _assert_matches(interleaved, uv, "bicubic", ("mirror", "border"), TOL[dtype])
    uv[0, 3, 5, 0] = float("nan")
    for filter, wrap in itertools.product(("nearest", "bilinear", "bicubic"),
                                          (("repeat", "clamp"), ("clamp", "mirror"), ("mirror", "border"))):
        out, gt, gu = _read("native", tex, uv, filter, wrap)
        out_i, gt_i, gu_i = _read("native", interleaved, uv, filter, wrap)
        assert torch.equal(out.nan_to_num(7.0), out_i.nan_to_num(7.0)), (filter, wrap)
        assert torch.equal(gt, gt_i) and torch.equal(gu, gu_i), (filter, wrap)
        assert gt_i.is_contiguous(memory_format=torch.channels_last)


@pytest.mark.skipif(not WIDE, reason="this CPU has no AVX-512: no sixteen-point forward")
@pytest.mark.parametrize("layout", ["planar", "channels_last"])
@pytest.mark.parametrize("S, B, Bt", [((256, 512), 1, 1), ((200, 250), 2, 1), ((130, 700), 2, 2)], ids=str)
def test_an_output_of_a_megabyte_or_more_is_streamed_with_the_cached_stores_bits(S, B, Bt, layout):
    # The sixteen-point forward writes an output of 1 MB or more (here 1.5-2.2 MB) with non-temporal
    # stores, a group's whole aligned line of a channel at a time (rows of 512 points), the rest (rows of 250
    # and 700 points: groups across a line, a tile's tail, a NaN's group) with the cached stores: the same bits
    # as with the switch off, at one thread and two, and the reference's values.
    kernel = native.load()
    before = _set_path(kernel, "wide")
    g = torch.Generator().manual_seed(S[1])
    tex = torch.rand(Bt, 3, 96, 80, generator=g)
    if layout == "channels_last":
        tex = tex.contiguous(memory_format=torch.channels_last)
    uv = torch.rand(B, *S, 2, generator=g) * 3 - 1
    uv[B - 1, 7, 21, 0] = float("nan")
    opts = kernel.ReadOptions(wrap_u=WRAP_CODES["repeat"], wrap_v=WRAP_CODES["mirror"], border=0.0)
    try:
        for kind, filter in ((1, "bilinear"), (2, "bicubic")):
            was = kernel.set_stream(False)
            cached = kernel.sample(tex, uv, kind, opts)
            kernel.set_stream(True)
            for n in (1, 2):
                streamed = _threads(n, lambda: kernel.sample(tex, uv, kind, opts))
                assert torch.equal(streamed.nan_to_num(7.0), cached.nan_to_num(7.0)), (filter, n)
            kernel.set_stream(was)
            assert streamed.isnan().sum() == 3 and streamed[B - 1, :, 7, 21].isnan().all()
            with use_backend("reference"), torch.no_grad():
                ref = difftex.sample(tex, uv, filter=filter, wrap=("repeat", "mirror"))
            torch.testing.assert_close(streamed, ref, atol=1e-5, rtol=1e-5, equal_nan=True)
    finally:
        _restore_path(kernel, before)


@pytest.mark.parametrize("filter", ["bilinear", "bicubic"])
@pytest.mark.parametrize("wrap", [("repeat", "clamp"), ("mirror", "border")])
def test_gradcheck_through_the_kernel(filter, wrap):
    tex, uv = _inputs(f64, H=5, W=6, Ho=3, Wo=4)
    tex.requires_grad_()
    uv.requires_grad_()
    with use_backend("native"):
        f = lambda t, u: difftex.sample(t, u, filter=filter, wrap=wrap, border_value=0.5)
        assert torch.autograd.gradcheck(f, (tex, uv), atol=1e-7, rtol=1e-6)
        # Double backward runs the differentiable reference backward.
        assert torch.autograd.gradgradcheck(f, (tex, uv), atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("filter", ["nearest", "bilinear", "bicubic"])
def test_a_nan_uv_stays_in_its_pixel(filter, path):
    tex, uv = _inputs(f32, Ho=4, Wo=5)
    uv[0, 1, 2, 0] = float("nan")
    uv[0, 3, 0, 1] = float("inf")
    out, gt, gu = _read("native", tex, uv, filter, "repeat")
    ref, rt, ru = _read("reference", tex, uv, filter, "repeat")
    bad = ~torch.isfinite(uv).all(-1)
    assert torch.isnan(out[:, :, bad[0]]).all() and torch.isfinite(out[:, :, ~bad[0]]).all()
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5, equal_nan=True)
    assert torch.isfinite(gt).all() and torch.isfinite(gu).all()
    assert (gu[bad] == 0).all()
    torch.testing.assert_close(gt, rt, atol=1e-5, rtol=1e-5)


def test_huge_and_far_uv_read_as_the_reference(path):
    # float32 uv far outside [0, 1]: the folding (repeat, mirror) and the clamping keep their texels.
    tex, uv = _inputs(f32, Ho=3, Wo=4)
    uv[0, 0] = torch.tensor([[1e30, -1e30], [3e7 + 0.25, -5e6 - 0.75], [-20.3, 41.6], [1e-30, 1 - 1e-7]])
    for filter, wrap in itertools.product(("nearest", "bilinear", "bicubic"), WRAPS):
        out, *_ = _read("native", tex, uv, filter, wrap)
        ref, *_ = _read("reference", tex, uv, filter, wrap)
        torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5, msg=lambda m: f"{filter} {wrap}: {m}")


@pytest.mark.skipif(not SIMD, reason="this CPU has no AVX2 / FMA")
@pytest.mark.parametrize("filter", ["bilinear", "bicubic"])
def test_the_vector_paths_read_as_the_scalar_loop_and_the_reference(filter):
    # 3 x 45 points: groups of eight and a tail of five per batch entry (of sixteen and thirteen on the
    # sixteen-point forward), a NaN and an inf inside groups (lanes that write NaN, or nothing in the
    # backward), coordinates on texel centres and edges, just below 0 and 1, huge. The sixteen-point
    # forward reads a row's taps as pairs of texels (pair_taps16) where every lane's taps lie within K
    # adjacent texels: a row of 9 points (a group) whose taps are texels x0 - 1 ... x0 + 2 in order, one
    # whose u all lie past the left edge (clamp, mirror: one texel repeated), the random rest (repeat:
    # seams, read texel by texel).
    tex, uv = _inputs(f32, B=3, Bt=3, C=5, H=9, W=6, Ho=5, Wo=9, seed=11)
    special = torch.tensor([[0.5 / 6, 0.5 / 9], [1 / 6, 1 / 9], [-1e-9, 1 - 1e-7], [1e30, -1e30], [-1.0, 2.0],
                            [3e7 + 0.25, -5e6 - 0.75], [-2.0 - 1 / 6, 3.5], [1e-30, -1e-30]])
    uv[1, 1, :8] = special
    uv[2, 0, :, 0] = torch.linspace(1.5 / 6, 3.4 / 6, 9)
    uv[2, 3, :, 0] = torch.linspace(-0.4, -0.01, 9)
    uv[0, 2, 3, 0] = float("nan")
    uv[2, 4, 1, 1] = float("inf")
    kernel = native.load()
    paths = ("wide", "simd", "scalar") if WIDE else ("simd", "scalar")
    for wrap in itertools.product(WRAPS, WRAPS):
        got = {}
        for name in paths:
            before = _set_path(kernel, name)
            try:
                got[name] = _read("native", tex, uv, filter, wrap)
            finally:
                _restore_path(kernel, before)
        ref = list(_read("reference", tex, uv, filter, wrap))
        ok = torch.isfinite(uv).all(-1, keepdim=True)
        ref[2] = torch.where(ok, ref[2], 0.0)  # the reference's uv gradient is NaN there, the kernel's 0
        for i, (name, r) in enumerate(zip(("values", "texture gradient", "uv gradient"), ref)):
            a, b = got["simd"][i], got["scalar"][i]
            s = max(1.0, r.abs().max().item())
            msg = lambda m: f"{wrap} {name}: {m}"  # noqa: E731
            torch.testing.assert_close(a, r, atol=1e-5 * s, rtol=1e-5, equal_nan=True, msg=msg)
            torch.testing.assert_close(a, b, atol=1e-5 * s, rtol=1e-5, equal_nan=True, msg=msg)
            if WIDE:  # the sixteen-point forward does the eight-point arithmetic in each lane: the same bits
                w = got["wide"][i]
                assert torch.equal(w.nan_to_num(7.0), a.nan_to_num(7.0)) and torch.equal(w.isnan(), a.isnan()), \
                    msg("the sixteen- and eight-point paths differ")
        for name in paths:
            out = got[name][0]
            assert torch.isnan(out[0, :, 2, 3]).all() and torch.isnan(out[2, :, 4, 1]).all(), name
            assert torch.isfinite(out[0, :, 2, 2]).all() and torch.isfinite(out[0, :, 2, 4]).all(), name


@pytest.mark.skipif(not SIMD, reason="this CPU has no AVX2 / FMA")
@pytest.mark.parametrize("C", [3, 5])  # 3 fixed at compile time, 5 at run time (its backward crashed once)
@pytest.mark.parametrize("filter", ["trilinear", "nearest-mip", "anisotropic", "auto"])
def test_the_eight_point_taps_read_as_the_scalar_loop_and_the_reference(filter, C):
    # 2 x 12 x 16 points on a 20 x 24 texture: the first rows share one footprint, 4:1 (groups of eight on the
    # same levels with one tap count: the eight-point paths, one tap or four), the next ones the same two
    # levels with 4-8 taps (the N-tap paths' groups with mixed counts), one an integer level (trilinear: 2),
    # the others a random one each (groups on mixed levels: the scalar loop); a NaN inside a group; uv up to a
    # texture past each edge; gradients to texture, uv and both derivatives (through the level). Both paths
    # give the same bits, so grouping cannot change a result.
    g = torch.Generator().manual_seed(5)
    tex = torch.rand(2, C, 20, 24, generator=g)
    uv = torch.rand(2, 12, 16, 2, generator=g) * 3 - 1
    dx = torch.randn(2, 12, 16, 2, generator=g) * 0.1
    dy = torch.randn(2, 12, 16, 2, generator=g) * 0.1
    dx[:, :6], dy[:, :6] = torch.tensor([0.16, 0.02]), torch.tensor([-0.01, 0.04])
    # Rows 6-8: levels 1 and 2 for all (a 3-texel minor axis), 4-8 taps a point: groups of eight with mixed counts.
    stretch = 1 + torch.rand(2, 3, 16, generator=g)
    dx[:, 6:9] = torch.stack((0.5 * stretch, torch.zeros_like(stretch)), -1)
    dy[:, 6:9] = torch.tensor([0.0, 0.15])
    # Row 9: level 2 exactly (4 texels along u): level 1 read at weight 0 for the derivative from below.
    dx[:, 9], dy[:, 9] = torch.tensor([4 / 24, 0.0]), torch.tensor([0.0, 0.05])
    uv[1, 3, 4, 1] = float("nan")
    kernel = native.load()

    def read(backend, simd, wrap):
        before = kernel.set_simd(simd)
        try:
            ins = [t.detach().clone().requires_grad_() for t in (tex, uv, dx, dy)]
            with use_backend(backend):
                out = difftex.sample(ins[0], ins[1], uv_dx=ins[2], uv_dy=ins[3], filter=filter, wrap=wrap,
                                     border_value=0.25)
            w = torch.randn(out.shape, generator=torch.Generator().manual_seed(7))
            grads = torch.autograd.grad((out.nan_to_num() * w).sum(), ins, allow_unused=True)
            return [out.detach()] + [torch.zeros_like(t) if gr is None else gr for t, gr in zip(ins, grads)]
        finally:
            kernel.set_simd(before)

    ok = torch.isfinite(uv).all(-1, keepdim=True)
    for wrap in (("repeat", "mirror"), ("mirror", "clamp"), ("border", "repeat"), ("clamp", "border")):
        fast, slow, ref = read("native", True, wrap), read("native", False, wrap), read("reference", True, wrap)
        names = ("values", "texture gradient", "uv gradient", "uv_dx gradient", "uv_dy gradient")
        for name, a, b, r in zip(names, fast, slow, ref):
            if name != "values" and name != "texture gradient":
                r = torch.where(ok, r, 0.0)  # NaN on the reference at the NaN point, 0 on the kernel
            s = max(1.0, r.abs().max().item())
            msg = lambda m: f"{wrap} {name}: {m}"  # noqa: E731
            assert torch.equal(a.nan_to_num(), b.nan_to_num()), msg("the two paths differ")  # bit for bit
            torch.testing.assert_close(a, r, atol=1e-5 * s, rtol=1e-5, equal_nan=True, msg=msg)
        assert torch.isnan(fast[0][1, :, 3, 4]).all() and torch.isfinite(fast[0][1, :, 3, 5]).all()


@pytest.mark.skipif(not SIMD, reason="this CPU has no AVX2 / FMA")
@pytest.mark.parametrize("filter", ["trilinear", "nearest-mip", "anisotropic", "auto"])
def test_the_eight_point_band_keys_give_the_scalar_keys(filter):
    # float32 reads key their points for the banded scatter four at a time (taps.cpp tap_keys4; not for mirror
    # along v): one tap each, or N along the axis, whose v range sets the rows. 8100 points over several levels
    # and band scales, 1-16 taps, far uv, taps spread over more than a period, a NaN and an inf: any key other
    # than the scalar one reorders a texel's sums, so both paths must give the same bits, at one and two
    # threads, and (one tap) the reference's values within 1e-5.
    g = torch.Generator().manual_seed(9)
    tex = torch.rand(1, 3, 64, 48, generator=g)
    uv = torch.rand(1, 90, 90, 2, generator=g) * 3 - 1
    uv[0, :3, :, 1] *= 3e4
    uv[0, 4, :9, 1] = 1e10  # past the four-point path's |v| < 2^31: the scalar key, inside a group
    uv[0, 5, 6, 1], uv[0, 7, 8, 0] = float("nan"), float("inf")
    dx = torch.randn(1, 90, 90, 2, generator=g) * torch.exp(torch.randn(1, 90, 90, 1, generator=g) * 2) * 0.02
    dy = torch.randn(1, 90, 90, 2, generator=g) * 0.01
    kernel = native.load()

    def run(backend, simd, threads, wrap):
        def go():
            t, u = tex.clone().requires_grad_(), uv.clone().requires_grad_()
            with use_backend(backend):
                out = difftex.sample(t, u, filter=filter, wrap=wrap, uv_dx=dx, uv_dy=dy, border_value=0.25)
            w = torch.randn(out.shape, generator=torch.Generator().manual_seed(1))
            return (out.detach(), *torch.autograd.grad((out.nan_to_num() * w).sum(), (t, u)))
        before = kernel.set_simd(simd)
        try:
            return _threads(threads, go)
        finally:
            kernel.set_simd(before)

    for wrap in (("mirror", "repeat"), ("repeat", "clamp"), ("clamp", "border")):
        fast = run("native", True, 2, wrap)
        for other in (run("native", False, 2, wrap), run("native", True, 1, wrap)):
            for a, b in zip(fast, other):
                assert torch.equal(a.nan_to_num(), b.nan_to_num()), wrap
        if filter in ("anisotropic", "auto"):
            # The kernel places taps along the axis in double, the reference in float32: at v ~ 1e5 they read
            # other texels (the two are compared on ordinary uv in the test above).
            continue
        ref = run("reference", True, 2, wrap)
        s = max(1.0, ref[1].abs().max().item())
        torch.testing.assert_close(fast[1], ref[1], atol=1e-5 * s, rtol=1e-5)


def _threads(n, fn):
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        return fn()
    finally:
        torch.set_num_threads(old)


@pytest.mark.parametrize("dtype", [f32, f64], ids=["float32", "float64"])
@pytest.mark.parametrize("filter", ["nearest", "bilinear", "bicubic"])
def test_the_banded_scatter_over_threads_gives_the_reference_bit_for_bit_at_any_thread_count(filter, dtype, path):
    # 16000 points over a 40-row texture: bands of 4-8 rows, both parities busy, on two threads. float32 runs
    # the eight-point path too, whose groups (and partial last groups) fall differently on one and two threads.
    tex, uv = _inputs(dtype, B=2, Bt=2, H=40, W=24, Ho=80, Wo=100, seed=3, spread=1.5)
    bad = uv.clone()
    bad[1, 7, 3, 0] = float("nan")  # a live lane fewer in its group
    for wrap in (("repeat", "mirror"), ("clamp", "repeat"), ("border", "border")):
        for points in (uv, bad):
            one = _threads(1, lambda: _read("native", tex, points, filter, wrap))
            two = _threads(2, lambda: _read("native", tex, points, filter, wrap))
            for a, b in zip(one, two):
                assert torch.equal(a.nan_to_num(), b.nan_to_num())
        _assert_matches(tex, uv, filter, wrap, TOL[dtype])


def _band_count(h: int, reach: int, cap: int = 512) -> int:
    """csrc/bands.h band_count: the largest power of two up to cap whose bands all have at least reach rows."""
    nb = 1
    while nb * 2 <= cap and nb * 2 * reach <= h:
        nb *= 2
    return nb


@pytest.mark.skipif(not SIMD, reason="this CPU has no AVX2 / FMA: no eight-point backward")
@pytest.mark.parametrize("Bt", [1, 2])
def test_the_eight_point_scatter_adds_in_band_order(Bt, path):
    # The float32 bilinear backward's texture gradient, emulated add by add in float32 with the eight-point
    # path's arithmetic (x = u * W - 0.5 clamped, weights 1 - t and t, shares (g * w_y) * w_x) and the banded
    # order (csrc/bands.h): each point keyed by the band of the first row it writes, the even bands' points
    # first, then the odd ones', each band's in index order. Equal bits need every key right: a key one band
    # off moves a point's adds before or after another band's. 37 rows (16 bands of 2-3 rows: rows near band
    # edges are common) and 29 columns, neither a power of two, so that u * 37 rounds in float32. Two batch
    # entries of 3939 points (groups of eight straddle them), on one shared texture or one texture each.
    if path == "scalar":
        pytest.skip("the scalar loop places taps in double")
    np = pytest.importorskip("numpy")
    H, W = 37, 29
    g = torch.Generator().manual_seed(21)
    tex = torch.rand(Bt, 1, H, W, generator=g)
    uv = torch.rand(2, 39, 101, 2, generator=g) * 1.2 - 0.1  # a few points past the clamped edges
    # v * 37 - 0.5 just under the first row of a band (7, 17, 19, 26, 33, 35), which float32 rounds up to:
    # these points write from that row, where double arithmetic (the scalar loop's) names the band before.
    uv[0, 5:11, 7, 1] = torch.tensor([0.2027027, 0.47297296, 0.527027, 0.7162162, 0.9054054, 0.95945942])
    grad = torch.randn(2, 1, 39, 101, generator=g)
    kernel = native.load()
    opts = kernel.ReadOptions(wrap_u=WRAP_CODES["clamp"], wrap_v=WRAP_CODES["clamp"], border=0.0)

    def taps(c, n):  # float32, as axis8
        x = np.minimum(np.maximum(c * np.float32(n) - np.float32(0.5), np.float32(-3)), np.float32(n + 2))
        x0 = np.floor(x)
        t = x - x0
        i = x0.astype(np.int64)
        return (np.clip(i, 0, n - 1), np.clip(i + 1, 0, n - 1)), (np.float32(1) - t, t)

    u, v = uv.reshape(-1, 2).numpy().T
    (cx, wx), (ry, wy) = taps(u, W), taps(v, H)
    nb = _band_count(H, 2)
    band = ry[0] * nb // H  # of the first row written: the lower tap, clamped
    texture = np.arange(u.size) // (u.size // 2) if Bt == 2 else np.zeros(u.size, np.int64)
    want = np.zeros((Bt, H, W), np.float32)
    gs = grad.reshape(-1).numpy()
    for parity in (0, 1):
        for p in np.flatnonzero(band % 2 == parity):
            for r in range(2):
                share = gs[p] * wy[r][p]
                for q in range(2):
                    want[texture[p], ry[r][p], cx[q][p]] += share * wx[q][p]
    for threads in (1, 2):
        gt, _ = _threads(threads, lambda: kernel.sample_backward(tex, uv, grad, 1, opts, need_texture=True,
                                                                 need_uv=False))
        assert torch.equal(gt[:, 0], torch.from_numpy(want)), threads


@pytest.mark.parametrize("filter", ["trilinear", "anisotropic"])
@pytest.mark.parametrize("wrap", [("repeat", "mirror"), ("mirror", "repeat"), ("clamp", "border")])
def test_the_threaded_taps_backward_gives_the_reference(filter, wrap):
    # Enough points (8100) for the taps' banded scatter on two threads, footprints over several levels and scales.
    g = torch.Generator().manual_seed(5)
    tex = torch.rand(1, 3, 64, 48, generator=g, dtype=f64)
    uv = torch.rand(1, 90, 90, 2, generator=g, dtype=f64) * 3 - 1
    dx = torch.randn(1, 90, 90, 2, generator=g, dtype=f64) * torch.exp(torch.randn(1, 90, 90, 1, generator=g) * 2) * 0.02
    dy = torch.randn(1, 90, 90, 2, generator=g, dtype=f64) * 0.01

    def run(backend):
        t, u = tex.clone().requires_grad_(), uv.clone().requires_grad_()
        with use_backend(backend):
            out = difftex.sample(t, u, filter=filter, wrap=wrap, uv_dx=dx, uv_dy=dy, border_value=0.25, max_aniso=4)
            w = torch.randn(out.shape, generator=torch.Generator().manual_seed(1), dtype=f64)
            return (out.detach(), *torch.autograd.grad((out * w).sum(), (t, u)))

    one = _threads(1, lambda: run("native"))
    two = _threads(2, lambda: run("native"))
    ref = run("reference")
    for a, b in zip(one, two):
        assert torch.equal(a, b)
    for name, a, b in zip(("values", "texture", "uv"), two, ref):
        s = max(1.0, b.abs().max().item())
        torch.testing.assert_close(a, b, atol=1e-10 * s, rtol=1e-9, msg=lambda m: f"{name}: {m}")


def test_the_kernel_constants_are_the_reference_ones():
    k = native.load()
    assert k.CUBIC_A == gather._CUBIC_A and k.FAR_UV == gather._FAR
    assert k.KIND_CODES == {"nearest": 0, "linear": 1, "cubic": 2}
    with pytest.raises(RuntimeError, match="kind must be a filter code 0-2, got 3"):
        k.sample(torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2), 3, k.ReadOptions(wrap_u=0, wrap_v=0))
    with pytest.raises(RuntimeError, match="uv must be contiguous"):
        k.sample(torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2, dtype=f64), 1, k.ReadOptions(wrap_u=0, wrap_v=0))

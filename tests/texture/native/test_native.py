"""The native CPU kernel of the mip taps: where it is used, and how it falls back.

Its values and gradients against the reference are in tests/test_backend.py.
"""
from __future__ import annotations

import importlib
import sys
import types

import pytest
import torch

import difftex
from difftex import _native as native
from difftex.texture import taps as taps_mod
from tests.conftest import use_backend

f64 = torch.float64
backend_mod = importlib.import_module("difftex.backend")  # the module, not the function difftex.backend
BUILT = native.load() is not None
needs_kernel = pytest.mark.skipif(not BUILT, reason="native kernel not built here (no compiler or ninja)")
needs_simd = pytest.mark.skipif(not (BUILT and native.load().simd_available()),
                                reason="native kernel not built here, or this CPU has no AVX2 / FMA")


def _case(dtype=f64, B=1):
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(B, 2, 16, 12, generator=g, dtype=dtype)
    uv = torch.rand(B, 3, 4, 2, generator=g, dtype=dtype) * 2 - 0.5
    dx = torch.randn(B, 3, 4, 2, generator=g, dtype=dtype) * 0.2
    dy = torch.randn(B, 3, 4, 2, generator=g, dtype=dtype) * 0.05
    return tex, uv, dx, dy


@needs_kernel
@pytest.mark.parametrize("filter", ["trilinear", "nearest-mip", "anisotropic", "auto", "bilinear", "ewa"])
def test_the_tap_filters_run_on_the_kernel_forward_and_backward(filter, monkeypatch):
    calls = []
    real = native.load()
    spy = types.SimpleNamespace(**{name: getattr(real, name) for name in dir(real) if not name.startswith("_")})
    for name in ("forward", "backward", "front", "ewa", "ewa_backward", "sample", "sample_backward"):
        setattr(spy, name, (lambda name: lambda *a, **k: calls.append(name) or getattr(real, name)(*a, **k))(name))
    monkeypatch.setattr(native, "load", lambda: spy)
    tex, uv, dx, dy = (t.requires_grad_() for t in _case())
    taps = filter in ("trilinear", "nearest-mip", "anisotropic", "auto")
    kernel = (["forward", "backward"] if taps else ["ewa", "ewa_backward"] if filter == "ewa" else
              ["sample", "sample_backward"])
    difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy).sum().backward()
    assert calls == kernel
    # Derivatives without a gradient: the taps' footprint front end runs on the kernel too.
    calls.clear()
    difftex.sample(tex, uv, filter=filter, uv_dx=dx.detach(), uv_dy=dy.detach()).sum().backward()
    assert calls == (["front"] if taps else []) + kernel
    calls.clear()
    with torch.no_grad():
        difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy, lod_bias=torch.zeros(1, 3, 4, dtype=f64))
    assert calls == (["front"] if taps else []) + kernel[:1]


def _front_cases(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Footprints over 16 octaves with every degenerate case, and per-point biases with non-finite ones."""
    g = torch.Generator().manual_seed(3)
    M = 4000
    dx = torch.randn(M, 2, generator=g, dtype=dtype) * torch.exp(torch.randn(M, 1, generator=g, dtype=dtype) * 3)
    dy = torch.randn(M, 2, generator=g, dtype=dtype) * torch.exp(torch.randn(M, 1, generator=g, dtype=dtype) * 3)
    dx[:10] = dy[:10] = 0.0  # a point
    dx[10:20, 0] = float("nan")
    dy[20:30, 1] = float("inf")
    dx[30:35, 1] = -float("inf")
    dx[35:40, 0], dy[35:40, 1] = float("nan"), float("inf")  # NaN wins
    dy[40:60] = dx[40:60] * 3  # rank 1: minor axis 0
    dy[60:80] = torch.stack((-dx[60:80, 1], dx[60:80, 0]), -1)  # round in uv (not in texels unless square)
    dx[80:85, 1] = float("nan")  # NaN in a component std::max would drop (its second argument)
    dy[85:90, 1] = float("nan")
    bias = torch.randn(M, generator=g, dtype=dtype) * 2
    bias[100:103] = torch.tensor([float("nan"), float("inf"), -float("inf")], dtype=dtype)
    bias[103:105] = torch.tensor([500.0, -500.0], dtype=dtype)
    return dx, dy, bias


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, f64])
@pytest.mark.parametrize("filter", ["trilinear", "anisotropic", "auto"])
@pytest.mark.parametrize("max_aniso, tolerance", [(1, 0.1), (4.5, 0.0), (16, 0.1), (16, 2.0)])
def test_the_kernel_front_end_gives_the_torch_front_end(dtype, filter, max_aniso, tolerance):
    dx, dy, bias = _front_cases(dtype)
    for b in (0.25, bias, torch.tensor(-1.5, dtype=dtype)):
        for H, W in ((64, 128), (1, 7)):
            args = (filter, dx, dy, b, H, W, 6 if H > 1 else 4, max_aniso, tolerance)
            D, axis, n = taps_mod.taps(*args)
            with use_backend("reference"):
                D_ref, axis_ref, n_ref = taps_mod.taps(*args)
            tol = 2e-6 if dtype == torch.float32 else 1e-12
            torch.testing.assert_close(D, D_ref, atol=tol, rtol=0)
            assert torch.isfinite(D).all()
            if filter == "trilinear":
                assert axis is None and n is None and axis_ref is None and n_ref is None
                continue
            assert torch.isfinite(axis).all()
            if n_ref is None:  # the torch path's one-tap-everywhere shortcut (no axis)
                assert (n == 1).all()
                continue
            assert torch.equal(n, n_ref)
            # Every point's axis, one-tap points' too: the cube map raises a count near an edge and spreads the
            # taps along it. (Degenerate footprints, where the reference has no finite non-zero axis: 0 in the
            # kernel, one tap at uv whatever the axis.)
            live = axis_ref.isfinite().all(-1) & (axis_ref.abs().amax(-1) > 0)
            scale = axis_ref[live].abs().amax(-1, keepdim=True)
            torch.testing.assert_close(axis[live] / scale, axis_ref[live] / scale, atol=tol, rtol=0)


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, f64])
@pytest.mark.parametrize("filter", ["anisotropic", "auto"])
def test_one_tap_points_get_their_major_axis(dtype, filter):
    # The cube map raises a one-tap point's count near an edge and spreads the taps along this axis; the
    # kernel gave 0 there, and a float64 auto cube read then changed by 2e-3 with a gradient on the directions.
    W, H = 128, 64
    dx = torch.tensor([[1.0 / W, 0.0], [1.05 / W, 0.0], [0.0, 0.5 / H], [0.7 / W, 0.7 / H], [8.0 / W, 0.0]],
                      dtype=dtype)
    dy = torch.tensor([[0.0, 1.0 / H], [0.0, 1.0 / H], [0.5 / W, 0.0], [-0.7 / W, 0.7 / H], [0.0, 1.0 / H]],
                      dtype=dtype)
    args = (filter, dx, dy, 0.0, H, W, 6, 16, 0.1)
    _, axis, n = taps_mod.taps(*args)
    with use_backend("reference"):
        _, axis_ref, n_ref = taps_mod.taps(*args)
    # Round footprints (0, 2, 3: the axis (1, 0), as lod.py's angle 0.5 atan2(0, 0)), longer ones (1, 4).
    assert torch.equal(n, n_ref) and n.tolist()[:4] == [1, 2, 1, 1] and n[4] > 2
    assert (axis.abs().amax(-1) > 0).all()
    torch.testing.assert_close(axis, axis_ref, atol=1e-6 if dtype == torch.float32 else 1e-12, rtol=0)


@needs_simd
@pytest.mark.parametrize("layout", ["contiguous", "uv_da"])
@pytest.mark.parametrize("kind", [0, 1, 2])
def test_the_vector_front_end_gives_the_scalar_one(layout, kind):
    # float32 footprints four points at a time (front.cpp front_range4: the scalar loop's operations lane by
    # lane but its own log2, the last points of a range through a copy) against the scalar loop, degenerate
    # footprints included; 3999 points leave a tail of three. kind: trilinear, anisotropic, auto. "uv_da":
    # nvdiffrast's interleaved derivatives, rows 4 floats apart.
    kernel = native.load()
    dx, dy, bias = _front_cases(torch.float32)
    M = dx.shape[0] - 1
    if layout == "uv_da":
        da = torch.cat((dx, dy), -1)
        dx, dy = da[:, :2], da[:, 2:]
    dx, dy = dx[:M], dy[:M]

    def front(simd: bool, b: torch.Tensor, n: int, max_aniso: float, tolerance: float):
        before = kernel.set_simd(simd)
        try:
            return kernel.front(dx, dy, b, bias0=0.25, height=64, width=128, levels=n, kind=kind,
                                max_aniso=max_aniso, tolerance=tolerance)
        finally:
            kernel.set_simd(before)

    for b in (dx.new_empty(0), bias[:M].contiguous()):
        for n, max_aniso, tolerance in ((6, 16.0, 0.1), (40, 4.5, 0.0), (40, 16.0, 2.0)):
            (D, axis, count), (D_ref, axis_ref, count_ref) = (front(simd, b, n, max_aniso, tolerance)
                                                              for simd in (True, False))
            # the levels within a float32 rounding (the log2s differ by 1e-12), the degenerate ones exactly;
            # the counts and axes bit for bit
            torch.testing.assert_close(D, D_ref, atol=0, rtol=2 ** -23)
            assert torch.equal(D[:100], D_ref[:100])
            assert torch.equal(count, count_ref) and torch.equal(axis, axis_ref)
            if kind:
                assert (count > 1).any() and (count == 1).any()


def test_disabled_or_failed_build_falls_back_to_the_torch_path(monkeypatch):
    tex, uv, dx, dy = _case()
    ref = difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy)
    monkeypatch.setenv("DIFFTEX_NATIVE", "0")
    assert native.load() is None and native.kernel(uv) is None
    monkeypatch.delenv("DIFFTEX_NATIVE")

    # An install that could not build the kernels has no difftex._C: a None entry in sys.modules makes the
    # import fail as it would then.
    monkeypatch.setitem(sys.modules, "difftex._C", None)
    monkeypatch.setattr(native, "_kernel", None)
    monkeypatch.setattr(native, "_tried", False)
    with pytest.warns(RuntimeWarning, match=r"the native CPU kernels are not built \(.*\); using the torch path "
                                            r"\(same results, slower\)\. To get them: install torch >= 2\.10"):
        assert native.load() is None
    assert native.load() is None  # tried once, no second warning or build
    out = difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)


def test_float16_and_cuda_points_take_the_torch_path():
    tex, uv, dx, dy = _case(torch.float16)
    assert native.kernel(uv) is None
    if torch.cuda.is_available():
        assert native.kernel(uv.float().cuda()) is None
    out = difftex.sample(tex, uv, filter="trilinear", uv_dx=dx, uv_dy=dy)
    ref = difftex.sample(tex.double(), uv.double(), filter="trilinear", uv_dx=dx.double(), uv_dy=dy.double())
    assert out.dtype == torch.float16
    torch.testing.assert_close(out.double(), ref, atol=3e-3, rtol=0)


@needs_kernel
@pytest.mark.parametrize("filter", ["trilinear", "anisotropic", "ewa"])
def test_double_backward_through_the_kernel_uses_the_torch_path(filter):
    tex, uv, dx, dy = _case()
    assert backend_mod.current() == "auto" and native.kernel(uv) is not None
    # Away from texel centres and level boundaries (kinks): uv and footprints as drawn.
    tex.requires_grad_()
    uv.requires_grad_()

    def f(t, u):
        return difftex.sample(t, u, filter=filter, uv_dx=dx, uv_dy=dy, wrap="repeat")

    # fast_mode: random projections of the second derivative (the full check takes a minute for ewa).
    assert torch.autograd.gradgradcheck(f, (tex, uv), atol=1e-6, rtol=1e-5, fast_mode=True)


@needs_kernel
def test_threads_split_the_points_without_changing_the_result():
    # The forward splits the points over torch's intra-op threads (chunks of 1024).
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(1, 3, 64, 64, generator=g)
    uv = torch.rand(1, 60, 90, 2, generator=g) * 3 - 1
    dx = torch.randn(1, 60, 90, 2, generator=g) * 0.1
    dy = torch.randn(1, 60, 90, 2, generator=g) * 0.02
    threads = torch.get_num_threads()
    try:
        outs = []
        for n in (1, 2):
            torch.set_num_threads(n)
            outs.append(difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(outs[0], outs[1])


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, f64])
def test_the_kernel_box_step_is_bit_identical_to_the_torch_one(dtype):
    g = torch.Generator().manual_seed(4)
    x = torch.rand(2, 3, 64, 130, generator=g, dtype=dtype).transpose(2, 3)  # non-contiguous, 130 x 64
    y = x[..., 0::2] + x[..., 1::2]  # the torch path of mipmap._box2, the same sums in the same order
    ref = torch.add(y[..., 0::2, :], y[..., 1::2, :]).mul_(0.25)
    out = native.load().box2(x)
    assert out.shape == (2, 3, 65, 32) and torch.equal(out, ref)
    with pytest.raises(RuntimeError, match="even H and W"):
        native.load().box2(x[..., :3, :])


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, f64])
def test_the_kernel_box_step_transpose_is_bit_identical_to_the_torch_one(dtype):
    mipmap = importlib.import_module("difftex.texture.pyramid.mipmap")  # the module, not the function
    g = torch.Generator().manual_seed(5)
    coarse = torch.randn(2, 3, 65, 32, generator=g, dtype=dtype).transpose(2, 3)  # non-contiguous, 32 x 65
    fine = torch.randn(2, 3, 64, 130, generator=g, dtype=dtype)
    with difftex.backend("reference"), torch.no_grad():
        ref_add = mipmap.step_adjoint(fine, coarse, (64, 130), inplace=False)
        ref_new = mipmap.step_adjoint(None, coarse.clone(), (64, 130), inplace=True)
    kernel = native.load()
    assert torch.equal(kernel.box2_adjoint(coarse, fine), ref_add) and torch.equal(kernel.box2_adjoint(coarse), ref_new)
    # Both equal the transpose of the box step: <box(x), c> = <x, box^T(c)>.
    x = torch.randn(2, 3, 64, 130, generator=g, dtype=dtype)
    lhs, rhs = (kernel.box2(x) * coarse).sum(), (x * kernel.box2_adjoint(coarse)).sum()
    torch.testing.assert_close(lhs, rhs, rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0)
    with torch.no_grad():  # the pyramid's adjoint takes the kernel where it may
        assert torch.equal(mipmap.step_adjoint(fine, coarse, (64, 130), inplace=False), ref_add)
    with pytest.raises(RuntimeError, match=r"fine must be \[\.\.\., 2h, 2w\]"):
        kernel.box2_adjoint(coarse, fine[..., :4])


@needs_kernel
def test_the_kernel_constants_are_the_python_ones():
    # Each rule has one Python constant; the kernel mirrors it and exports its copy.
    lod, wrap, anisotropic, auto, ewa = (importlib.import_module(f"difftex.texture.{name}") for name in (
        "lod", "wrap", "filters.anisotropic", "filters.auto", "filters.ewa"))  # modules, not same-named functions
    k = native.load()
    assert k.FAR == lod.FAR
    assert k.RATIO_TOL == anisotropic.RATIO_TOL
    assert k.MAX_LOG2 == auto.MAX_LOG2 and k.MAX_RATIO == 2.0 ** auto.MAX_LOG2
    assert k.LOG2_FLOOR == auto.LOG2_FLOOR
    assert k.ALPHA == ewa.ALPHA and k.MAX_MINOR == ewa.MAX_MINOR
    assert k.INDEX_CAP == wrap.INDEX_CAP == 2.0 ** 52
    assert k.WRAP_CODES == wrap.WRAP_CODES
    common = importlib.import_module("difftex.mapping.common")
    assert k.DIR_FLOOR == common.DIR_FLOOR and k.DIR_FLOOR_FLOAT32 == common.DIR_FLOOR_FLOAT32


@needs_kernel
def test_the_kernel_options_are_filled_by_keyword():
    k = native.load()
    opts = k.ReadOptions(wrap_u=1, wrap_v=3, border=0.5, d_grad=True)
    assert (opts.wrap_u, opts.wrap_v, opts.border, opts.nearest, opts.d_grad) == (1, 3, 0.5, False, True)
    need = k.TapNeeds(uv=True, axis=True)
    assert (need.levels, need.uv, need.D, need.axis) == (False, True, False, True)
    need = k.EwaNeeds(levels=True, D=True)
    assert (need.levels, need.uv, need.ellipse, need.D) == (True, False, False, True)
    with pytest.raises(TypeError):  # no positional flags
        k.TapNeeds(True, True, False, False)
    with pytest.raises(ValueError, match="wrap_v must be a wrap code 0-3, got 4"):
        k.ReadOptions(wrap_u=0, wrap_v=4)
    tex, uv, dx, dy = _case()
    D = torch.zeros(3, dtype=f64)
    with pytest.raises(ValueError, match="nearest-mip is not an EWA option"):
        k.ewa([tex[0, :, :4, :4].contiguous()], uv[0, 0].contiguous(), torch.zeros(4, 3, dtype=f64)[:3],
              D, D, D, 4, 4, k.ReadOptions(wrap_u=0, wrap_v=0, nearest=True))



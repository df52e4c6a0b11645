"""The native kernels of the box filters ("sat": csrc/sat.cpp, "ripmap": csrc/ripmap.cpp) against the torch path.

The torch path (``difftex.backend("reference")``) is the tested reference
(tests/texture/filters/test_sat.py, test_ripmap.py); here the kernel gives
its values and every first-order gradient, for every wrap mode on each
axis, float64 to 1e-10 and float32 to a stated tolerance, and the same NaN
behaviour.
"""
from __future__ import annotations

import types

import pytest
import torch

import difftex
from difftex import _native as native
from tests.conftest import use_backend

f64 = torch.float64
BUILT = native.load() is not None
needs_kernel = pytest.mark.skipif(not BUILT, reason="native kernel not built here (no compiler or ninja)")
# Every mode on each axis, and each mode against every other at least once.
WRAP_PAIRS = [("repeat", "repeat"), ("clamp", "clamp"), ("mirror", "mirror"), ("border", "border"),
              ("repeat", "mirror"), ("mirror", "border"), ("border", "clamp"), ("clamp", "repeat")]
BORDER = 0.35


def _case(seed: int, dtype=f64, B: int = 1, H: int = 13, W: int = 18):
    """Points across every edge, footprints from under a texel to past the texture, axis-aligned and not."""
    g = torch.Generator().manual_seed(seed)
    tex = torch.rand(B, 3, H, W, generator=g, dtype=dtype)
    uv = torch.rand(B, 5, 6, 2, generator=g, dtype=dtype) * 3 - 1
    scale = torch.exp2(torch.rand(B, 5, 6, 1, generator=g, dtype=dtype) * 8 - 6)
    dx = torch.randn(B, 5, 6, 2, generator=g, dtype=dtype) * scale
    dy = torch.randn(B, 5, 6, 2, generator=g, dtype=dtype) * scale * 0.4
    dx[:, 0, :, 1] = 0  # a row of axis-aligned footprints
    dy[:, 0, :, 0] = 0
    bias = torch.randn(B, 5, 6, generator=g, dtype=dtype) * 0.5
    return tex, uv, dx, dy, bias


def _run(backend: str, filter: str, wrap, tex, uv, dx, dy, bias, prebuilt: bool = False):
    """Values and the gradients of a random projection to every input."""
    leaves = [t.detach().clone().requires_grad_() for t in (tex, uv, dx, dy, bias)]
    with use_backend(backend):
        src = difftex.ripmap(leaves[0]) if prebuilt else leaves[0]
        out = difftex.sample(src, leaves[1], filter=filter, wrap=wrap, border_value=BORDER, uv_dx=leaves[2],
                             uv_dy=leaves[3], lod_bias=leaves[4])
        w = torch.rand(out.shape, generator=torch.Generator().manual_seed(99), dtype=out.dtype)
        grads = torch.autograd.grad((torch.where(torch.isnan(out), 0.0, out) * w).sum(), leaves)
    return out.detach(), grads


@needs_kernel
@pytest.mark.parametrize("filter", ["sat", "ripmap"])
@pytest.mark.parametrize("wrap", WRAP_PAIRS, ids=lambda w: "-".join(w))
def test_float64_values_and_gradients_match_the_torch_path(filter, wrap):
    case = _case(1)
    a, ga = _run("native", filter, wrap, *case)
    b, gb = _run("reference", filter, wrap, *case)
    torch.testing.assert_close(a, b, atol=1e-10, rtol=0)
    for name, x, y in zip(("texture", "uv", "uv_dx", "uv_dy", "lod_bias"), ga, gb):
        torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-10, msg=name)


@needs_kernel
@pytest.mark.parametrize("wrap", [("repeat", "clamp"), ("mirror", "border")], ids=lambda w: "-".join(w))
def test_a_prebuilt_ripmap_gets_the_same_gradients(wrap):
    case = _case(2, B=2)
    a, ga = _run("native", "ripmap", wrap, *case, prebuilt=True)
    b, gb = _run("reference", "ripmap", wrap, *case, prebuilt=True)
    c, gc = _run("native", "ripmap", wrap, *case)
    torch.testing.assert_close(a, b, atol=1e-10, rtol=0)
    torch.testing.assert_close(a, c, atol=1e-10, rtol=0)
    for x, y, z in zip(ga, gb, gc):
        torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(x, z, atol=1e-10, rtol=1e-10)


@needs_kernel
@pytest.mark.parametrize("filter", ["sat", "ripmap"])
def test_float32_against_the_torch_path(filter):
    # float32: the kernel's values within 2e-6 of the float64 torch path; its gradients within 1e-4 of the
    # largest entry of the float32 torch path's (same inputs: float32 rounding of a footprint flips some boxes
    # across the one-period cap, where the gradient jumps, so float64 is no reference for them).
    case = _case(3, H=37, W=29)
    wrap = ("mirror", "repeat")
    a, ga = _run("native", filter, wrap, *(t.float() for t in case))
    b, gb = _run("reference", filter, wrap, *(t.float() for t in case))
    c, _ = _run("reference", filter, wrap, *case)
    assert a.dtype == torch.float32
    torch.testing.assert_close(a.double(), c, atol=2e-6, rtol=0)
    torch.testing.assert_close(a, b, atol=2e-6, rtol=0)
    for name, x, y in zip(("texture", "uv", "uv_dx", "uv_dy", "lod_bias"), ga, gb):
        assert x.dtype == torch.float32
        torch.testing.assert_close(x, y, atol=1e-4 * y.abs().max().item(), rtol=0, msg=name)


@needs_kernel
@pytest.mark.parametrize("filter", ["sat", "ripmap"])
def test_gradcheck_on_the_kernel(filter):
    g = torch.Generator().manual_seed(4)
    tex = torch.rand(1, 2, 6, 9, dtype=f64, generator=g, requires_grad=True)
    uv = (torch.rand(1, 2, 3, 2, generator=g, dtype=f64) * 3 - 1).requires_grad_()
    dx = (torch.randn(1, 2, 3, 2, generator=g, dtype=f64) * 0.3).requires_grad_()
    dy = (torch.randn(1, 2, 3, 2, generator=g, dtype=f64) * 0.1).requires_grad_()
    bias = (torch.randn(1, 2, 3, dtype=f64, generator=g) * 0.5).requires_grad_()
    fn = lambda *x: difftex.sample(x[0], x[1], filter=filter, wrap=("mirror", "border"), border_value=BORDER,
                                   uv_dx=x[2], uv_dy=x[3], lod_bias=x[4])
    with use_backend("native"):
        assert torch.autograd.gradcheck(fn, (tex, uv, dx, dy, bias), atol=1e-7)
        # create_graph: the torch path differentiates the backward.
        assert torch.autograd.gradgradcheck(fn, (tex, uv, dx, dy, bias), atol=1e-6, fast_mode=True)


@needs_kernel
@pytest.mark.parametrize("filter", ["sat", "ripmap"])
def test_nan_uv_as_the_torch_path(filter):
    tex, uv, dx, dy, bias = _case(5)
    uv[0, 1, 2, 0] = float("nan")
    uv[0, 3, 4, 1] = float("inf")
    a, ga = _run("native", filter, "repeat", tex, uv, dx, dy, bias)
    b, gb = _run("reference", filter, "repeat", tex, uv, dx, dy, bias)
    nan = torch.isnan(a)
    assert torch.equal(nan, torch.isnan(b)) and nan.sum() == 2 * 3 and nan[0, :, 1, 2].all()
    torch.testing.assert_close(a[~nan], b[~nan], atol=1e-10, rtol=0)
    for x, y in zip(ga, gb):
        assert torch.isfinite(x).all()
        torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-10)


@needs_kernel
@pytest.mark.parametrize("filter", ["sat", "ripmap"])
def test_the_box_filters_run_on_the_kernel(filter, monkeypatch):
    calls = []
    real = native.load()
    spy = types.SimpleNamespace(**{name: getattr(real, name) for name in dir(real) if not name.startswith("_")})
    names = ("sat_forward", "sat_backward", "ripmap_build", "ripmap_read", "ripmap_read_backward", "ripmap_adjoint")
    for name in names:
        setattr(spy, name, (lambda name: lambda *a, **k: calls.append(name) or getattr(real, name)(*a, **k))(name))
    monkeypatch.setattr(native, "load", lambda: spy)
    tex, uv, dx, dy, _ = (t.requires_grad_() for t in _case(6))
    difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy).sum().backward()
    assert calls == (["sat_forward", "sat_backward"] if filter == "sat" else
                     ["ripmap_build", "ripmap_read", "ripmap_read_backward", "ripmap_adjoint"])
    calls.clear()
    with use_backend("reference"):
        difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy).sum().backward()
    assert calls == []


@needs_kernel
@pytest.mark.parametrize("filter", ["sat", "ripmap"])
def test_the_thread_count_does_not_change_the_result(filter):
    # Threads own row blocks (sat: table build, gradient scatter, suffix sums; ripmap: each level's rows in the
    # scatter): 1 and 4 threads agree, the ripmap's to the bit (every texel's terms come in point order), the
    # table's to rounding (the blocks' fix-up adds in another order); both match the torch path.
    g = torch.Generator().manual_seed(7)
    tex = torch.rand(1, 3, 300, 257, generator=g, requires_grad=True)
    uv = torch.rand(1, 40, 40, 2, generator=g).requires_grad_()
    d = torch.rand(1, 40, 40, 2, generator=g) * 0.2
    outs = []
    threads = torch.get_num_threads()
    try:
        for n in (1, 4):
            torch.set_num_threads(n)
            out = difftex.sample(tex, uv, filter=filter, wrap="mirror", uv_dx=d, uv_dy=d.flip(-1))
            outs.append((out.detach(), *torch.autograd.grad(out.sum(), (tex, uv))))
    finally:
        torch.set_num_threads(threads)
    exact = filter == "ripmap"
    for x, y in zip(outs[0], outs[1]):
        if exact:
            assert torch.equal(x, y)
        else:
            torch.testing.assert_close(x, y, atol=1e-5 * y.abs().max().item(), rtol=0)
    with use_backend("reference"):
        ref = difftex.sample(tex, uv, filter=filter, wrap="mirror", uv_dx=d, uv_dy=d.flip(-1))
        want = (ref.detach(), *torch.autograd.grad(ref.sum(), (tex, uv)))
    for x, y in zip(outs[1], want):
        torch.testing.assert_close(x, y, atol=1e-4 * y.abs().max().item(), rtol=0)

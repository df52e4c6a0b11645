"""The native CPU kernel of the mip taps: where it is used, and how it falls back.

Its values and gradients against the reference are in test_fast_path.py.
"""
from __future__ import annotations

import types

import pytest
import torch

import difftex
from difftex import native
from difftex.filters import basic

f64 = torch.float64
BUILT = native.load() is not None
needs_kernel = pytest.mark.skipif(not BUILT, reason="native kernel not built here (no compiler or ninja)")


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
    spy = types.SimpleNamespace(forward=lambda *a: calls.append("forward") or real.forward(*a),
                                backward=lambda *a: calls.append("backward") or real.backward(*a))
    monkeypatch.setattr(native, "load", lambda: spy)
    tex, uv, dx, dy = (t.requires_grad_() for t in _case())
    difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy).sum().backward()
    uses = filter in ("trilinear", "nearest-mip", "anisotropic", "auto")
    assert calls == (["forward", "backward"] if uses else [])


def test_disabled_or_failed_build_falls_back_to_the_torch_path(monkeypatch):
    tex, uv, dx, dy = _case()
    ref = difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy)
    monkeypatch.setenv("DIFFTEX_NATIVE", "0")
    assert native.load() is None and not native.usable(uv)
    monkeypatch.delenv("DIFFTEX_NATIVE")

    def broken(*args, **kwargs):
        raise RuntimeError("Ninja is required to load C++ extensions")

    monkeypatch.setattr(native, "_module", None)
    monkeypatch.setattr(native, "_tried", False)
    monkeypatch.setattr("torch.utils.cpp_extension.load", broken)
    with pytest.warns(RuntimeWarning, match=r"native CPU kernel unavailable, using the torch path "
                                            r"\(RuntimeError: Ninja is required"):
        assert native.load() is None
    assert native.load() is None  # tried once, no second warning or build
    out = difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)


def test_float16_and_cuda_points_take_the_torch_path():
    tex, uv, dx, dy = _case(torch.float16)
    assert not native.usable(uv)
    if torch.cuda.is_available():
        assert not native.usable(uv.float().cuda())
    out = difftex.sample(tex, uv, filter="trilinear", uv_dx=dx, uv_dy=dy)
    ref = difftex.sample(tex.double(), uv.double(), filter="trilinear", uv_dx=dx.double(), uv_dy=dy.double())
    assert out.dtype == torch.float16
    torch.testing.assert_close(out.double(), ref, atol=3e-3, rtol=0)


@needs_kernel
@pytest.mark.parametrize("filter", ["trilinear", "anisotropic"])
def test_double_backward_through_the_kernel_uses_the_torch_path(filter):
    tex, uv, dx, dy = _case()
    assert basic.IMPL == "fast" and native.usable(uv)
    # Away from texel centres and level boundaries (kinks): uv and footprints as drawn.
    tex.requires_grad_()
    uv.requires_grad_()

    def f(t, u):
        return difftex.sample(t, u, filter=filter, uv_dx=dx, uv_dy=dy, wrap="repeat")

    assert torch.autograd.gradgradcheck(f, (tex, uv), atol=1e-6, rtol=1e-5)


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

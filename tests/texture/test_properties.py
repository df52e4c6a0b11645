"""Property-based tests of sample(): every filter, wrap mode and odd shape; no crash, no NaN, values in range.

Hypothesis draws small textures (1x1, 1xN, Nx1, odd and even sides up to
9x11, C 1-3, B 1-2), uv far outside [0, 1] (up to 1e4), derivatives from
zero through tiny to huge (1e4) with mixed signs, and wrap modes per axis.
Derandomized so that CI sees the same examples every run.
"""
from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import difftex
from difftex import WRAP_MODES
from difftex.texture.options import FILTERS

# Outputs are convex combinations of texels (and the border constant): all but bicubic.
CONVEX = ("nearest", "bilinear", "trilinear", "nearest-mip", "anisotropic", "ewa", "auto", "ripmap", "sat")
SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow],
                print_blob=True)

MAGNITUDES = [0.0, 1e-30, 1e-7, 1e-3, 0.05, 0.3, 1.0, 7.0, 1e2, 1e4]


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py: many small ops


@st.composite
def cases(draw, nonfinite_derivatives: bool = False):
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    B = draw(st.integers(1, 2))
    Bt = draw(st.sampled_from([1, B]))
    C = draw(st.integers(1, 3))
    H = draw(st.sampled_from([1, 2, 3, 4, 5, 8, 9]))
    W = draw(st.sampled_from([1, 2, 3, 6, 7, 10, 11]))
    Ho, Wo = draw(st.integers(1, 3)), draw(st.integers(1, 4))
    seed = draw(st.integers(0, 2 ** 16))
    g = torch.Generator().manual_seed(seed)
    lo, span = draw(st.sampled_from([(0.0, 1.0), (-2.0, 5.0), (1e3, 1e-3)]))
    tex = lo + span * torch.rand(Bt, C, H, W, generator=g, dtype=torch.float64)
    # uv: uniform in a window of the drawn size around a drawn centre, so both
    # exact edges and huge values (up to 1e4) occur.
    centre = draw(st.sampled_from([0.0, 0.5, 1.0, -3.0, 1e2, -1e4, 1e4]))
    width = draw(st.sampled_from([0.0, 1e-3, 1.0, 10.0]))
    uv = centre + width * (torch.rand(B, Ho, Wo, 2, generator=g, dtype=torch.float64) - 0.5)
    if draw(st.booleans()):  # exact texel centres / edges
        uv = torch.round(uv * 4) / 4
    if nonfinite_derivatives:
        vals = torch.tensor([0.0, 1.0, float("inf"), -float("inf"), float("nan"), 1e-3, 1e4], dtype=torch.float64)
        pick = lambda: vals[torch.randint(0, len(vals), (B, Ho, Wo, 2), generator=g)]
        dx, dy = pick(), pick()
    else:
        mags = torch.tensor(MAGNITUDES, dtype=torch.float64)
        def pick():
            m = mags[torch.randint(0, len(mags), (B, Ho, Wo, 2), generator=g)]
            sign = torch.randint(0, 2, (B, Ho, Wo, 2), generator=g) * 2 - 1
            return m * sign * (1 + 0.5 * torch.rand(B, Ho, Wo, 2, generator=g, dtype=torch.float64))
        dx, dy = pick(), pick()
    wrap = draw(st.one_of(st.sampled_from(WRAP_MODES),
                          st.tuples(st.sampled_from(WRAP_MODES), st.sampled_from(WRAP_MODES))))
    return dict(
        texture=tex.to(dtype), uv=uv.to(dtype), uv_dx=dx.to(dtype), uv_dy=dy.to(dtype), wrap=wrap,
        border_value=draw(st.sampled_from([0.0, 0.5, -1.5])),
        lod_bias=draw(st.sampled_from([0.0, -2.0, 0.7, 3.0])),
        max_aniso=draw(st.sampled_from([1, 2.5, 16])),
        tolerance=draw(st.sampled_from([0.0, 0.25, 3.0])),
    )


def _kw(case, filter):
    kw = dict(case, filter=filter)
    if filter != "auto":
        kw.pop("tolerance")
    return kw


def _range(case):
    t = case["texture"].double()
    lo, hi = t.min().item(), t.max().item()
    wrap = case["wrap"] if isinstance(case["wrap"], tuple) else (case["wrap"],)
    if "border" in wrap:
        lo, hi = min(lo, case["border_value"]), max(hi, case["border_value"])
    slack = 1e-5 * max(1.0, abs(lo), abs(hi))
    return lo - slack, hi + slack


@settings(max_examples=60, **SETTINGS)
@given(case=cases(), filter=st.sampled_from(FILTERS))
def test_finite_input_gives_finite_output_in_range(case, filter):
    out = difftex.sample(**_kw(case, filter))
    B = case["uv"].shape[0]
    assert out.shape == (B, case["texture"].shape[1]) + case["uv"].shape[1:3]
    assert torch.isfinite(out).all(), out
    if filter in CONVEX:
        lo, hi = _range(case)
        assert out.min().item() >= lo and out.max().item() <= hi, (out.min().item(), out.max().item(), lo, hi)


@settings(max_examples=40, **SETTINGS)
@given(case=cases(), filter=st.sampled_from(FILTERS))
def test_gradients_are_finite(case, filter):
    tex = case["texture"].clone().requires_grad_(True)
    uv = case["uv"].clone().requires_grad_(True)
    dx = case["uv_dx"].clone().requires_grad_(True)
    dy = case["uv_dy"].clone().requires_grad_(True)
    out = difftex.sample(**_kw(dict(case, texture=tex, uv=uv, uv_dx=dx, uv_dy=dy), filter))
    w = torch.linspace(-1, 1, out.numel(), dtype=out.dtype).view(out.shape)
    grads = torch.autograd.grad((out * w).sum(), (tex, uv, dx, dy), allow_unused=True)
    for name, gr in zip(("texture", "uv", "uv_dx", "uv_dy"), grads):
        assert gr is None or torch.isfinite(gr).all(), (name, gr)


@settings(max_examples=40, **SETTINGS)
@given(case=cases(nonfinite_derivatives=True), filter=st.sampled_from(FILTERS[3:]))
def test_nonfinite_derivatives_give_finite_values_and_gradients(case, filter):
    tex = case["texture"].clone().requires_grad_(True)
    uv = case["uv"].clone().requires_grad_(True)
    dx = case["uv_dx"].clone().requires_grad_(True)
    out = difftex.sample(**_kw(dict(case, texture=tex, uv=uv, uv_dx=dx), filter))
    assert torch.isfinite(out).all(), out
    lo, hi = _range(case)
    assert out.min().item() >= lo and out.max().item() <= hi
    grads = torch.autograd.grad(out.sum(), (tex, uv, dx), allow_unused=True)
    assert all(gr is None or torch.isfinite(gr).all() for gr in grads)

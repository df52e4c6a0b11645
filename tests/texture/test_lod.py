"""The level of detail at its boundaries: the derivative from below at D = 0, at the top level and at integers.

``level()`` clamps ``D = log2 L + lod_bias`` to ``[0, levels - 1]`` and
``mip_blend`` blends ``floor(D)`` and ``floor(D) + 1``. Where D is an exact
integer, the blend has a kink; DESIGN.md defines its derivative as the one
from below (0 at D = 0, ``v_k - v_{k-1}`` at an integer k > 0, the same at
the top level), and every backend must give it. Checked against one-sided
finite differences in float64, for every mip filter with a level gradient.
"""
from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import difftex
from difftex.texture.options import MIP_FILTERS

f64 = torch.float64
FILTERS = MIP_FILTERS  # nearest-mip included: its level gradient is 0, as its finite differences at an integer
SIZE = 16  # 16 x 16 texture: levels 0 .. 4
TOP = 4
H = 1e-7


def _case(filter: str, k: int, seed: int = 0):
    """A texture, one uv point and a footprint whose level is exactly ``k`` (before the bias) for ``filter``.

    The footprint is round (trilinear: dx is the longer vector), 2^k level-0
    texels across and axis-aligned (a signed, possibly swapped pair of axes),
    so log2 L, the ellipse's axes and the tap count (1) are exact.
    """
    g = torch.Generator().manual_seed(seed)
    tex = torch.rand(1, 2, SIZE, SIZE, generator=g, dtype=f64)
    uv = (torch.rand(1, 1, 3, 2, generator=g, dtype=f64) * 0.8 + 0.1)
    a = 2.0 ** k / SIZE
    sx, sy, swap = (torch.randint(0, 2, (3,), generator=g) * 2 - 1).tolist()
    ratio = 0.75 if filter == "trilinear" else 1.0  # trilinear's max(|dx|, |dy|) must not tie
    dx = torch.tensor([sx * a, 0.0], dtype=f64)
    dy = torch.tensor([0.0, sy * a * ratio], dtype=f64)
    if swap > 0:
        dx, dy = dx.flip(0), dy.flip(0)
    dx, dy = dx.expand(1, 1, 3, 2).clone(), dy.expand(1, 1, 3, 2)
    return tex, uv, dx, dy.clone()


def _value(filter, tex, uv, dx, dy, bias):
    return (difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy, lod_bias=bias, wrap="repeat")
            * torch.tensor([1.0, -0.7], dtype=f64).view(1, 2, 1, 1)).sum()


def _check_from_below(filter: str, k: int, bias: float, seed: int = 0) -> None:
    tex, uv, dx, dy = _case(filter, k, seed)
    b = torch.full((1, 1, 3), bias, dtype=f64, requires_grad=True)
    gdx, gdy = dx.clone().requires_grad_(), dy.clone().requires_grad_()
    f = _value(filter, tex.requires_grad_(), uv, gdx, gdy, b)
    # nearest-mip passes no level gradient at all (None): count it as 0.
    grads = torch.autograd.grad(f, (b, gdx, gdy), allow_unused=True)
    gb, gx, gy = (torch.zeros_like(x) if g is None else g for x, g in zip((b, gdx, gdy), grads))
    with torch.no_grad():
        f0 = _value(filter, tex, uv, dx, dy, bias)
        below = (f0 - _value(filter, tex, uv, dx, dy, bias - H)) / H
        # Shrinking the footprint by (1 - h) lowers the level: log2(1 - h) ~ -h / ln 2.
        shrunk = (f0 - _value(filter, tex, uv, dx * (1 - H), dy * (1 - H), bias)) / H
    D = k + bias
    where = f"{filter} D = {D}"
    torch.testing.assert_close(gb.sum(), below, atol=1e-6, rtol=0, msg=where)
    torch.testing.assert_close((gx * dx).sum() + (gy * dy).sum(), shrunk, atol=1e-6, rtol=0, msg=where)
    if D <= 0 or D > TOP:  # clamped (or at D = 0, clamped from below): no level gradient
        assert gb.abs().max() == 0, where


@pytest.mark.parametrize("filter", FILTERS)
@pytest.mark.parametrize("k, bias", [(0, 0.0), (2, -2.0), (TOP, 0.0), (2, 2.0), (1, 0.0), (2, 0.0), (3, 0.0),
                                     (2, 1.0), (0, -1.0), (TOP, 1.0)])
def test_the_level_gradient_is_the_derivative_from_below(filter, k, bias, backend):
    _check_from_below(filter, k, bias)


def test_a_one_to_one_view_has_no_level_gradient_at_d_0(backend):
    # The case: a 64^2 texture shown at 64^2 has D = 0 at every pixel; its level gradient is 0 (from
    # below: clamped), not -v_0 (torch.clamp's gradient of 1 meeting a one-level blend) as before.
    tex = torch.rand(1, 3, 64, 64, dtype=f64)
    uv = (torch.stack(torch.meshgrid(torch.arange(64), torch.arange(64), indexing="xy"), -1) + 0.5) / 64
    uv = uv.to(f64).unsqueeze(0)
    dx = torch.tensor([1 / 64, 0.0], dtype=f64).expand(1, 64, 64, 2).clone().requires_grad_()
    dy = torch.tensor([0.0, 1 / 64], dtype=f64).expand(1, 64, 64, 2).clone().requires_grad_()
    bias = torch.zeros((), dtype=f64, requires_grad=True)
    for filter in FILTERS:
        out = difftex.sample(tex.requires_grad_(), uv, filter=filter, uv_dx=dx, uv_dy=dy, lod_bias=bias)
        grads = torch.autograd.grad(out.sum(), (bias, dx, dy), allow_unused=True)
        gb, gx, gy = (torch.zeros_like(x) if g is None else g for x, g in zip((bias, dx, dy), grads))
        assert gb == 0, filter
        if filter != "ewa":  # EWA's Gaussian depends on the footprint's shape too, not only through the level
            assert gx.abs().max() == 0 and gy.abs().max() == 0, filter


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(filter=st.sampled_from(FILTERS), k=st.integers(0, TOP), bias=st.integers(-2, 2),
       seed=st.integers(0, 2 ** 16))
def test_property_exact_integer_levels_take_the_derivative_from_below(filter, k, bias, seed, backend):
    _check_from_below(filter, k, float(bias), seed)


def test_level_gradient_mask():
    x = torch.tensor([-1.0, 0.0, 0.5, 3.0, 3.5, float("nan")], dtype=f64, requires_grad=True)
    from difftex.texture.lod import level
    D = level(x, 0.0, 4)
    assert D.tolist() == [0.0, 0.0, 0.5, 3.0, 3.0, 0.0]
    (g,) = torch.autograd.grad(D.sum(), x)
    assert g.tolist() == [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]

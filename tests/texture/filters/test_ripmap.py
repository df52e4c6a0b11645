"""The "ripmap" filter (difftex/texture/filters/ripmap.py): values, accuracy where it wins and loses, gradients."""
from __future__ import annotations

import pytest
import torch

import difftex
from difftex.metrics import psnr
from difftex.testing import checker_noise_texture
from experiments.studies.box_filters import footprint_points, parallelogram_reference, rotated

f64 = torch.float64
WRAPS = ("repeat", "clamp", "mirror", "border")


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _points(B: int, Ho: int, Wo: int, seed: int, scale: float = 0.2, dtype=f64):
    g = _gen(seed)
    uv = torch.rand(B, Ho, Wo, 2, generator=g, dtype=dtype) * 3 - 1
    dx = torch.randn(B, Ho, Wo, 2, generator=g, dtype=dtype) * scale
    dy = torch.randn(B, Ho, Wo, 2, generator=g, dtype=dtype) * scale * 0.3
    return uv, dx, dy


@pytest.mark.parametrize("wrap_u", WRAPS)
def test_a_texture_constant_along_v_reads_as_a_one_dimensional_mip_along_u(wrap_u):
    # Every row of levels holds the one-row texture's mip chain, and the level along u comes from the box's
    # width |dx_u| + |dy_u|: the same as trilinear on the one-row texture with that length.
    row = torch.rand(1, 2, 1, 37, dtype=f64, generator=_gen(1))
    tex = row.expand(1, 2, 11, 37)
    uv, dx, dy = _points(2, 4, 6, seed=2, scale=0.1)
    bias = torch.randn(2, 4, 6, dtype=f64, generator=_gen(3)) * 0.5
    out = difftex.sample(tex, uv, filter="ripmap", wrap=(wrap_u, "mirror"), uv_dx=dx, uv_dy=dy, lod_bias=bias)
    width = torch.stack((dx[..., 0].abs() + dy[..., 0].abs(), torch.zeros_like(dx[..., 0])), -1)
    ref = difftex.sample(row, uv, filter="trilinear", wrap=(wrap_u, "mirror"), uv_dx=width,
                         uv_dy=torch.zeros_like(width), lod_bias=bias)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)


def _scores(J):
    # Every point with the footprint J (texels per pixel column / row, as columns), scored against 16 x 16
    # bilinear samples over its parallelogram: the study experiments/studies/box_filters.py charts.
    tex = checker_noise_texture(64, dtype=f64)
    uv, dx, dy = footprint_points(16, 64, J, seed=11)
    ref = parallelogram_reference(tex, uv, dx, dy)
    return {f: psnr(difftex.sample(tex, uv, filter=f, uv_dx=dx, uv_dy=dy), ref)
            for f in ("trilinear", "ripmap", "sat", "anisotropic")}


@pytest.mark.parametrize("J", [rotated(8, 1, 0), rotated(1, 8, 0), rotated(16, 2, 0)], ids=["u8:1", "v1:8", "u16:2"])
def test_axis_aligned_anisotropic_footprints_beat_trilinear(J):
    # Measured: 39.4 vs 35.0 dB (u 8:1), 39.4 vs 35.5 (v 1:8), 43.0 vs 39.6 (16:2); the summed-area table's
    # exact box is 48-60 dB.
    s = _scores(J)
    assert s["ripmap"] >= s["trilinear"] + 3.0, s
    assert s["sat"] >= s["ripmap"] + 5.0, s


@pytest.mark.parametrize("J", [rotated(8, 1, 45), rotated(16, 2, 45)], ids=["45deg 8:1", "45deg 16:2"])
def test_a_diagonal_footprint_gains_nothing_over_trilinear(J):
    # The seed's warning as numbers: a 45-degree footprint's box is a square, so the ripmap reads the level
    # trilinear reads (measured 15.9 vs 15.6 dB and 17.2 vs 17.2) while the anisotropic taps along the
    # footprint reach 38-39 dB. The box of the summed-area table blurs the same way (16.0, 17.7).
    s = _scores(J)
    assert abs(s["ripmap"] - s["trilinear"]) <= 1.0, s
    assert s["sat"] <= s["trilinear"] + 1.0, s
    assert s["anisotropic"] >= s["ripmap"] + 15.0, s


def test_magnified_reads_are_bilinear():
    tex = torch.rand(1, 3, 9, 14, dtype=f64, generator=_gen(4))
    uv, dx, dy = _points(1, 5, 6, seed=5, scale=1e-3)
    for wrap in WRAPS:
        out = difftex.sample(tex, uv, filter="ripmap", wrap=wrap, border_value=0.4, uv_dx=dx, uv_dy=dy)
        ref = difftex.sample(tex, uv, filter="bilinear", wrap=wrap, border_value=0.4)
        torch.testing.assert_close(out, ref, atol=1e-14, rtol=0, msg=wrap)


def test_level_blend_weights():
    # A box 4 x 2^1.5 texels: level (2, 1.5), i.e. half (2, 1) and half (2, 2) of the ripmap.
    tex = torch.rand(1, 1, 32, 32, dtype=f64, generator=_gen(6))
    uv = torch.rand(1, 3, 3, 2, dtype=f64, generator=_gen(7))
    dx = torch.tensor([4 / 32, 0.0], dtype=f64).expand(1, 3, 3, 2)
    dy = torch.tensor([0.0, 2 ** 1.5 / 32], dtype=f64).expand(1, 3, 3, 2)
    rip = difftex.ripmap(tex)
    out = difftex.sample(rip, uv, filter="ripmap", uv_dx=dx, uv_dy=dy)
    lv = lambda i, j: difftex.sample(rip[i, j], uv, filter="bilinear")
    want = (1 - (1.5 - 1)) * lv(2, 1) + 0.5 * lv(2, 2)
    torch.testing.assert_close(out, want, atol=1e-14, rtol=0)
    # Which vector is which and their signs do not matter, only the axis-aligned box.
    swapped = difftex.sample(rip, uv, filter="ripmap", uv_dx=-dy, uv_dy=dx)
    torch.testing.assert_close(swapped, out, atol=1e-14, rtol=0)


@pytest.mark.parametrize("wrap", ["repeat", ("mirror", "border"), ("clamp", "repeat")])
def test_gradcheck_texture_uv_derivatives_and_bias(wrap):
    # Every wrap mode is the bilinear read's (tested with it); here the blend over four levels and its weights.
    g = _gen(8)
    tex = torch.rand(1, 1, 7, 10, dtype=f64, generator=g, requires_grad=True)
    uv, dx, dy = _points(1, 2, 3, seed=9, scale=0.3)
    bias = (torch.randn(1, 2, 3, dtype=f64, generator=g) * 0.5).requires_grad_()
    leaves = [t.requires_grad_() for t in (uv, dx, dy)]
    fn = lambda t, u, a, b, s: difftex.sample(t, u, filter="ripmap", wrap=wrap, border_value=0.3, uv_dx=a,
                                               uv_dy=b, lod_bias=s)
    # The other wraps only change the reads: random projections (fast_mode) suffice there and save ~100 lookups.
    assert torch.autograd.gradcheck(fn, (tex, *leaves, bias), atol=1e-7, fast_mode=wrap != "repeat")


def test_prebuilt_ripmap_levels_get_their_gradients_and_equal_the_texture_path():
    tex = torch.rand(1, 2, 12, 9, dtype=f64, generator=_gen(10), requires_grad=True)
    uv, dx, dy = _points(1, 4, 4, seed=11, scale=0.3)
    rip = difftex.ripmap(tex)
    a = difftex.sample(rip, uv, filter="ripmap", uv_dx=dx, uv_dy=dy)
    b = difftex.sample(tex, uv, filter="ripmap", uv_dx=dx, uv_dy=dy)
    torch.testing.assert_close(a, b, atol=1e-14, rtol=0)
    w = torch.rand(a.shape, dtype=f64, generator=_gen(12))
    ga, = torch.autograd.grad((a * w).sum(), tex)
    gb, = torch.autograd.grad((b * w).sum(), tex)
    torch.testing.assert_close(ga, gb, atol=1e-13, rtol=0)
    assert ga.abs().sum() > 0


def test_batches_match_single_lookups():
    tex = torch.rand(2, 3, 10, 13, dtype=f64, generator=_gen(13))
    uv, dx, dy = _points(2, 3, 5, seed=14)
    bias = torch.randn(2, 3, 5, dtype=f64, generator=_gen(15))
    out = difftex.sample(tex, uv, filter="ripmap", uv_dx=dx, uv_dy=dy, lod_bias=bias)
    for b in range(2):
        one = difftex.sample(tex[b:b + 1], uv[b:b + 1], filter="ripmap", uv_dx=dx[b:b + 1], uv_dy=dy[b:b + 1],
                             lod_bias=bias[b:b + 1])
        torch.testing.assert_close(out[b:b + 1], one, atol=1e-14, rtol=0)
    # One texture, two views.
    shared = difftex.sample(tex[:1], uv, filter="ripmap", uv_dx=dx, uv_dy=dy, lod_bias=bias)
    torch.testing.assert_close(shared[:1], out[:1], atol=1e-14, rtol=0)


def test_float32_matches_float64():
    tex = torch.rand(1, 3, 33, 20, dtype=f64, generator=_gen(16))
    uv, dx, dy = _points(1, 6, 7, seed=17)
    ref = difftex.sample(tex, uv, filter="ripmap", uv_dx=dx, uv_dy=dy, wrap="mirror")
    out = difftex.sample(tex.float(), uv.float(), filter="ripmap", uv_dx=dx.float(), uv_dy=dy.float(), wrap="mirror")
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), ref, atol=2e-6, rtol=0)


def test_nan_uv_gives_nan_and_no_gradient_elsewhere():
    tex = torch.rand(1, 2, 8, 8, dtype=f64, generator=_gen(18), requires_grad=True)
    uv, dx, dy = _points(1, 2, 3, seed=19)
    uv[0, 0, 1, 0] = float("nan")
    dx.requires_grad_()
    out = difftex.sample(tex, uv, filter="ripmap", uv_dx=dx, uv_dy=dy)
    assert torch.isnan(out[0, :, 0, 1]).all() and torch.isfinite(out.sum((0, 1))[torch.arange(2) != 0]).all()
    torch.where(torch.isnan(out), 0.0, out).sum().backward()
    assert torch.isfinite(tex.grad).all() and torch.isfinite(dx.grad).all() and dx.grad[0, 0, 1].abs().max() == 0


def test_bad_input():
    tex = torch.rand(1, 1, 4, 4)
    uv = torch.rand(1, 2, 2, 2)
    with pytest.raises(ValueError, match=r"uv_dx: required by filter 'ripmap'"):
        difftex.sample(tex, uv, filter="ripmap")
    with pytest.raises(ValueError, match=r"filter: 'ripmap' is not supported by cubemap"):
        difftex.envmap.cubemap(torch.rand(1, 6, 1, 4, 4), torch.randn(1, 2, 2, 3), filter="ripmap",
                               dirs_dx=torch.zeros(1, 2, 2, 3), dirs_dy=torch.zeros(1, 2, 2, 3))

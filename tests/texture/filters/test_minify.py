"""Minification filters (trilinear, nearest-mip, anisotropic, EWA), difftex.lod and the grazing-plane scene."""
from __future__ import annotations

import math
import time

import pytest
import torch
import torch.nn.functional as F

import difftex
from difftex import lod, mipmap
from difftex.texture.filters import trilinear as trilinear_mod
from difftex.texture.lod import ellipse, footprint
from difftex.texture.options import MIP_FILTERS
from difftex.metrics import psnr
from difftex.testing import checker_noise_texture, grazing_plane, supersampled

MIP = ("trilinear", "nearest-mip", "anisotropic", "ewa")
f64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py: many small ops


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _iso(B, Ho, Wo, L, H, W, theta=0.0, dtype=f64):
    """Derivatives of a conformal footprint: both vectors L texels long, rotated by theta."""
    c, s = math.cos(theta), math.sin(theta)
    dx = torch.tensor([L * c / W, L * s / H], dtype=dtype).expand(B, Ho, Wo, 2).clone()
    dy = torch.tensor([-L * s / W, L * c / H], dtype=dtype).expand(B, Ho, Wo, 2).clone()
    return dx, dy


def _grid(level, uv, padding="border"):
    return F.grid_sample(level, 2 * uv - 1, mode="bilinear", padding_mode=padding, align_corners=False)


# ---------------------------------------------------------------- lod

def test_lod_is_the_seed_formula():
    g = _gen(0)
    dx = torch.randn(2, 5, 6, 2, dtype=f64, generator=g) * 0.05
    dy = torch.randn(2, 5, 6, 2, dtype=f64, generator=g) * 0.05
    H, W = 48, 80
    size = torch.tensor([W, H], dtype=f64)
    L = torch.maximum((dx * size).norm(dim=-1), (dy * size).norm(dim=-1))
    levels = 1 + math.ceil(math.log2(80))
    ref = torch.log2(L).clamp(0, levels - 1)
    torch.testing.assert_close(lod(dx, dy, (H, W)), ref, atol=1e-12, rtol=0)
    tex = torch.zeros(1, 1, H, W, dtype=f64)
    torch.testing.assert_close(lod(dx, dy, tex), ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(lod(dx, dy, mipmap(tex, max_levels=3)), torch.log2(L).clamp(0, 2), atol=1e-12, rtol=0)
    bias = torch.randn(2, 5, 6, dtype=f64, generator=g)
    torch.testing.assert_close(lod(dx, dy, (H, W), lod_bias=bias, levels=4), (torch.log2(L) + bias).clamp(0, 3),
                               atol=1e-12, rtol=0)


def test_lod_degenerate_derivatives_are_finite_with_zero_gradient():
    vals = [0.0, float("inf"), float("-inf"), float("nan"), 1e30, 1e-30, 3e38]
    dx = torch.tensor([[v, 0.01] for v in vals], dtype=torch.float32).view(1, 1, -1, 2).requires_grad_(True)
    dy = torch.tensor([[0.0, v] for v in vals], dtype=torch.float32).view(1, 1, -1, 2).requires_grad_(True)
    D = lod(dx, dy, (256, 256))
    assert torch.isfinite(D).all()
    # zero -> uses the other finite entry; inf -> coarsest; NaN -> level 0.
    assert D[0, 0, 1].item() == 8 and D[0, 0, 2].item() == 8 and D[0, 0, 3].item() == 0
    assert D[0, 0, 4].item() == 8 and D[0, 0, 6].item() == 8
    D.sum().backward()
    assert torch.isfinite(dx.grad).all() and torch.isfinite(dy.grad).all()
    assert (dx.grad[0, 0, 1:4] == 0).all() and (dy.grad[0, 0, 1:4] == 0).all()
    z = torch.zeros(1, 2, 2, 2, requires_grad=True)
    D = lod(z, z, (16, 16), lod_bias=torch.tensor(float("nan")))
    D.sum().backward()
    assert (D == 0).all() and (z.grad == 0).all()


def test_ellipse_axes_match_svd():
    g = _gen(1)
    dx = torch.randn(1, 8, 8, 2, dtype=f64, generator=g)
    dy = torch.randn(1, 8, 8, 2, dtype=f64, generator=g)
    fp = footprint(dx, dy, 32, 64)
    ell = ellipse(fp)
    size = torch.tensor([64.0, 32.0], dtype=f64)
    J = torch.stack((dx * size, dy * size), -1)  # columns: texels per pixel column / row
    U, S, _ = torch.linalg.svd(J)
    scale = torch.exp2(fp.log2_scale)
    torch.testing.assert_close(ell.major * scale, S[..., 0], atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(ell.minor * scale, S[..., 1], atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(torch.exp2(ell.log2_major), S[..., 0], atol=1e-10, rtol=1e-10)
    torch.testing.assert_close((ell.direction * U[..., 0]).sum(-1).abs(), torch.ones_like(S[..., 0]),
                               atol=1e-10, rtol=0)


# ------------------------------------------------------- trilinear values

def test_trilinear_at_level_zero_equals_bilinear():
    g = _gen(2)
    tex = torch.rand(2, 3, 20, 13, dtype=f64, generator=g, requires_grad=True)
    uv = (torch.rand(2, 6, 7, 2, dtype=f64, generator=g) * 3 - 1).requires_grad_(True)
    dx = torch.randn(2, 6, 7, 2, dtype=f64, generator=g).requires_grad_(True)
    dy = torch.randn(2, 6, 7, 2, dtype=f64, generator=g).requires_grad_(True)
    bias = torch.full((2, 6, 7), -100.0, dtype=f64, requires_grad=True)
    for wrap in ("repeat", ("mirror", "clamp"), "border"):
        a = difftex.sample(tex, uv, filter="trilinear", wrap=wrap, uv_dx=dx, uv_dy=dy, lod_bias=bias,
                           border_value=0.3)
        b = difftex.sample(tex, uv, filter="bilinear", wrap=wrap, border_value=0.3)
        torch.testing.assert_close(a, b, atol=1e-14, rtol=0)
        w = torch.randn(a.shape, dtype=f64, generator=g)
        ga = torch.autograd.grad((a * w).sum(), (tex, uv, dx, dy, bias))
        gb = torch.autograd.grad((b * w).sum(), (tex, uv))
        torch.testing.assert_close(ga[0], gb[0], atol=1e-13, rtol=0)
        torch.testing.assert_close(ga[1], gb[1], atol=1e-12, rtol=0)
        assert all((x == 0).all() for x in ga[2:])


@pytest.mark.parametrize("hw", [(64, 64), (45, 70)])
def test_trilinear_at_integer_level_equals_grid_sample_on_that_level(hw):
    H, W = hw
    g = _gen(3)
    tex = torch.rand(1, 2, H, W, dtype=f64, generator=g)
    m = mipmap(tex)
    uv = torch.rand(1, 9, 11, 2, dtype=f64, generator=g)
    for k in range(len(m)):
        dx, dy = _iso(1, 9, 11, 2.0 ** k, H, W, theta=0.3)
        out = difftex.sample(tex, uv, filter="trilinear", wrap="clamp", uv_dx=dx, uv_dy=dy)
        torch.testing.assert_close(out, _grid(m[k], uv), atol=1e-12, rtol=0)
        if k + 1 < len(m):  # halfway between levels: the plain average
            dx, dy = _iso(1, 9, 11, 2.0 ** (k + 0.5), H, W)
            out = difftex.sample(m, uv, filter="trilinear", wrap="clamp", uv_dx=dx, uv_dy=dy)
            torch.testing.assert_close(out, 0.5 * (_grid(m[k], uv) + _grid(m[k + 1], uv)), atol=1e-12, rtol=0)
            near = difftex.sample(m, uv, filter="nearest-mip", wrap="clamp", uv_dx=dx * 0.9, uv_dy=dy * 0.9)
            torch.testing.assert_close(near, _grid(m[k], uv), atol=1e-12, rtol=0)
            near = difftex.sample(m, uv, filter="nearest-mip", wrap="clamp", uv_dx=dx * 1.1, uv_dy=dy * 1.1)
            torch.testing.assert_close(near, _grid(m[k + 1], uv), atol=1e-12, rtol=0)


def test_trilinear_bias_gradient_is_level_difference():
    g = _gen(4)
    tex = torch.rand(1, 1, 32, 32, dtype=f64, generator=g)
    m = mipmap(tex)
    uv = torch.rand(1, 4, 4, 2, dtype=f64, generator=g)
    dx, dy = _iso(1, 4, 4, 2.0 ** 1.25, 32, 32)
    bias = torch.zeros(1, 4, 4, dtype=f64, requires_grad=True)
    out = difftex.sample(tex, uv, filter="trilinear", wrap="clamp", uv_dx=dx, uv_dy=dy, lod_bias=bias)
    (grad,) = torch.autograd.grad(out.sum(), bias)
    torch.testing.assert_close(grad, (_grid(m[2], uv) - _grid(m[1], uv)).sum(1), atol=1e-12, rtol=0)


# ----------------------------------------------------- anisotropic values

def test_anisotropic_with_isotropic_footprint_equals_trilinear():
    g = _gen(5)
    tex = torch.rand(1, 3, 64, 48, dtype=f64, generator=g)
    uv = torch.rand(2, 8, 8, 2, dtype=f64, generator=g)
    for L, theta in ((0.5, 0.0), (3.3, 0.4), (7.9, 2.0), (100.0, -1.0)):
        dx, dy = _iso(2, 8, 8, L, 64, 48, theta)
        a = difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy)
        t = difftex.sample(tex, uv, filter="trilinear", uv_dx=dx, uv_dy=dy)
        torch.testing.assert_close(a, t, atol=1e-12, rtol=0)


def test_anisotropic_is_the_mean_of_trilinear_taps_along_the_true_major_axis():
    g = _gen(6)
    H = W = 64
    tex = torch.rand(1, 2, H, W, dtype=f64, generator=g)
    uv = torch.rand(1, 3, 5, 2, dtype=f64, generator=g)
    # Footprint with axes 12 and 3.5 texels rotated by 0.6 rad, sheared in
    # screen space (J = R diag(12, 3.5) Q): N = ceil(12 / 3.5) = 4.
    th, ph = 0.6, 1.1
    R = torch.tensor([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]], dtype=f64)
    Q = torch.tensor([[math.cos(ph), -math.sin(ph)], [math.sin(ph), math.cos(ph)]], dtype=f64)
    J = R @ torch.diag(torch.tensor([12.0, 3.5], dtype=f64)) @ Q
    dx = (J[:, 0] / W).expand(1, 3, 5, 2)
    dy = (J[:, 1] / H).expand(1, 3, 5, 2)
    out = difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy, max_aniso=16)
    N = 4
    tdx, tdy = _iso(1, 3, 5, 12.0 / N, H, W)
    ref = 0
    for i in range(N):
        off = R[:, 0] * 12.0 * ((i + 0.5) / N - 0.5) / W
        ref = ref + difftex.sample(tex, uv + off, filter="trilinear", uv_dx=tdx, uv_dy=tdy) / N
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)
    # max_aniso = 2 caps the taps at 2, level from major / 2.
    out2 = difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy, max_aniso=2)
    tdx, tdy = _iso(1, 3, 5, 6.0, H, W)
    ref2 = sum(difftex.sample(tex, uv + R[:, 0] * 12.0 * ((i + 0.5) / 2 - 0.5) / W, filter="trilinear",
                              uv_dx=tdx, uv_dy=tdy) / 2 for i in range(2))
    torch.testing.assert_close(out2, ref2, atol=1e-12, rtol=0)


@pytest.mark.parametrize("backend", ["grid_sample"], indirect=True)
def test_pixels_that_need_one_tap_cost_one_tap(backend, monkeypatch):
    # The torch path's reads are countable (the native kernel loops over each point's own count).
    seen = []
    real = trilinear_mod.separable_sample

    def counting(texture, uv, *args):
        seen.append(uv.shape[1])
        return real(texture, uv, *args)

    monkeypatch.setattr(trilinear_mod, "separable_sample", counting)
    tex = torch.rand(1, 1, 64, 64)
    uv = torch.rand(1, 10, 10, 2)
    dx, dy = _iso(1, 10, 10, 4.0, 64, 64, 0.3, dtype=torch.float32)  # level 2 exactly
    # Half the pixels isotropic (1 tap), half 3:1 (3 taps, level log2(12/3) = 2).
    dx = dx.clone()
    dx[:, :5] *= 3
    difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy)
    assert sum(seen) == 50 * 1 + 50 * 3
    seen.clear()
    difftex.sample(tex, uv, filter="trilinear", uv_dx=dy, uv_dy=dy)
    assert sum(seen) == 100  # an exact integer level reads one level


# ------------------------------------------------------------ EWA values

def _ewa_brute(level, st, Sigma, wrap="repeat"):
    """Direct pbrt-v4 EWA of one point on one level: every texel in a wide window, float64."""
    Hk, Wk = level.shape[-2:]
    x, y = st[0] * Wk - 0.5, st[1] * Hk - 0.5
    Q = torch.linalg.inv(Sigma)
    num, den = 0, 0
    R = int(math.ceil(math.sqrt(Sigma.diagonal().max().item()))) + 2
    for iy in range(int(math.floor(y)) - R, int(math.floor(y)) + R + 2):
        for ix in range(int(math.floor(x)) - R, int(math.floor(x)) + R + 2):
            d = torch.tensor([ix - x, iy - y], dtype=f64)
            r2 = d @ Q @ d
            if r2 < 1:
                w = math.exp(-2 * r2) - math.exp(-2)
                num = num + w * level[0, :, iy % Hk, ix % Wk]
                den += w
    return num / den


@pytest.mark.parametrize("L2", [4.0, 2.0 ** 2.5])
def test_ewa_matches_a_brute_force_reference(L2):
    g = _gen(7)
    H, W = 40, 56
    tex = torch.rand(1, 2, H, W, dtype=f64, generator=g)
    m = mipmap(tex)
    uv = torch.rand(1, 2, 3, 2, dtype=f64, generator=g) * 3 - 1
    # Axes 6 * L2 and L2 texels (ratio 6 < max_aniso), rotated.
    th = 0.7
    R = torch.tensor([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]], dtype=f64)
    J = R @ torch.diag(torch.tensor([6 * L2, L2], dtype=f64))
    dx = (J[:, 0] / torch.tensor([W, H], dtype=f64)).expand(1, 2, 3, 2)
    dy = (J[:, 1] / torch.tensor([W, H], dtype=f64)).expand(1, 2, 3, 2)
    out = difftex.sample(tex, uv, filter="ewa", uv_dx=dx, uv_dy=dy)
    D = math.log2(L2)
    k0 = int(math.floor(D))
    t = D - k0
    for r in range(2):
        for c in range(3):
            ref = 0
            for k, wk in ((k0, 1 - t), (k0 + 1, t)):
                if wk == 0:
                    continue
                Hk, Wk = m[k].shape[-2:]
                Jk = torch.diag(torch.tensor([Wk / W, Hk / H], dtype=f64)) @ J
                ref = ref + wk * _ewa_brute(m[k], uv[0, r, c], Jk @ Jk.T + torch.eye(2, dtype=f64))
            torch.testing.assert_close(out[0, :, r, c], ref, atol=1e-12, rtol=0)


def test_ewa_of_a_constant_is_the_constant():
    tex = torch.full((1, 3, 33, 17), 0.7, dtype=f64)
    g = _gen(8)
    uv = torch.rand(1, 6, 6, 2, dtype=f64, generator=g) * 5
    dx = torch.randn(1, 6, 6, 2, dtype=f64, generator=g) * 0.3
    dy = torch.randn(1, 6, 6, 2, dtype=f64, generator=g) * 0.3
    for ma in (1, 4, 16):
        out = difftex.sample(tex, uv, filter="ewa", uv_dx=dx, uv_dy=dy, max_aniso=ma)
        torch.testing.assert_close(out, torch.full_like(out, 0.7), atol=1e-14, rtol=0)


# ----------------------------------------------------- grazing-plane scene

def test_grazing_plane_derivatives_are_exact():
    uv, dx, dy = grazing_plane(32, 20.0, 1.0, dtype=f64)
    assert torch.isfinite(uv).all()
    # Central differences on the 15x15 sub-pixel grid, whose centre sub-pixel
    # (7, 7) is the pixel centre: step 1/15 pixel, error O(1/225).
    fine = grazing_plane(32, 20.0, 1.0, ss=15, dtype=f64)[0]
    c = torch.arange(32) * 15 + 7
    torch.testing.assert_close(fine[:, c][:, :, c], uv)
    cdx = (fine[:, c][:, :, c + 1] - fine[:, c][:, :, c - 1]) / 2 * 15
    cdy = (fine[:, c + 1][:, :, c] - fine[:, c - 1][:, :, c]) / 2 * 15
    torch.testing.assert_close(cdx, dx, rtol=2e-3, atol=1e-9)
    torch.testing.assert_close(cdy, dy, rtol=2e-3, atol=1e-9)
    uv2, dx2, _ = grazing_plane(16, 20.0, 1.0, ss=2, dtype=f64)
    torch.testing.assert_close(uv2, grazing_plane(32, 20.0, 1.0, dtype=f64)[0])
    uv_sky, dx_sky, _ = grazing_plane(16, 5.0, 1.0, fov_deg=60)  # top rows look above the horizon
    assert torch.isnan(uv_sky[:, 0]).all() and (dx_sky[:, 0] == 0).all() and torch.isfinite(uv_sky[:, -1]).all()


def test_psnr_scores_non_finite_output_as_nan():
    ref = torch.rand(1, 3, 8, 8, generator=_gen(5))
    x = ref + 0.01
    assert abs(psnr(x, ref) - 40.0) < 1e-4
    ref_masked = ref.clone()
    ref_masked[..., :2, :] = float("nan")  # the reference's non-finite pixels are left out
    assert abs(psnr(x, ref_masked) - 40.0) < 1e-4
    x[..., 4:, :] = float("nan")  # a filter's NaN output must not score a perfect inf
    assert math.isnan(psnr(x, ref))
    x[..., 4:, :] = float("inf")
    assert math.isnan(psnr(x, ref))


def test_grazing_plane_psnr_ordering(capsys):
    """The issue's scene: 256x256, 1024^2 checker + noise, repeat, 16x16 supersampled bilinear reference."""
    torch.manual_seed(0)
    tex = checker_noise_texture(1024)
    uv, dx, dy = grazing_plane(256, 20.0, 1.0)
    ref = supersampled(tex, grazing_plane(256, 20.0, 1.0, ss=16)[0], 16, "repeat")
    mm = mipmap(tex)
    scores, times = {}, {}
    for name, kw in (("bilinear", {}), ("trilinear", {}), ("anisotropic", {"max_aniso": 16}),
                     ("ewa", {"max_aniso": 16})):
        t0 = time.perf_counter()
        out = difftex.sample(mm, uv, filter=name, uv_dx=dx, uv_dy=dy, **kw)
        times[name] = time.perf_counter() - t0
        scores[name] = psnr(out, ref)
    for ss in (4, 8):
        scores[f"bilinear {ss}x{ss}"] = psnr(F.avg_pool2d(difftex.sample(tex, grazing_plane(256, ss=ss)[0]), ss), ref)
    with capsys.disabled():
        print("\ngrazing plane PSNR (dB) vs 16x16 supersampled bilinear:",
              ", ".join(f"{k} {v:.2f}" for k, v in scores.items()))
    assert scores["anisotropic"] > scores["trilinear"] + 3
    assert scores["ewa"] > scores["trilinear"] + 3
    assert scores["trilinear"] > scores["bilinear"] + 3
    assert scores["anisotropic"] > scores["bilinear 4x4"]


def test_filters_approach_the_reference_as_the_footprint_is_resolved():
    tex = checker_noise_texture(256, checks=8)
    uv, dx, dy = grazing_plane(96, 15.0, 1.0, fov_deg=28)
    ref = supersampled(tex, grazing_plane(96, 15.0, 1.0, fov_deg=28, ss=8)[0], 8, "repeat")
    for f in ("anisotropic", "ewa"):
        scores = [psnr(difftex.sample(tex, uv, filter=f, uv_dx=dx, uv_dy=dy, max_aniso=a), ref) for a in (1, 2, 4, 16)]
        assert all(b > a + 0.3 for a, b in zip(scores, scores[1:])), (f, scores)


# ------------------------------------------------------------- gradients

def _grad_inputs(seed, J, Ho=2, Wo=3, H=11, W=9):
    g = _gen(seed)
    tex = torch.rand(1, 2, H, W, dtype=f64, generator=g, requires_grad=True)
    uv = (torch.rand(1, Ho, Wo, 2, dtype=f64, generator=g) * 0.8 + 0.1).requires_grad_(True)
    size = torch.tensor([W, H], dtype=f64)
    jit = 1 + 0.05 * torch.rand(1, Ho, Wo, 2, 2, dtype=f64, generator=g)
    Jp = torch.tensor(J, dtype=f64) * jit  # columns are the two footprint vectors, texels
    dx = (Jp[..., :, 0] / size).requires_grad_(True)
    dy = (Jp[..., :, 1] / size).requires_grad_(True)
    bias = (0.1 * torch.rand(1, Ho, Wo, dtype=f64, generator=g)).requires_grad_(True)
    return tex, uv, dx, dy, bias


@pytest.mark.parametrize("filter,J", [
    ("trilinear", [[2.3, -0.3], [0.4, 1.7]]),
    ("anisotropic", [[4.6, -0.4], [0.9, 1.3]]),
    ("ewa", [[4.6, -0.4], [0.9, 1.3]]),
    ("ewa", [[0.6, 0.1], [-0.2, 0.5]]),  # magnified: level 0, only the ellipse shape moves
])
@pytest.mark.parametrize("wrap", ["repeat", "border"])
def test_gradcheck(filter, J, wrap):
    tex, uv, dx, dy, bias = _grad_inputs(9, J)
    if filter == "anisotropic":
        ell = ellipse(footprint(dx.detach(), dy.detach(), 11, 9))
        ratio = ell.major / ell.minor
        assert ((ratio - ratio.floor()) > 0.05).all() and ((ratio.ceil() - ratio) > 0.05).all()
    fn = lambda t, u, a, b, c: difftex.sample(t, u, filter=filter, wrap=wrap, uv_dx=a, uv_dy=b, lod_bias=c,
                                              border_value=0.25)
    assert torch.autograd.gradcheck(fn, (tex, uv, dx, dy, bias), atol=1e-7)


def test_gradcheck_nearest_mip_and_double_backward_trilinear():
    tex, uv, dx, dy, bias = _grad_inputs(10, [[2.3, -0.3], [0.4, 1.7]])
    fn = lambda t, u: difftex.sample(t, u, filter="nearest-mip", uv_dx=dx, uv_dy=dy, lod_bias=bias)
    assert torch.autograd.gradcheck(fn, (tex, uv))
    fn = lambda t, u, a, c: difftex.sample(t, u, filter="trilinear", uv_dx=a, uv_dy=dy, lod_bias=c)
    assert torch.autograd.gradgradcheck(fn, (tex, uv, dx, bias))


@pytest.mark.parametrize("filter", MIP + ("auto",))
def test_degenerate_derivatives_give_finite_values_and_zero_gradients(filter):
    g = _gen(11)
    tex = torch.rand(1, 3, 32, 16, generator=g, requires_grad=True)
    uv = torch.rand(1, 1, 8, 2, generator=g).requires_grad_(True)
    vals = [0.0, float("inf"), float("-inf"), float("nan")]
    dx = torch.tensor([[v, v] for v in vals] + [[1e30, 1e-30], [1e-30, 0.0], [0.05, 0.0], [0.0, 0.0]])
    dy = torch.tensor([[v, 0.0] for v in vals] + [[0.0, 1e30], [0.0, 1e-30], [0.0, 0.0], [0.01, 0.0]])
    dx = dx.view(1, 1, 8, 2).requires_grad_(True)
    dy = dy.view(1, 1, 8, 2).requires_grad_(True)
    bias = torch.zeros(1, 1, 8, requires_grad=True)
    out = difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy, lod_bias=bias)
    assert torch.isfinite(out).all()
    grads = torch.autograd.grad(out.sum(), (tex, uv, dx, dy, bias), allow_unused=True)
    grads = [torch.zeros_like(x) if gr is None else gr for x, gr in zip((tex, uv, dx, dy, bias), grads)]
    assert all(torch.isfinite(gr).all() for gr in grads)
    assert (grads[2][0, 0, :4] == 0).all() and (grads[3][0, 0, :4] == 0).all()
    # Absurd biases too (NaN reads level 0, -inf / 1e4 clamp): finite, and
    # EWA's work stays bounded for the 1e30 footprints read at level 0.
    for b in (float("nan"), float("inf"), -float("inf"), 1e4):
        out = difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy, lod_bias=b)
        assert torch.isfinite(out).all(), b
    # The largest max_aniso: rank-1 footprints take all 1024 taps (EWA: a
    # 1024:1 ellipse), a bounded amount of work with finite results.
    out = difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy, max_aniso=1024)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("filter", ["trilinear", "anisotropic", "auto", "ewa"])
def test_nan_uv_sends_no_nan_to_the_footprint(filter, backend):
    # A masked-out NaN-uv pixel: its derivative and bias gradients are 0 on
    # every path (the torch path's mip_blend once gave 0 * NaN = NaN there).
    tex = torch.rand(1, 3, 8, 8, generator=_gen(21), dtype=f64)
    uv = torch.tensor([[[[0.3, 0.4], [float("nan"), 0.5]]]], dtype=f64)
    dx = torch.tensor([0.3, 0.05], dtype=f64).expand(1, 1, 2, 2).clone().requires_grad_(True)
    dy = torch.tensor([0.02, 0.2], dtype=f64).expand(1, 1, 2, 2).clone().requires_grad_(True)
    bias = torch.zeros(1, 1, 2, dtype=f64, requires_grad=True)
    out = difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy, lod_bias=bias)
    assert torch.isnan(out[0, :, 0, 1]).all() and torch.isfinite(out[0, :, 0, 0]).all()
    grads = torch.autograd.grad(torch.where(torch.isnan(out), 0.0, out).sum(), (dx, dy, bias))
    for g in grads:
        assert torch.isfinite(g).all()
        assert (g[0, 0, 1] == 0).all()
    assert grads[0][0, 0, 0].abs().sum() > 0  # the good pixel still has its gradient


@pytest.mark.parametrize("filter", MIP + ("auto",))
def test_huge_finite_uv_clamps_and_borders(filter):
    # Past 2^52 texels a coordinate has no fraction left: clamp reads the
    # edge texel, border the constant (the kernel once took x - floor as the
    # fraction there and gave 0 or NaN).
    tex = torch.full((1, 1, 4, 4), 0.5, requires_grad=True)
    uv = torch.tensor([[[[3e15, 0.5], [1e20, 1e20], [0.3, 0.6], [-1e20, 0.5]]]])
    dx = torch.tensor([0.25, 0.0]).expand(1, 1, 4, 2)
    dy = torch.tensor([0.0, 0.25]).expand(1, 1, 4, 2)
    for wrap, want in (("clamp", [0.5, 0.5, 0.5, 0.5]), ("border", [0.0, 0.0, 0.5, 0.0])):
        out = difftex.sample(tex, uv, filter=filter, wrap=wrap, uv_dx=dx, uv_dy=dy)
        torch.testing.assert_close(out.flatten(), torch.tensor(want), rtol=0, atol=1e-6)
        (g,) = torch.autograd.grad(out.sum(), tex)
        assert torch.isfinite(g).all(), wrap


@pytest.mark.parametrize("filter", MIP + ("auto",))
def test_nan_uv_poisons_only_its_pixel(filter):
    g = _gen(12)
    tex = torch.rand(1, 2, 16, 16, generator=g, requires_grad=True)
    uv = torch.rand(1, 4, 4, 2, generator=g)
    dx, dy = _iso(1, 4, 4, 3.0, 16, 16, 0.2, dtype=torch.float32)
    dx[:, :2] *= 3.5
    clean = difftex.sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy)
    bad = uv.clone()
    bad[0, 1, 2, 0] = float("nan")
    bad[0, 3, 3, 1] = float("inf")
    out = difftex.sample(tex, bad, filter=filter, uv_dx=dx, uv_dy=dy)
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[1, 2] = mask[3, 3] = True
    assert torch.isnan(out[0, :, mask]).all()
    torch.testing.assert_close(out[0, :, ~mask], clean[0, :, ~mask])
    (gt,) = torch.autograd.grad(torch.where(torch.isnan(out), 0.0, out).sum(), tex)
    assert torch.isfinite(gt).all()


# ------------------------------------------------- batch, dtype, Mipmap input

@pytest.mark.parametrize("filter", MIP + ("auto",))
def test_batches_and_dtypes(filter):
    g = _gen(13)
    tex = torch.rand(2, 3, 24, 40, dtype=f64, generator=g)
    uv = torch.rand(2, 5, 6, 2, dtype=f64, generator=g) * 2
    dx = torch.randn(1, 5, 6, 2, dtype=f64, generator=g) * 0.1
    dy = torch.randn(2, 5, 6, 2, dtype=f64, generator=g) * 0.1
    bias = torch.randn(2, 5, 6, dtype=f64, generator=g) * 0.3
    kw = dict(filter=filter, wrap=("repeat", "mirror"), lod_bias=bias, max_aniso=8)
    out = difftex.sample(tex, uv, uv_dx=dx, uv_dy=dy, **kw)
    assert out.shape == (2, 3, 5, 6) and out.dtype == f64
    for b in range(2):  # a batch of textures == each texture alone
        kb = dict(kw, lod_bias=bias[b:b + 1])
        one = difftex.sample(tex[b:b + 1], uv[b:b + 1], uv_dx=dx, uv_dy=dy[b:b + 1], **kb)
        torch.testing.assert_close(out[b:b + 1], one, atol=1e-12, rtol=0)
    shared = difftex.sample(tex[:1], uv, uv_dx=dx, uv_dy=dy, **kw)  # one texture, two views
    for b in range(2):
        kb = dict(kw, lod_bias=bias[b:b + 1])
        one = difftex.sample(tex[:1], uv[b:b + 1], uv_dx=dx, uv_dy=dy[b:b + 1], **kb)
        torch.testing.assert_close(shared[b:b + 1], one, atol=1e-12, rtol=0)
    f32 = difftex.sample(tex.float(), uv.float(), uv_dx=dx.float(), uv_dy=dy.float(),
                         **dict(kw, lod_bias=bias.float()))
    assert f32.dtype == torch.float32
    # nearest-mip can flip level on float32 rounding at a few pixels; the rest agree.
    close = ((f32.double() - out).abs() < 1e-4).float().mean().item()
    assert close > (0.97 if filter == "nearest-mip" else 0.999), close
    # A plain tensor builds only the levels read (EWA: all): the same values as the full pyramid, exactly.
    torch.testing.assert_close(difftex.sample(mipmap(tex), uv, uv_dx=dx, uv_dy=dy, **kw), out, atol=0, rtol=0)


@pytest.mark.parametrize("filter", ("trilinear", "nearest-mip", "anisotropic", "auto"))
@pytest.mark.parametrize("hw", [(32, 32), (24, 20), (13, 7)])
def test_texture_and_prebuilt_mipmap_give_the_same_gradients(filter, hw):
    # A plain texture is read through one node that builds the pyramid and
    # folds the level gradients in place (a level read at few points gets
    # its gradient scattered into the coarser levels' spread total); a
    # prebuilt Mipmap is read level by level through autograd. Both must
    # agree, for even chains, chains that turn odd, every wrap mode, batches
    # of textures and both dtypes.
    H, W = hw
    wrap = {(32, 32): "repeat", (24, 20): ("mirror", "border"), (13, 7): "clamp"}[hw]
    g = _gen(17)
    for dtype, tol in ((f64, 1e-12), (torch.float32, 2e-5)):
        tex = torch.rand(2, 3, H, W, dtype=dtype, generator=g)
        uv = torch.rand(2, 6, 5, 2, dtype=dtype, generator=g) * 3 - 1
        # footprints from magnified (level 0 read) to 20 texels (coarse levels)
        scale = torch.logspace(-1, 1.3, 30, dtype=dtype).view(1, 6, 5, 1)
        dx = torch.cat((scale / W, 0.3 * scale / H), -1).expand(2, 6, 5, 2)
        dy = torch.cat((-0.2 * scale / W, 0.6 * scale / H), -1).expand(2, 6, 5, 2)
        grads = []
        for build in (lambda t: t, mipmap):
            t = tex.clone().requires_grad_(True)
            u = uv.clone().requires_grad_(True)
            out = difftex.sample(build(t), u, filter=filter, uv_dx=dx, uv_dy=dy, max_aniso=4, wrap=wrap,
                                 border_value=0.3)
            (out * torch.linspace(-1, 2, out.numel(), dtype=dtype).view(out.shape)).sum().backward()
            grads.append((out.detach(), t.grad, u.grad))
        for a, b in zip(*grads):
            torch.testing.assert_close(a, b, atol=tol, rtol=tol)


@pytest.mark.parametrize("filter", ["trilinear", "nearest-mip", "anisotropic", "auto"])
@pytest.mark.parametrize("L", [0.5, 4.0, 5.0])
def test_a_plain_texture_builds_only_the_levels_its_points_read(filter, L, monkeypatch):
    # Footprints of L texels everywhere: magnified (0.5) builds level 0 only; an exact
    # level 2 (4.0) builds levels 0-2, with a gradient of D too (its derivative from
    # below reads level 1, not 3); level log2(5) builds 0-3. Values and the gradients
    # of texture, uv and derivatives equal those of the full prebuilt chain.
    built = []
    real = trilinear_mod.build_levels
    monkeypatch.setattr(trilinear_mod, "build_levels", lambda t, n: built.append(n) or real(t, n))
    tex = torch.rand(1, 2, 64, 64, dtype=f64, generator=_gen(3))
    uv = torch.rand(1, 4, 5, 2, dtype=f64, generator=_gen(4))
    dx, dy = _iso(1, 4, 5, L, 64, 64, 0.4)  # isotropic: anisotropic takes one tap at log2 L
    results = []
    for texture in ("plain", "prebuilt"):
        t, u, ddx, ddy = (x.clone().requires_grad_(True) for x in (tex, uv, dx, dy))
        out = difftex.sample(t if texture == "plain" else mipmap(t), u, filter=filter, uv_dx=ddx, uv_dy=ddy)
        out.pow(2).sum().backward()
        results.append([out.detach(), t.grad, u.grad, ddx.grad, ddy.grad])
    expected = {0.5: 1, 4.0: 3, 5.0: 3} if filter == "nearest-mip" else {0.5: 1, 4.0: 3, 5.0: 4}
    assert built[0] == expected[L]
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_user_supplied_levels_each_get_their_gradient():
    g = _gen(14)
    levels = [torch.rand(1, 1, 8, 8, dtype=f64, generator=g, requires_grad=True),
              torch.rand(1, 1, 4, 4, dtype=f64, generator=g, requires_grad=True),
              torch.rand(1, 1, 2, 2, dtype=f64, generator=g, requires_grad=True)]
    uv = torch.rand(1, 3, 3, 2, dtype=f64, generator=g)
    dx, dy = _iso(1, 3, 3, 2.0 ** 0.5, 8, 8)
    out = difftex.sample(mipmap(levels), uv, filter="trilinear", uv_dx=dx, uv_dy=dy)
    out.sum().backward()
    assert levels[0].grad.sum().item() == pytest.approx(9 * 0.5)
    assert levels[1].grad.sum().item() == pytest.approx(9 * 0.5)
    assert levels[2].grad is None


def test_cuda_same_code_path():
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    tex, uv, dx, dy, bias = (t.detach() for t in _grad_inputs(15, [[4.1, -0.4], [0.9, 1.3]]))
    for f in MIP:
        a = difftex.sample(tex, uv, filter=f, uv_dx=dx, uv_dy=dy, lod_bias=bias)
        b = difftex.sample(tex.cuda(), uv.cuda(), filter=f, uv_dx=dx.cuda(), uv_dy=dy.cuda(), lod_bias=bias.cuda())
        torch.testing.assert_close(a, b.cpu(), atol=1e-10, rtol=0)


# ------------------------------------------------------------- bad input

def test_bad_input():
    tex = torch.rand(1, 1, 8, 8)
    uv = torch.rand(1, 4, 5, 2)
    d = torch.zeros(1, 4, 5, 2)
    ok = dict(uv_dx=d, uv_dy=d)
    with pytest.raises(ValueError, match="uv_dx: required"):
        difftex.sample(tex, uv, filter="trilinear")
    with pytest.raises(ValueError, match="uv_dy: required"):
        difftex.sample(tex, uv, filter="ewa", uv_dx=d)
    with pytest.raises(ValueError, match=r"uv_dx.*\[1, 4, 5, 2\].*\(1, 5, 4, 2\)"):
        difftex.sample(tex, uv, filter="trilinear", uv_dx=torch.zeros(1, 5, 4, 2), uv_dy=d)
    with pytest.raises(ValueError, match=r"uv_dy.*last dimension 2"):
        difftex.sample(tex, uv, filter="anisotropic", uv_dx=d, uv_dy=torch.zeros(1, 4, 5, 3))
    with pytest.raises(ValueError, match=r"uv_dx.*4-D"):
        difftex.sample(tex, uv, filter="anisotropic", uv_dx=torch.zeros(4, 5, 2), uv_dy=d)
    with pytest.raises(TypeError, match=r"uv_dx.*dtype"):
        difftex.sample(tex, uv, filter="trilinear", uv_dx=d.double(), uv_dy=d)
    with pytest.raises(TypeError, match=r"uv_dy.*floating"):
        difftex.sample(tex, uv, filter="trilinear", uv_dx=d, uv_dy=d.long())
    with pytest.raises(ValueError, match=r"uv_dx.*device"):
        difftex.sample(tex, uv, filter="trilinear", uv_dx=d.to("meta"), uv_dy=d)
    with pytest.raises(ValueError, match="batch sizes"):
        difftex.sample(tex, uv.expand(2, -1, -1, -1), filter="trilinear", uv_dx=torch.zeros(3, 4, 5, 2), uv_dy=d)
    for bad in (0.5, 0, -1, float("nan"), float("inf"), 1024.5, 1e30):
        with pytest.raises(ValueError, match=r"max_aniso: expected a finite number in \[1, 1024\], got"):
            difftex.sample(tex, uv, filter="anisotropic", max_aniso=bad, **ok)
    for bad in ("4", True, None):
        with pytest.raises(TypeError, match="max_aniso"):
            difftex.sample(tex, uv, filter="ewa", max_aniso=bad, **ok)
    with pytest.raises(ValueError, match=r"lod_bias.*\[1, 4, 5\]"):
        difftex.sample(tex, uv, filter="trilinear", lod_bias=torch.zeros(1, 5, 4), **ok)
    with pytest.raises(ValueError, match=r"lod_bias"):
        difftex.sample(tex, uv, filter="trilinear", lod_bias=torch.zeros(4, 5), **ok)
    with pytest.raises(TypeError, match=r"lod_bias.*dtype"):
        difftex.sample(tex, uv, filter="trilinear", lod_bias=torch.zeros(1, 4, 5, dtype=f64), **ok)
    with pytest.raises(TypeError, match="lod_bias"):
        difftex.sample(tex, uv, filter="trilinear", lod_bias="1", **ok)
    with pytest.raises(ValueError, match="filter"):
        difftex.sample(tex, uv, filter="trilinearr", **ok)
    with pytest.raises(ValueError, match=r"texture\[1\]"):
        difftex.sample(difftex.Mipmap([tex, torch.zeros(1, 1, 3, 4)]), uv, filter="trilinear", **ok)
    with pytest.raises(ValueError, match="texture_size"):
        lod(d, d, (8,))
    with pytest.raises(ValueError, match="uv_dy"):
        lod(d, torch.zeros(1, 4, 4, 2), (8, 8))
    with pytest.raises(ValueError, match="levels"):
        lod(d, d, (8, 8), levels=0)
    with pytest.raises(ValueError, match=r"lod_bias: expected a scalar or \[B, Ho, Wo\] like uv_dx \(1, 4, 5\), got \(1, 5, 4\)"):
        lod(d, d, (8, 8), lod_bias=torch.zeros(1, 5, 4))
    with pytest.raises(ValueError, match=r"lod_bias: expected a scalar or \[B, Ho, Wo\] like uv_dx \(1, 4, 5\), got \(1, 1, 5\)"):
        lod(d, d, (8, 8), lod_bias=torch.zeros(1, 1, 5))
    with pytest.raises(ValueError, match="batch sizes"):
        lod(d.expand(2, -1, -1, -1), d.expand(2, -1, -1, -1), (8, 8), lod_bias=torch.zeros(3, 4, 5))
    with pytest.raises(TypeError, match="lod_bias: expected a number"):
        lod(d, d, (8, 8), lod_bias="1")


@pytest.mark.parametrize("filter", MIP_FILTERS)
def test_a_zero_output_gradient_gives_the_texture_zeros_not_none(filter, backend):
    # Every backend hands the texture a zero gradient where the loss ignores the image; the native nodes once
    # returned None for levels no point had read, leaving texture.grad None where the torch path gave zeros.
    tex = torch.rand(1, 3, 16, 16, dtype=f64, generator=_gen(31), requires_grad=True)
    uv = torch.rand(1, 4, 4, 2, dtype=f64, generator=_gen(32))
    d = torch.full((1, 4, 4, 2), 0.1, dtype=f64)
    (difftex.sample(tex, uv, filter=filter, uv_dx=d, uv_dy=d) * 0).sum().backward()
    assert tex.grad is not None and torch.equal(tex.grad, torch.zeros_like(tex)), filter

"""filter="auto" (difftex/texture/filters/auto.py) and difftex.levels_needed (difftex/texture/taps.py)."""
from __future__ import annotations

import math
import sys

import pytest
import torch

import difftex
from difftex.texture.options import MIP_FILTERS
from difftex import levels_needed, mipmap
from difftex.texture.filters import trilinear as trilinear_mod
from difftex.texture.filters.anisotropic import tap_count
from difftex.texture.filters.auto import auto_tap_count
from difftex.texture.lod import ellipse, footprint
from difftex.metrics import psnr
from difftex.testing import checker_noise_texture, grazing_plane, plane_scene, sphere_scene, supersampled

f64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py: many small ops


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _const_J(J, B, Ho, Wo, H, W, dtype=f64):
    """Derivatives of a constant texel Jacobian J (columns: texels per pixel column / row)."""
    J = torch.as_tensor(J, dtype=dtype)
    size = torch.tensor([W, H], dtype=dtype)
    return (J[:, 0] / size).expand(B, Ho, Wo, 2).clone(), (J[:, 1] / size).expand(B, Ho, Wo, 2).clone()


def _rot(t):
    return torch.tensor([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]], dtype=f64)


# ------------------------------------------------------------ tap counts

def test_tap_count_formula():
    # major = 64 texels, minor 64 / r >= 1.6, along a rotated axis.
    H, W = 64, 64
    for r, tol, want in ((1.0, 0.25, 1), (1.2, 0.25, 2), (1.2, 1.0, 1), (3.0, 0.0, 3), (7.5, 0.25, 7),
                         (16.0, 0.25, 13), (40.0, 0.25, 16), (40.0, 0.0, 16)):
        J = _rot(0.4) @ torch.diag(torch.tensor([64.0, 64.0 / r], dtype=f64))
        dx, dy = _const_J(J, 1, 1, 1, H, W)
        fp = footprint(dx.view(-1, 2), dy.view(-1, 2), H, W)
        n = auto_tap_count(ellipse(fp), fp, 0.0, 16, tol)
        # ceil(ceil(r) / (1 + tol)), capped at 16 first; a ratio past the
        # cap keeps all 16 taps (they are already wider than the minor axis).
        assert n.item() == want, (r, tol, n.item())
    # Minor axis under half a texel: the spacing floor is half a texel, ceil(major / 0.5).
    J = torch.diag(torch.tensor([3.0, 0.125], dtype=f64))
    dx, dy = _const_J(J, 1, 1, 1, H, W)
    fp = footprint(dx.view(-1, 2), dy.view(-1, 2), H, W)
    ell = ellipse(fp)
    assert tap_count(ell, fp, 16).item() == 16 and auto_tap_count(ell, fp, 0.0, 16, 0.0).item() == 6
    assert auto_tap_count(ell, fp, 1.0, 16, 0.0).item() == 12  # bias +1: footprint 6 x 0.25 texels
    assert auto_tap_count(ell, fp, -2.0, 16, 0.0).item() == 2  # bias -2: 0.75 texels, two level-0 taps
    assert auto_tap_count(ell, fp, -3.0, 16, 0.0).item() == 1  # bias -3: 0.375 texels, one bilinear read


def test_auto_never_takes_more_taps_than_anisotropic():
    g = _gen(0)
    dx = torch.randn(4000, 2, dtype=f64, generator=g) * torch.rand(4000, 1, dtype=f64, generator=g) * 0.5
    dy = torch.randn(4000, 2, dtype=f64, generator=g) * torch.rand(4000, 1, dtype=f64, generator=g) * 0.5
    fp = footprint(dx, dy, 64, 32)
    ell = ellipse(fp)
    for ma in (1, 4, 16):
        for tol in (0.0, 0.25, 2.0):
            n, a = auto_tap_count(ell, fp, 0.0, ma, tol), tap_count(ell, fp, ma)
            assert (n >= 1).all() and (n <= a).all()


# ------------------------------------------------------------ values

def test_auto_equals_bilinear_on_a_magnified_view():
    g = _gen(1)
    tex = torch.rand(2, 3, 32, 24, dtype=f64, generator=g)
    uv = torch.rand(2, 6, 7, 2, dtype=f64, generator=g) * 3 - 1
    # Anisotropic but magnified under half a texel: axes 0.45 and 0.1 texels.
    dx, dy = _const_J(_rot(0.7) @ torch.diag(torch.tensor([0.45, 0.1], dtype=f64)), 2, 6, 7, 32, 24)
    for wrap in ("repeat", ("mirror", "border")):
        a = difftex.sample(tex, uv, filter="auto", wrap=wrap, uv_dx=dx, uv_dy=dy, border_value=0.3)
        b = difftex.sample(tex, uv, filter="bilinear", wrap=wrap, border_value=0.3)
        torch.testing.assert_close(a, b, atol=1e-14, rtol=0)


def test_auto_equals_trilinear_on_an_isotropic_minified_view():
    g = _gen(2)
    tex = torch.rand(1, 3, 64, 48, dtype=f64, generator=g)
    uv = torch.rand(2, 8, 8, 2, dtype=f64, generator=g)
    for L, theta in ((3.3, 0.4), (7.9, 2.0), (100.0, -1.0)):
        # A conformal footprint (both vectors L texels) and one with axis ratio 1.1 < 1 + tolerance
        # whose trilinear length L = max(|J e_x|, |J e_y|) equals the major axis.
        for J in (L * _rot(theta), _rot(theta) @ torch.diag(torch.tensor([L, L / 1.1], dtype=f64))):
            dx, dy = _const_J(J, 2, 8, 8, 64, 48)
            a = difftex.sample(tex, uv, filter="auto", uv_dx=dx, uv_dy=dy, tolerance=1.0)
            t = difftex.sample(tex, uv, filter="trilinear", uv_dx=dx, uv_dy=dy)
            torch.testing.assert_close(a, t, atol=1e-12, rtol=0)
    dx, dy = _const_J(5.0 * _rot(0.3), 2, 8, 8, 64, 48)  # default tolerance, exactly round
    torch.testing.assert_close(difftex.sample(tex, uv, filter="auto", uv_dx=dx, uv_dy=dy),
                               difftex.sample(tex, uv, filter="trilinear", uv_dx=dx, uv_dy=dy), atol=1e-12, rtol=0)


def test_auto_with_zero_tolerance_is_anisotropic_where_the_minor_axis_is_a_texel_or_more():
    g = _gen(3)
    tex = torch.rand(1, 2, 64, 64, dtype=f64, generator=g)
    uv = torch.rand(1, 5, 5, 2, dtype=f64, generator=g)
    for axes in ((12.0, 3.5), (40.0, 1.5), (2.2, 2.0)):
        dx, dy = _const_J(_rot(0.6) @ torch.diag(torch.tensor(axes, dtype=f64)) @ _rot(1.1), 1, 5, 5, 64, 64)
        for ma in (4, 16):
            a = difftex.sample(tex, uv, filter="auto", uv_dx=dx, uv_dy=dy, tolerance=0.0, max_aniso=ma)
            b = difftex.sample(tex, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy, max_aniso=ma)
            torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


@pytest.fixture(scope="module")
def plane():
    """The grazing-plane scene at a reduced size: 96x96, 256^2 texture, 16x16 reference."""
    tex = checker_noise_texture(256, checks=8)
    uv, dx, dy = grazing_plane(96, 20.0, 1.0)
    ref = supersampled(tex, grazing_plane(96, 20.0, 1.0, ss=16)[0], 16, "repeat")
    return tex, uv, dx, dy, ref


def test_auto_is_within_half_a_db_of_anisotropic_16_with_fewer_taps(plane, monkeypatch):
    tex, uv, dx, dy, ref = plane
    reads = {}
    real = trilinear_mod.trilinear_points

    def counting(levels, pts, D, *args, **kw):
        count = kw.get("count")
        reads[name] = pts.shape[0] if count is None else int(count.sum())
        return real(levels, pts, D, *args, **kw)

    monkeypatch.setattr(sys.modules["difftex.texture.sample"], "trilinear_points", counting)
    scores = {}
    for name, kw in (("anisotropic", {}), ("auto", {}), ("trilinear", {})):
        out = difftex.sample(tex, uv, filter=name, uv_dx=dx, uv_dy=dy, max_aniso=16, **kw)
        scores[name] = psnr(out, ref)
    # Measured: aniso 16 37.81 dB, auto 37.82 dB, trilinear 25.43 dB; taps 46.9k vs 46.3k (the
    # default tolerance trims only counts over 10; the 17-scene check is experiments/studies/speed_vs_accuracy.py).
    assert scores["auto"] > scores["anisotropic"] - 0.5, scores
    assert scores["auto"] > scores["trilinear"] + 8, scores
    assert reads["auto"] < reads["anisotropic"], reads


@pytest.mark.parametrize("scene", ["plane-spot-5", "sphere-0.5x"])
def test_auto_within_half_a_db_where_it_used_not_to_be(scene):
    # The two scenes of the speed-vs-accuracy suite (difftex.testing.suite, at 64^2) where the
    # first auto fell short: a 5-degree plane (tolerance 0.25: -1.0 dB) and a
    # sphere magnified 2x (a one-texel spacing floor: -6.6 dB, one bilinear
    # read against anisotropic's two level-0 taps).
    sc = plane_scene(5, "spot", 64, ss_rates=()) if scene.startswith("plane") else sphere_scene(0.5, 64, ss_rates=())
    kw = dict(wrap=sc.wrap, uv_dx=sc.uv_dx, uv_dy=sc.uv_dy)
    score = {f: psnr(difftex.sample(sc.texture, sc.uv, filter=f, **kw), sc.reference, mask=sc.mask)
             for f in ("anisotropic", "auto")}
    # Measured: plane 41.78 / 41.55 dB, sphere 55.20 / 55.20 dB.
    assert score["auto"] > score["anisotropic"] - 0.5, score
    H, W = sc.texture.shape[-2:]
    fp = footprint(sc.uv_dx.reshape(-1, 2), sc.uv_dy.reshape(-1, 2), H, W)
    ell = ellipse(fp)
    assert (auto_tap_count(ell, fp, 0.0, 16, 0.1) <= tap_count(ell, fp, 16)).all()


def test_auto_tolerance_trades_taps_for_accuracy(plane):
    tex, uv, dx, dy, ref = plane
    fp = footprint(dx.view(-1, 2), dy.view(-1, 2), 256, 256)
    ell = ellipse(fp)
    taps = [auto_tap_count(ell, fp, 0.0, 16, t).sum().item() for t in (0.0, 0.5, 2.0)]
    scores = [psnr(difftex.sample(tex, uv, filter="auto", uv_dx=dx, uv_dy=dy, tolerance=t), ref)
              for t in (0.0, 0.5, 2.0)]
    assert taps[0] > taps[1] > taps[2]
    assert scores[0] > scores[1] > scores[2]


# ------------------------------------------------------------ gradients, degenerate input

def _grad_inputs(seed, J, Ho=2, Wo=3, H=11, W=9):
    g = _gen(seed)
    tex = torch.rand(1, 2, H, W, dtype=f64, generator=g, requires_grad=True)
    uv = (torch.rand(1, Ho, Wo, 2, dtype=f64, generator=g) * 0.8 + 0.1).requires_grad_(True)
    size = torch.tensor([W, H], dtype=f64)
    Jp = torch.tensor(J, dtype=f64) * (1 + 0.05 * torch.rand(1, Ho, Wo, 2, 2, dtype=f64, generator=g))
    dx = (Jp[..., :, 0] / size).requires_grad_(True)
    dy = (Jp[..., :, 1] / size).requires_grad_(True)
    bias = (0.1 * torch.rand(1, Ho, Wo, dtype=f64, generator=g)).requires_grad_(True)
    return tex, uv, dx, dy, bias


@pytest.mark.parametrize("J", [
    [[4.6, -0.4], [0.9, 1.3]],    # ratio ~3.8: 4 taps at tolerance 0.1
    [[2.3, -0.3], [0.4, 2.1]],    # nearly round: one trilinear tap
    [[0.6, 0.1], [-0.2, 0.5]],    # magnified, 0.6 texels: two level-0 taps
    [[0.3, 0.05], [-0.1, 0.25]],  # magnified under half a texel: bilinear on level 0
])
@pytest.mark.parametrize("wrap", ["repeat", "border"])
def test_gradcheck(J, wrap):
    tex, uv, dx, dy, bias = _grad_inputs(4, J)
    # Away from the kinks: the tap count is constant under gradcheck's steps.
    fp = footprint(dx.detach().view(-1, 2), dy.detach().view(-1, 2), 11, 9)
    ell = ellipse(fp)
    b = bias.detach().view(-1)
    full = torch.exp2(ell.log2_major + b - (ell.log2_minor + b).clamp(min=-1))
    assert ((full - full.floor()) > 0.05).all() and ((full.ceil() - full) > 0.05).all()
    fn = lambda t, u, a, c, d: difftex.sample(t, u, filter="auto", wrap=wrap, uv_dx=a, uv_dy=c, lod_bias=d,
                                              border_value=0.25)
    assert torch.autograd.gradcheck(fn, (tex, uv, dx, dy, bias), atol=1e-7)


def test_bad_tolerance():
    tex = torch.rand(1, 1, 8, 8)
    uv = torch.rand(1, 4, 5, 2)
    d = torch.zeros(1, 4, 5, 2)
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="tolerance.*>= 0"):
            difftex.sample(tex, uv, filter="auto", uv_dx=d, uv_dy=d, tolerance=bad)
    for bad in ("0.1", True, None):
        with pytest.raises(TypeError, match="tolerance"):
            difftex.sample(tex, uv, filter="auto", uv_dx=d, uv_dy=d, tolerance=bad)
    with pytest.raises(ValueError, match="uv_dx: required"):
        difftex.sample(tex, uv, filter="auto")


# ------------------------------------------------------------ levels_needed

MIP = MIP_FILTERS


@pytest.mark.parametrize("filter", MIP)
@pytest.mark.parametrize("hw,scale", [((64, 64), 1.0), ((45, 70), 1.0), ((64, 64), 0.05), ((45, 70), 0.3)])
def test_levels_needed_gives_the_same_output_as_the_full_pyramid(filter, hw, scale):
    H, W = hw
    g = _gen(8)
    tex = torch.rand(1, 2, H, W, dtype=f64, generator=g, requires_grad=True)
    uv = torch.rand(2, 6, 7, 2, dtype=f64, generator=g) * 2
    # Footprints from ~0.5 to ~20 texels (times scale), various shapes.
    dx = torch.randn(2, 6, 7, 2, dtype=f64, generator=g) * torch.rand(2, 6, 7, 1, dtype=f64, generator=g) * 0.3
    dy = torch.randn(2, 6, 7, 2, dtype=f64, generator=g) * torch.rand(2, 6, 7, 1, dtype=f64, generator=g) * 0.3
    dx, dy = dx * scale, dy * scale
    bias = torch.randn(2, 6, 7, dtype=f64, generator=g) * 0.5
    full = mipmap(tex)
    n = levels_needed(dx, dy, tex, lod_bias=bias, max_aniso=8, filter=filter)
    assert isinstance(n, int) and 1 <= n <= len(full)
    if scale < 0.1:
        assert n < len(full)
    kw = dict(filter=filter, uv_dx=dx, uv_dy=dy, lod_bias=bias, max_aniso=8, wrap="repeat")
    a = difftex.sample(full, uv, **kw)
    b = difftex.sample(mipmap(tex, max_levels=n), uv, **kw)
    torch.testing.assert_close(a, b, atol=0, rtol=0)
    ga = torch.autograd.grad(a.sum(), tex)[0]
    gb = torch.autograd.grad(b.sum(), tex)[0]
    torch.testing.assert_close(ga, gb, atol=1e-12, rtol=0)
    if n > 1 and filter != "ewa":  # one level fewer changes something: n is not wasteful (EWA keeps a spare)
        c = difftex.sample(mipmap(tex, max_levels=n - 1), uv, **kw)
        assert not torch.equal(a, c)


def test_levels_needed_values():
    H, W = 256, 256  # full chain: 9 levels
    for L, want in ((0.5, 1), (1.0, 1), (1.5, 2), (4.0, 3), (5.0, 4), (1e6, 9)):
        dx, dy = _const_J(L * _rot(0.3), 1, 2, 2, H, W)
        assert levels_needed(dx, dy, (H, W)) == want, L
        assert levels_needed(dx, dy, (H, W), filter="nearest-mip") == min(int(math.floor(math.log2(max(L, 1)) + 0.5)) + 1, 9)
        assert levels_needed(dx, dy, (H, W), filter="bilinear") == 1
    dx, dy = _const_J(4.0 * _rot(0.3), 1, 2, 2, H, W)
    assert levels_needed(dx, dy, (H, W), lod_bias=1.5) == 5  # ceil(2 + 1.5) + 1
    assert levels_needed(dx, dy, (H, W), filter="ewa") == 4  # one more than the blend reads
    assert levels_needed(dx, dy, mipmap(torch.zeros(1, 1, H, W), max_levels=2)) == 2
    # Anisotropic: 16 x 2 texels, 8 taps at level log2(16 / 8) = 1 -> 2 levels; trilinear reads log2 16 -> 5.
    dx, dy = _const_J(torch.diag(torch.tensor([16.0, 2.0], dtype=f64)), 1, 2, 2, H, W)
    assert levels_needed(dx, dy, (H, W), filter="anisotropic") == 2
    assert levels_needed(dx, dy, (H, W), filter="trilinear") == 5
    # Degenerate derivatives: zero / NaN read level 0, infinite the coarsest.
    z = torch.zeros(1, 2, 2, 2)
    assert levels_needed(z, z, (H, W)) == 1 and levels_needed(z * float("nan"), z, (H, W)) == 1
    assert levels_needed(z + float("inf"), z, (H, W), filter="auto") == 9
    assert levels_needed(torch.zeros(1, 0, 3, 2), torch.zeros(1, 0, 3, 2), (H, W)) == 1


def test_levels_needed_bad_input():
    d = torch.zeros(1, 4, 5, 2)
    with pytest.raises(ValueError, match="filter"):
        levels_needed(d, d, (8, 8), filter="trilinearr")
    with pytest.raises(ValueError, match="texture_size"):
        levels_needed(d, d, (8,))
    with pytest.raises(ValueError, match="uv_dy"):
        levels_needed(d, torch.zeros(1, 4, 4, 2), (8, 8))
    with pytest.raises(ValueError, match="batch sizes"):
        levels_needed(torch.zeros(2, 4, 5, 2), torch.zeros(3, 4, 5, 2), (8, 8))
    with pytest.raises(TypeError, match="uv_dx"):
        levels_needed(d.long(), d, (8, 8))
    for bad in (0.5, 2000):
        with pytest.raises(ValueError, match=r"max_aniso: expected a finite number in \[1, 1024\]"):
            levels_needed(d, d, (8, 8), max_aniso=bad)
    with pytest.raises(ValueError, match="tolerance"):
        levels_needed(d, d, (8, 8), filter="auto", tolerance=-1)
    with pytest.raises(ValueError, match="lod_bias"):
        levels_needed(d, d, (8, 8), lod_bias=torch.zeros(1, 5, 4))
    with pytest.raises(TypeError, match="lod_bias"):
        levels_needed(d, d, (8, 8), lod_bias="1")

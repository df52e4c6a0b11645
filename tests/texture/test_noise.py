"""Perlin noise, fBm, turbulence and the wood / marble solid textures of difftex.texture.noise."""
import math

import pytest
import torch

from difftex.texture import noise
from difftex.texture.noise import NOISE_BOUND, fbm, marble, perlin, turbulence, wood


def _points(n, dtype=torch.float64, scale=256.0, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g, dtype=torch.float64).mul(scale).to(dtype)


def test_deterministic_from_the_seed(device, dtype):
    p = _points(1000, dtype).to(device)
    a, b = perlin(p, seed=3), perlin(p.clone(), seed=3)
    assert torch.equal(a, b)
    assert a.dtype == dtype and a.device.type == torch.device(device).type
    # Another seed is another noise, and the tables do not depend on the device or dtype.
    assert (a - perlin(p, seed=4)).abs().mean() > 0.05
    ref = perlin(p.double().cpu(), seed=3)
    assert torch.allclose(a.double().cpu(), ref, atol=1e-5 if dtype == torch.float32 else 1e-12)


def test_zero_on_the_lattice_and_periodic():
    k = torch.randint(-300, 300, (200, 3), generator=torch.Generator().manual_seed(0)).double()
    assert perlin(k).abs().max() < 1e-12
    p = _points(500, scale=10.0)
    assert torch.allclose(perlin(p + 256 * torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)), perlin(p), atol=1e-9)


def test_zero_mean_bounded_and_not_flat():
    p = _points(100_000)
    for seed in (0, 1):
        v = perlin(p, seed=seed)
        # The std is ~0.19; over one period the mean of a fixed table stays well under 0.005.
        assert abs(float(v.mean())) < 0.005
        assert 0.15 < float(v.std()) < 0.25
        assert float(v.abs().max()) <= NOISE_BOUND
    a = torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64)
    f = fbm(p[:20000], a)
    assert abs(float(f.mean())) < 0.01
    assert float(f.abs().max()) <= NOISE_BOUND * 1.75
    t = turbulence(p[:20000], a)
    assert float(t.min()) >= 0 and float(t.max()) <= NOISE_BOUND * 1.75


def test_fbm_is_the_sum_of_its_octaves():
    p = _points(50, scale=5.0)
    a = torch.tensor([0.7, -0.3], dtype=torch.float64)
    one = fbm(p, a[:1])
    two = fbm(p, a)
    second = fbm(p, torch.tensor([0.0, 1.0], dtype=torch.float64))
    assert torch.allclose(two, one + a[1] * second, atol=1e-12)
    assert torch.allclose(fbm(p, octaves=3, gain=0.5), fbm(p, torch.tensor([1.0, 0.5, 0.25]).double()), atol=1e-12)
    assert torch.allclose(one, 0.7 * perlin(p + noise._tables_cpu(0)[2][0]), atol=1e-12)


def test_gradient_matches_finite_differences():
    p = _points(200, scale=20.0).requires_grad_()
    v = fbm(p, octaves=3)
    (g,) = torch.autograd.grad(v.sum(), p)
    h = 1e-6
    fd = torch.stack([(fbm(p.detach() + h * e, octaves=3) - fbm(p.detach() - h * e, octaves=3)) / (2 * h)
                      for e in torch.eye(3, dtype=torch.float64)], -1)
    assert torch.allclose(g, fd, atol=1e-6)
    assert g.abs().max() > 0.5  # the check sees real slopes


def test_gradcheck_points_and_amplitudes():
    p = _points(6, scale=4.0).requires_grad_()
    a = torch.tensor([1.0, 0.6, 0.3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: perlin(x, seed=2), (p,))
    assert torch.autograd.gradgradcheck(lambda x: perlin(x, seed=2), (p[:2],))
    assert torch.autograd.gradcheck(lambda x, w: fbm(x, w), (p, a))
    assert torch.autograd.gradcheck(lambda x, w: turbulence(x, w), (p, a))
    assert torch.autograd.gradcheck(lambda x: wood(x) + marble(x), (p[:2] / 4,))


def test_float32_close_to_float64():
    p = _points(2000, scale=30.0)
    assert torch.allclose(fbm(p.float()).double(), fbm(p), atol=1e-4)


def test_wood_and_marble_colours():
    p = _points(5000, scale=2.0) - 1
    w, m = wood(p), marble(p)
    assert w.shape == (5000, 3) and m.shape == (5000, 3)
    light = torch.tensor([0.80, 0.58, 0.34], dtype=torch.float64)
    dark = torch.tensor([0.45, 0.26, 0.12], dtype=torch.float64)
    s = (w - light) / (dark - light)  # every pixel is a blend of the two colours
    assert torch.allclose(s, s[:, :1].expand(-1, 3), atol=1e-9)
    assert float(s.min()) >= -1e-9 and float(s.max()) <= 1 + 1e-9 and float(s.std()) > 0.1
    # Marble: mostly light stone with darker veins.
    lum = m.mean(-1)
    assert float(lum.median()) > 0.7 and float(lum.min()) < 0.5
    # Wood rings are concentric about the z axis: without noise the colour depends on the radius only.
    q = torch.tensor([[0.3, 0.0, 0.0], [0.0, 0.3, 0.5], [-0.3 / math.sqrt(2), 0.3 / math.sqrt(2), -1.0]]).double()
    c = wood(q, grain=0.0)
    assert torch.allclose(c, c[:1].expand(3, -1), atol=1e-12)


def test_bad_input():
    with pytest.raises(ValueError, match=r"points: expected last dimension 3"):
        perlin(torch.zeros(4, 2))
    with pytest.raises(TypeError, match=r"points: expected a floating-point tensor"):
        perlin(torch.zeros(4, 3, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"seed: expected an int, got float"):
        perlin(torch.zeros(4, 3), seed=1.5)
    with pytest.raises(ValueError, match=r"octaves: expected an int in \[1, 64\], got 0"):
        fbm(torch.zeros(4, 3), octaves=0)
    with pytest.raises(ValueError, match=r"amplitudes: expected 1-D"):
        fbm(torch.zeros(4, 3), torch.ones(2, 2))
    with pytest.raises(ValueError, match=r"lacunarity: expected a finite number > 0"):
        fbm(torch.zeros(4, 3), lacunarity=-1.0)
    with pytest.raises(ValueError, match=r"light: expected 3 RGB values"):
        wood(torch.zeros(4, 3), light=(1.0, 0.0))


def test_non_finite_points_stay_local():
    p = torch.tensor([[0.5, 0.5, 0.5], [float("nan"), 0.0, 0.0], [float("inf"), 0.0, 0.0]])
    v = perlin(p)
    assert torch.isfinite(v[0]) and not torch.isfinite(v[1:]).any()


def test_perlin_just_below_a_period_reads_the_period_start():
    # p - 256 floor(p / 256) rounds to 256 itself just below a multiple of 256 (float32: p in about
    # (-7.6e-6, 0)); the cell index was then clamped to 255, the noise of the plane x = 255.
    xs = [-1e-4, -1e-6, -1e-7, 0.0, 1e-7, 256 - 1e-5, 512 - 2e-5]
    pts = torch.tensor([[x, 0.3, 0.3] for x in xs], dtype=torch.float64)
    ref = perlin(pts)
    got = perlin(pts.float())
    torch.testing.assert_close(got.double(), ref, atol=2e-5, rtol=0)
    assert (ref - ref[3]).abs().max() < 2e-5  # C2 and periodic: all close to the value at 0


def test_wood_is_its_documented_formula():
    p = torch.randn(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    f, g, ns = 4.0, 0.3, 1.5
    r = p[:, :2].norm(dim=-1)
    s = (0.5 + 0.5 * torch.cos(2 * math.pi * f * (r + g * fbm(ns * p, octaves=3)))) ** 3
    light, dark = torch.tensor([0.80, 0.58, 0.34], dtype=p.dtype), torch.tensor([0.45, 0.26, 0.12], dtype=p.dtype)
    got = wood(p, frequency=f, grain=g, noise_scale=ns)
    torch.testing.assert_close(got, light + (dark - light) * s[:, None], atol=1e-12, rtol=0)

"""Stochastic texture filtering (``sample(..., stochastic=k)``, difftex/texture/filters/stochastic.py).

The central check is statistical: over G independent groups of k draws,
each pixel's mean must sit within ``Z_BOUND`` standard errors of the
deterministic filter's value, for the values and for the gradients (the
texture's, uv's, uv_dx's). ``z_scores`` is that check, and a sampler with a
wrong pdf must fail it (``test_a_biased_sampler_fails_the_check``), so the
bound is not so loose that anything passes. Everything is seeded: the test
is deterministic, the bound is for a fresh seed.
"""
from __future__ import annotations

import math

import pytest
import torch

import difftex
from difftex import _native as native
from difftex import mipmap, sample
from difftex.testing.scenes import checker_noise_texture, grazing_plane
from difftex.texture.filters import stochastic as st
from difftex.texture.filters.ewa import covariance
from difftex.texture.lod import ellipse, footprint

# Largest |z| allowed over every pixel, channel and texel of a check. The
# check compares a few thousand numbers; for normal means and G = 40 groups
# (t with 39 degrees of freedom) P(|z| > 6) is about 3e-7 each.
Z_BOUND = 6.0
GROUPS = 40
FLOOR = 0.25


def z_scores(samples: torch.Tensor, exact: torch.Tensor, floor: float = FLOOR) -> float:
    """Largest |mean - exact| / standard error over the entries; samples [G, ...] independent, exact [...].

    Each entry's standard error is floored at ``floor`` times the root mean
    square of all of them: a tap of small probability (the defensive
    minimum, 1/256 of a bicubic draw) is missed by all G groups at many
    entries, which then show a small spread yet lack that tap's (small)
    share of the mean. The floor sets the check's resolution; the biased
    samplers below miss by far more.
    """
    G = samples.shape[0]
    se = samples.std(0) / math.sqrt(G)
    se = se.clamp(min=max(floor * float(se.square().mean().sqrt()), 1e-300))
    return float(((samples.mean(0) - exact).abs() / se).max())


def swirl(res: int = 12, dtype=torch.float64):
    """A minified, rotating, non-uniform uv field with its exact pixel derivatives: (uv, uv_dx, uv_dy)."""
    r = torch.arange(res, dtype=torch.float64).view(res, 1).expand(res, res)
    c = torch.arange(res, dtype=torch.float64).view(1, res).expand(res, res)
    x, y = (c + 0.5) / res, (r + 0.5) / res
    u = 0.3 + 2.5 * x + 0.4 * torch.sin(3 * y)
    v = 0.2 + 1.7 * y * y + 0.8 * x
    du_dc, du_dr = 2.5 / res, 1.2 * torch.cos(3 * y) / res
    dv_dc, dv_dr = 0.8 / res, 3.4 * y / res
    uv = torch.stack((u, v), -1)
    dx = torch.stack((torch.full_like(u, du_dc), torch.full_like(v, dv_dc)), -1)
    dy = torch.stack((du_dr, dv_dr), -1)
    return tuple(t.unsqueeze(0).to(dtype) for t in (uv, dx, dy))


def plane(res: int = 12, dtype=torch.float64):
    return grazing_plane(res, pitch_deg=25.0, fov_deg=40.0, tile=1.5, dtype=dtype)


TEXTURE = checker_noise_texture(32, checks=4, noise=0.5, channels=2, dtype=torch.float64)
SCENES = {"plane": (plane, "repeat"), "swirl": (swirl, ("mirror", "clamp"))}


def run(filter: str, scene: str, k: int, seed: int, *, texture=TEXTURE, grads: bool = True, iid: bool = False):
    """Values and gradients of one call: (value [1, C, H, W], d/dtexture, d/duv, d/duv_dx) of a fixed loss.

    ``iid``: the mean of k independent draws (one draw each of k copies of the scene), not k stratified ones.
    """
    make, wrap = SCENES[scene]
    uv, dx, dy = make(8 if filter == "ewa" else 12)  # EWA reads ~30 texels a draw on the torch path: fewer pixels
    tex = texture.clone().requires_grad_(grads)
    uv = uv.clone().requires_grad_(grads)
    dx = dx.clone().requires_grad_(grads)
    g = torch.Generator().manual_seed(seed)
    copies, k = (k, 1) if iid and k > 1 else (1, k)
    out = sample(tex, uv.expand(copies, -1, -1, -1), filter=filter, wrap=wrap, uv_dx=dx.expand(copies, -1, -1, -1),
                 uv_dy=dy, max_aniso=8, stochastic=k, generator=g).mean(0, keepdim=True)
    if not grads:
        return (out.detach(),)
    # A fixed, sign-changing weighting of the pixels: its gradient is no plain sum.
    w = torch.linspace(-1, 2, out.numel(), dtype=out.dtype).view_as(out)
    gt, gu, gd = torch.autograd.grad((out * w).sum(), (tex, uv, dx), allow_unused=True)
    return out.detach(), gt, gu, torch.zeros_like(dx) if gd is None else gd


def groups(filter: str, scene: str, k: int, seed: int = 0, grads: bool = True, iid: bool = False):
    """GROUPS independent estimates of k draws each, stacked per output: a list of [GROUPS, ...].

    Values alone: one call over a batch of GROUPS copies of the scene (each batch entry draws its own);
    with gradients, one call a group (each needs its own texture gradient), of k independent draws
    where ``iid`` (``run``).
    """
    if not grads:
        make, wrap = SCENES[scene]
        copies, k = (k, 1) if iid and k > 1 else (1, k)
        uv, dx, dy = (t.expand(GROUPS * copies, -1, -1, -1) for t in make(8 if filter == "ewa" else 12))
        out = sample(TEXTURE, uv, filter=filter, wrap=wrap, uv_dx=dx, uv_dy=dy, max_aniso=8, stochastic=k,
                     generator=torch.Generator().manual_seed(seed))
        return [out.view(GROUPS, copies, *out.shape[1:]).mean(1, keepdim=True)]
    parts = [run(filter, scene, k, seed * 1000 + i, iid=iid) for i in range(GROUPS)]
    return [torch.stack(p) for p in zip(*parts)]


CASES = [("trilinear", "plane"), ("trilinear", "swirl"), ("anisotropic", "plane"), ("anisotropic", "swirl"),
         ("ewa", "plane"), ("bicubic", "swirl"), ("bilinear", "swirl")]


@pytest.mark.parametrize("filter,scene", CASES)
def test_the_mean_of_the_draws_is_the_filter(filter, scene):
    """Values and the texture, uv and uv_dx (level) gradients, z-checked on two scenes.

    Means of 4 independent draws: a mean of 4 stratified ones is unbiased as well (each stratum's draw is
    the filter's draw restricted to it, test_stratified_draws), but its spread over 40 groups misleads the
    z-check where one draw's stratum alone decides (trilinear's level: a rare two-valued outcome; at 40
    groups z 6.9 on the plane's uv gradient, at 400 groups 2.5 with the error 2.3x smaller: no bias).
    """
    exact = run(filter, scene, 0, 0)
    names = ("value", "texture grad", "uv grad", "uv_dx grad")
    many = groups(filter, scene, 4, iid=True)
    for name, s, e in zip(names, many, exact):
        if name == "uv_dx grad" and filter in ("bilinear", "bicubic"):
            assert e.abs().max() == 0 and s.abs().max() == 0  # single-level: no footprint
            continue
        z = z_scores(s, e)
        print(f"{filter} {scene} {name}: max |z| {z:.2f}")
        assert z < Z_BOUND, f"{filter} on {scene}: {name} off by {z:.2f} standard errors"
    # And the estimate is not trivially the filter: the draws do differ.
    assert many[0].std(0).max() > 1e-3


def _biased_draw_level(D, u):
    """A wrong level pdf: the upper level drawn with probability frac^2, reported as frac."""
    with torch.no_grad():
        k0 = torch.floor(D.detach())
        f = D.detach() - k0
        upper = u < (f * f).to(u.dtype)
        return st.LevelDraw(k0 + upper.to(D.dtype), torch.where(upper, f, 1 - f))


def test_a_biased_sampler_fails_the_check(monkeypatch):
    exact = run("trilinear", "plane", 0, 0, grads=False)[0]
    good = groups("trilinear", "plane", 4, grads=False)[0]
    monkeypatch.setattr(st, "draw_level", _biased_draw_level)
    # The torch path (the kernel draws inside itself; test_the_kernel_draws_as_the_torch_path holds it to this).
    with difftex.backend("grid_sample"):
        bad = groups("trilinear", "plane", 4, grads=False)[0]
    print("z of the right sampler", z_scores(good, exact), "of the biased one", z_scores(bad, exact))
    assert z_scores(good, exact) < Z_BOUND
    assert z_scores(bad, exact) > Z_BOUND


def test_one_texel_too_many_fails_the_check(monkeypatch):
    """EWA whose texel draw skips to the next texel of the ellipse: a wrong tap, the same pdf."""
    exact = run("ewa", "plane", 0, 0, grads=False)[0]
    real = st.draw_ewa_texel

    def shifted(*args):
        d = real(*args)
        return st.TexelDraw(d.col + 1, d.row, d.pdf, d.total)

    monkeypatch.setattr(st, "draw_ewa_texel", shifted)
    bad = groups("ewa", "plane", 4, grads=False)[0]
    print("z of the shifted EWA", z_scores(bad, exact))
    assert z_scores(bad, exact) > Z_BOUND


@pytest.mark.parametrize("filter", ["trilinear", "anisotropic", "ewa", "bicubic"])
def test_variance_falls_as_one_over_k(filter):
    """Independent draws: 1 / k. Stratified draws (``stochastic=k``): at most that, and below it."""
    scene = "swirl" if filter == "bicubic" else "plane"
    var = lambda k, iid: groups(filter, scene, k, seed=k + 10 * iid, grads=False, iid=iid)[0].var(0).mean().item()  # noqa: E731
    one, iid, strat = var(1, False), var(4, True), var(4, False)
    print(f"{filter}: variance of 1 draw / of the mean of 4: independent {one / iid:.2f}, stratified {one / strat:.2f}")
    # 4 expected; the ratio of two means of 128-288 per-pixel variances of 40 groups is good to about 10 %.
    assert 3.0 < one / iid < 5.3, f"{filter}: variance ratio k=1 / k=4 is {one / iid:.2f}, expected 4"
    # Stratified: at least 1 / k (the same tolerance); far below it where the first uniform decides the draw
    # (trilinear's level: 12.2, anisotropic's probe: 23.6; EWA 5.6 and bicubic 4.6, whose second uniform is not
    # stratified).
    assert one / strat > (8.0 if filter in ("trilinear", "anisotropic") else 3.0), \
        f"{filter}: stratified variance ratio {one / strat:.2f}"


def test_stratified_draws():
    """Draw j of a point's k takes its first uniform in [j / k, (j + 1) / k); k anisotropic draws of points
    with k probes (or a divisor of k) read each probe equally often: the deterministic filter, values and
    gradients."""
    u = st.hashed_uniforms(3, 6, 12, 2, strata=3)  # counters 6..17: draws j = 0, 1, 2, 0, ...
    j = torch.arange(6, 18) % 3
    assert bool(((u[:, 0] >= j / 3) & (u[:, 0] < (j + 1) / 3)).all())
    assert torch.equal(u[:, 1], st.hashed_uniforms(3, 6, 12, 2)[:, 1])  # the other roles as they were
    res = 10
    r, c = torch.meshgrid(torch.arange(res, dtype=torch.float64), torch.arange(res, dtype=torch.float64),
                          indexing="ij")
    uv = torch.stack(((c + 0.5) * 0.11 + 0.05 * r, (r + 0.5) * 0.03), -1).unsqueeze(0)
    dx = torch.tensor([0.11, 0.0], dtype=torch.float64).expand(1, res, res, 2)  # 4 : 1, 4 probes a pixel
    dy = torch.tensor([0.0, 0.11 / 4], dtype=torch.float64).expand(1, res, res, 2)
    for backend in ("native", "grid_sample"):
        got = []
        for k in (0, 4, 8, 2):
            t, p = TEXTURE.clone().requires_grad_(), uv.clone().requires_grad_()
            with difftex.backend(backend):
                out = sample(t, p, filter="anisotropic", uv_dx=dx, uv_dy=dy, max_aniso=8, stochastic=k,
                             generator=torch.Generator().manual_seed(1))
            w = torch.linspace(-1, 2, out.numel(), dtype=out.dtype).view_as(out)
            got.append([out.detach(), *torch.autograd.grad((out * w).sum(), (t, p))])
        for exact in got[1:3]:
            for a, b in zip(exact, got[0]):
                torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
        assert (got[3][0] - got[0][0]).abs().max() > 1e-3  # 2 draws of 4 probes: not the filter


@pytest.mark.parametrize("filter", ["trilinear", "anisotropic", "ewa", "bicubic", "bilinear"])
@pytest.mark.parametrize("backend", ["native", "grid_sample"])
def test_decorrelate_takes_the_value_from_one_seed_and_the_gradient_from_the_next(filter, backend):
    """``decorrelate=True`` draws two seeds: its value is the plain call's (the first seed), its gradients
    (texture, uv, uv_dx) those of a plain call on the second seed, bit for bit (the native kernels' backward
    draws that set itself; the torch path evaluates it)."""
    uv, dx, dy = swirl(8 if filter == "ewa" else 10)

    def call(decorrelate, skip):
        g = torch.Generator().manual_seed(21)
        for _ in range(skip):
            st.draw_seed(g, "cpu")
        t, u, d = TEXTURE.clone().requires_grad_(), uv.clone().requires_grad_(), dx.clone().requires_grad_()
        with difftex.backend(backend):
            out = sample(t, u, filter=filter, wrap="mirror", uv_dx=d, uv_dy=dy, max_aniso=8, stochastic=2,
                         generator=g, decorrelate=decorrelate)
        w = torch.linspace(-1, 2, out.numel(), dtype=out.dtype).view_as(out)
        return [out.detach(), *torch.autograd.grad((out * w).sum(), (t, u, d), allow_unused=True)]

    both, first, second = call(True, 0), call(False, 0), call(False, 1)
    assert torch.equal(both[0], first[0])
    for a, b, c in zip(both[1:], second[1:], first[1:]):
        if b is None:  # bilinear / bicubic: no footprint
            assert a is None
            continue
        assert torch.equal(a, b)
    assert not torch.equal(both[1], first[1])
    with pytest.raises(TypeError, match="decorrelate: expected a bool, got int"):
        sample(TEXTURE, uv, filter=filter, uv_dx=dx, uv_dy=dy, stochastic=1, decorrelate=1)


def test_seeded_draws_repeat_bit_for_bit():
    a = run("anisotropic", "swirl", 3, 7)
    b = run("anisotropic", "swirl", 3, 7)
    c = run("anisotropic", "swirl", 3, 8)
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    assert not torch.equal(a[0], c[0])
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = run("ewa", "plane", 2, 3, grads=False)[0]
        torch.set_num_threads(2)
        two = run("ewa", "plane", 2, 3, grads=False)[0]
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)


@pytest.mark.skipif(native.load() is None, reason="native kernels not built")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("filter,k", [("trilinear", 1), ("trilinear", 3), ("anisotropic", 1), ("anisotropic", 2)])
def test_the_kernel_draws_as_the_torch_path(filter, k, dtype):
    """The native kernel hashes the same uniforms as hashed_uniforms: the same draws, so the same values and
    texture, uv and uv_dx (level) gradients as the torch path, to rounding; batches of textures included."""
    tex = checker_noise_texture(32, checks=4, noise=0.5, channels=3, dtype=dtype).expand(2, -1, -1, -1) * \
        torch.tensor([1.0, 0.5], dtype=dtype).view(2, 1, 1, 1)
    uv, dx, dy = (t.expand(2, -1, -1, -1) for t in swirl(10, dtype))
    got = []
    for choice in ("native", "grid_sample"):
        t, u, d = tex.clone().requires_grad_(), uv.clone().requires_grad_(), dx.clone().requires_grad_()
        with difftex.backend(choice):
            out = sample(t, u, filter=filter, wrap=("mirror", "repeat"), uv_dx=d, uv_dy=dy, max_aniso=8,
                         stochastic=k, generator=torch.Generator().manual_seed(11))
        w = torch.linspace(-1, 2, out.numel(), dtype=dtype).view_as(out)
        got.append([out.detach(), *torch.autograd.grad((out * w).sum(), (t, u, d))])
    # float64: the same draws to rounding. float32: the torch path places an anisotropic probe in float32
    # (addcmul), the kernel in double, as the deterministic taps do: a few texel fractions differ in their last
    # bits, times texel steps of up to 1 (test_native.py's float32 bound).
    tol = dict(rtol=0, atol=3e-3) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    for a, b in zip(*got):
        torch.testing.assert_close(a, b, **tol)
    assert got[0][3].abs().max() > 0  # the level's gradient reaches uv_dx


@pytest.mark.skipif(native.load() is None, reason="native kernels not built")
@pytest.mark.parametrize("wrap", ["repeat", "border", ("mirror", "clamp")])
@pytest.mark.parametrize("channels", [1, 3, 5])
def test_the_kernels_eight_point_draws_are_its_scalar_loop(wrap, channels):
    """float32 draws eight at a time (AVX2, where the CPU has it) give the scalar loop's bits, values and
    gradients, whatever the levels the lanes drew."""
    kernel = native.load()
    tex = checker_noise_texture(64, channels=channels)
    uv, dx, dy = grazing_plane(37, pitch_deg=25.0)
    uv = uv * 1.3 - 0.1
    got = []
    for simd in (True, False):
        before = kernel.set_simd(simd)
        try:
            for filter in ("trilinear", "anisotropic"):
                for d_grad in (False, True):  # with it: the level's and the axis's gradients too
                    t, u, d = tex.clone().requires_grad_(), uv.clone().requires_grad_(), dx.clone().requires_grad_(d_grad)
                    out = sample(t, u, filter=filter, wrap=wrap, uv_dx=d, uv_dy=dy, stochastic=1,
                                 generator=torch.Generator().manual_seed(4))
                    w = torch.linspace(-1, 2, out.numel()).view_as(out)
                    got.append([out.detach(), *torch.autograd.grad((out * w).sum(), (t, u, d) if d_grad else (t, u))])
        finally:
            kernel.set_simd(before)
    for a, b in zip(got[:4], got[4:]):
        for x, y in zip(a, b):
            assert torch.equal(x, y)


def test_hashed_uniforms_are_splitmix64():
    """The torch int64 arithmetic gives SplitMix64's outputs (Python's unbounded ints as the reference)."""
    def splitmix(seed, i):
        mask = (1 << 64) - 1
        z = (seed + (i + 1) * 0x9E3779B97F4A7C15) & mask
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
        return ((z ^ (z >> 31)) >> 11) / 2.0 ** 53
    for seed in (0, 12345, -(1 << 63), (1 << 63) - 1, -7):
        u = st.hashed_uniforms(seed, 5, 4, 3)
        want = torch.tensor([[splitmix(seed % (1 << 64), (5 + i) * 3 + r) for r in range(3)] for i in range(4)],
                            dtype=torch.float64)
        assert torch.equal(u, want)
        assert bool(((u >= 0) & (u < 1)).all())


@pytest.mark.skipif(native.load() is None, reason="native kernels not built")
def test_kernel_draws_do_not_depend_on_the_thread_count():
    uv, dx, dy = (t.float() for t in plane(40))
    tex = TEXTURE.float()
    threads = torch.get_num_threads()
    outs = []
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            t = tex.clone().requires_grad_()
            out = sample(t, uv, filter="anisotropic", uv_dx=dx, uv_dy=dy, max_aniso=8, stochastic=2,
                         generator=torch.Generator().manual_seed(2))
            outs.append((out.detach(), torch.autograd.grad(out.sum(), t)[0]))
    finally:
        torch.set_num_threads(threads)
    for o in outs[1:]:
        assert torch.equal(o[0], outs[0][0]) and torch.equal(o[1], outs[0][1])


def test_the_default_generator_is_used_and_seeded():
    uv, dx, dy = swirl()
    torch.manual_seed(5)
    a = sample(TEXTURE, uv, filter="trilinear", uv_dx=dx, uv_dy=dy, stochastic=True)
    torch.manual_seed(5)
    b = sample(TEXTURE, uv, filter="trilinear", uv_dx=dx, uv_dy=dy, stochastic=1)
    assert torch.equal(a, b)


def test_a_magnified_trilinear_draw_is_the_filter():
    """Level 0 only (D clamped at 0): one level, probability 1; the draw is its bilinear tap, exactly."""
    uv, dx, dy = swirl()
    d = torch.full_like(uv, 0.1 / 32)
    det = sample(TEXTURE, uv, filter="trilinear", uv_dx=d, uv_dy=d)
    sto = sample(TEXTURE, uv, filter="trilinear", uv_dx=d, uv_dy=d, stochastic=1, generator=torch.Generator())
    assert torch.equal(sto, det)


# ---------------------------------------------------------------- gradients given the draws


def test_trilinear_estimate_gradcheck():
    tex = TEXTURE[:, :1, :16, :16].clone().requires_grad_()
    g = torch.Generator().manual_seed(1)
    M = 6
    uv = (torch.rand(M, 2, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    D = (torch.rand(M, generator=g, dtype=torch.float64) * 3.4 + 0.05).requires_grad_()
    draw = st.draw_level(D, torch.linspace(0.01, 0.99, M, dtype=torch.float64))
    assert 0 < int((draw.level > D).sum()) < M  # both kinds of draw
    fn = lambda uv, D, tex: st.trilinear_estimate(mipmap(tex).levels, uv, D, draw, "repeat", "clamp",  # noqa
                                                 0.0)
    assert torch.autograd.gradcheck(fn, (uv, D, tex))


def test_ewa_texel_estimate_gradcheck():
    lev = TEXTURE[:, :1, :16, :16].clone().requires_grad_()
    g = torch.Generator().manual_seed(2)
    M = 3
    uv = (torch.rand(M, 2, generator=g, dtype=torch.float64) * 0.8 + 0.1)
    dx = torch.randn(M, 2, generator=g, dtype=torch.float64) * 0.08
    dy = torch.randn(M, 2, generator=g, dtype=torch.float64) * 0.05
    fp = footprint(dx, dy, 16, 16)
    sigma, minor, _ = covariance(fp, ellipse(fp), 8.0)
    scale = torch.exp2(fp.log2_scale)
    args = [uv.requires_grad_(), sigma.requires_grad_(), minor.requires_grad_(), scale.requires_grad_()]
    draw = st.draw_ewa_texel(16, 16, *args, 16, 16, False, torch.rand(M, generator=g, dtype=torch.float64))
    fn = lambda lev, uv, sigma, minor, scale: st.ewa_texel_estimate(  # noqa: E731
        lev, uv, sigma, minor, scale, 16, 16, False, draw, "repeat", "mirror", 0.0)
    assert torch.autograd.gradcheck(fn, (lev, *args))


@pytest.mark.parametrize("kind", ["linear", "cubic"])
def test_separable_estimate_gradcheck(kind):
    tex = TEXTURE[:, :, :8, :8].clone().requires_grad_()
    g = torch.Generator().manual_seed(3)
    uv = (torch.rand(1, 7, 2, generator=g, dtype=torch.float64) * 1.6 - 0.3).requires_grad_()
    draw = st.draw_separable(tex, uv, kind, "repeat", "border", torch.rand(1, 7, 2, generator=g,
                                                                            dtype=torch.float64))
    fn = lambda tex, uv: st.separable_estimate(tex, uv, kind, "repeat", "border", 0.25, draw)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (tex, uv))


# ---------------------------------------------------------------- exact expectations: every draw enumerated


def _points(M: int = 5, seed: int = 4):
    """M points in (0.1, 0.9)^2 with footprints of 0.3 .. 6 texels of a 32^2 texture, float64, needing grads."""
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(M, 2, generator=g, dtype=torch.float64) * 0.8 + 0.1
    dx = torch.randn(M, 2, generator=g, dtype=torch.float64) * torch.logspace(-1.5, -0.7, M, dtype=torch.float64)[:, None]
    dy = torch.randn(M, 2, generator=g, dtype=torch.float64) * 0.03
    return uv.requires_grad_(), dx.requires_grad_(), dy


def _value_and_grads(out, inputs):
    w = torch.linspace(-1, 2, out.numel(), dtype=out.dtype).view_as(out)
    return [out.detach(), *torch.autograd.grad((out * w).sum(), inputs, retain_graph=True)]


def _level_choices(D):
    """Both level draws of every point, forced: [(LevelDraw, probability)], probability 0 where impossible."""
    k0 = torch.floor(D.detach())
    p = st.upper_probability(D)
    return [(st.LevelDraw(k0, 1 - p), 1 - p), (st.LevelDraw(k0 + 1, torch.where(p > 0, p, 1.0)), p)]


def test_trilinear_expectation_is_exact():
    """Sum over both level draws of p * estimate = the filter: value and texture, uv, D (footprint) gradients."""
    from difftex.texture.filters.trilinear import trilinear_points
    from difftex.texture.lod import level, log2_length
    tex = TEXTURE.clone().requires_grad_()
    uv, dx, dy = _points()
    D = level(log2_length(dx, dy, 32, 32), 0.0, 6)
    assert ((D > 0.5) & (D % 1 > 0.05)).sum() >= 3  # a real blend at most points
    levels = mipmap(tex).levels
    exact = _value_and_grads(trilinear_points(levels, uv, D, "repeat", "mirror", 0.0), (tex, uv, dx))
    est = sum(p * st.trilinear_estimate(levels, uv, D, d, "repeat", "mirror", 0.0) for d, p in _level_choices(D))
    for a, b in zip(_value_and_grads(est, (tex, uv, dx)), exact):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_ewa_expectation_is_exact():
    """Sum over both levels and every texel of the ellipse of p * estimate = EWA: value and every gradient."""
    from difftex.texture.filters.ewa import _pairs, ewa_points, gaussian, level_ellipse
    from difftex.texture.lod import level
    tex = TEXTURE.clone().requires_grad_()
    uv, dx, dy = _points()
    fp = footprint(dx, dy, 32, 32)
    ell = ellipse(fp)
    levels = mipmap(tex).levels
    n = len(levels)
    exact = _value_and_grads(ewa_points(levels, uv, fp, ell, 0.0, 8.0, "repeat", "repeat", 0.0), (tex, uv, dx))
    sigma, minor, log2_minor = covariance(fp, ell, 8.0)
    D = level(log2_minor, 0.0, n)
    scale = torch.exp2(fp.log2_scale)
    est = 0
    for ldraw, p_level in _level_choices(D):
        per_point = []
        for m in range(uv.shape[0]):  # one point at a time: each may sit on another level
            k = min(int(ldraw.level[m]), n - 1)
            sl = slice(m, m + 1)
            args = (uv[sl], sigma[sl], minor[sl], scale[sl], 32, 32, k == n - 1)
            with torch.no_grad():
                sxx, sxy, syy, origin, frac = level_ellipse(*levels[k].shape[-2:], *args)
                _, rx, ry = _pairs(frac[:, 0], frac[:, 1], sxx, sxy, syy)
                w = gaussian(rx - frac[:, 0], ry - frac[:, 1], sxx, sxy, syy, sxx * syy - sxy * sxy)
            T = rx.numel()
            pdf = st.defensive(w / w.sum(), T)
            draw = st.TexelDraw(origin[0, 0] + rx, origin[0, 1] + ry, pdf, w.sum().expand(T))
            many = [x.expand(T, *x.shape[1:]) for x in args[:4]]
            e = st.ewa_texel_estimate(levels[k], *many, *args[4:], draw, "repeat", "repeat", 0.0)
            per_point.append((e * draw.pdf).sum(1))
        est = est + p_level * st.level_weight(D, ldraw) * torch.stack(per_point, 1)
    for a, b in zip(_value_and_grads(est, (tex, uv, dx)), exact):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize("kind", ["linear", "cubic"])
def test_separable_expectation_is_exact(kind):
    """Sum over the 4 / 16 texels of p * estimate = bilinear / bicubic (negative weights included)."""
    from difftex.texture.filters.separable import separable_sample
    tex = TEXTURE.clone().requires_grad_()
    uv = (_points()[0].detach() * 1.4 - 0.2).unsqueeze(0).requires_grad_()
    exact = _value_and_grads(separable_sample(tex, uv, kind, "border", "clamp", 0.5), (tex, uv))
    K = 2 if kind == "linear" else 4
    first = 0 if kind == "linear" else -1
    with torch.no_grad():
        _, t = st._texel_position(tex, uv, "border", "clamp")
        wx = st._axis_weights(t[..., 0], kind, False)[0]
        wy = st._axis_weights(t[..., 1], kind, False)[0]
        px = st.defensive(wx.abs() / wx.abs().sum(-2, keepdim=True), K)
        py = st.defensive(wy.abs() / wy.abs().sum(-2, keepdim=True), K)
    est = 0
    for i in range(K):
        for j in range(K):
            p = px[:, i] * py[:, j]
            ox = torch.full_like(p, i + first, dtype=torch.long)
            draw = st.SeparableDraw(ox, torch.full_like(ox, j + first), p)
            est = est + p.unsqueeze(1) * st.separable_estimate(tex, uv, kind, "border", "clamp", 0.5, draw)
    for a, b in zip(_value_and_grads(est, (tex, uv)), exact):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


# ---------------------------------------------------------------- edges, inputs


def test_nan_texels_stay_in_their_pixels_and_finite_input_gives_finite_output():
    tex = TEXTURE.clone()
    tex[0, :, 5, 7] = float("nan")
    for f, scene in CASES:
        make, wrap = SCENES[scene]
        uv, dx, dy = make()
        det = sample(tex, uv, filter=f, wrap=wrap, uv_dx=dx, uv_dy=dy, max_aniso=8)
        sto = sample(tex, uv, filter=f, wrap=wrap, uv_dx=dx, uv_dy=dy, max_aniso=8, stochastic=4,
                     generator=torch.Generator().manual_seed(0))
        assert torch.isfinite(sto[torch.isfinite(det)]).all(), f
        assert torch.isfinite(sample(TEXTURE, uv, filter=f, wrap=wrap, uv_dx=dx, uv_dy=dy, stochastic=2)).all()


def test_nan_uv_gives_a_nan_pixel_only():
    uv, dx, dy = swirl()
    uv = uv.clone()
    uv[0, 3, 4] = float("nan")
    for f in ("trilinear", "anisotropic", "ewa", "bicubic"):
        out = sample(TEXTURE, uv, filter=f, uv_dx=dx, uv_dy=dy, stochastic=2)
        bad = ~torch.isfinite(out)
        assert bad[:, :, 3, 4].all() and int(bad.sum()) == out.shape[1], f


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batches_and_dtypes(dtype):
    tex = torch.cat([TEXTURE, 1 - TEXTURE]).to(dtype)
    uv, dx, dy = (t.to(dtype).expand(2, -1, -1, -1) for t in swirl())
    for f, k in (("trilinear", 256), ("ewa", 64), ("bicubic", 256)):
        det = sample(tex, uv, filter=f, uv_dx=dx, uv_dy=dy)
        sto = sample(tex, uv, filter=f, uv_dx=dx, uv_dy=dy, stochastic=k,
                     generator=torch.Generator().manual_seed(1))
        assert sto.dtype == dtype and sto.shape == det.shape
        # A draw's standard deviation is under 1.2 on this [0, 1] texture (bicubic's weights over their
        # probabilities reach 1.9; EWA's and trilinear's under 0.4), so k draws are within 0.3 everywhere
        # (seeded; the z checks above are sharper). A texture of another batch entry would be off by ~0.7.
        assert (sto - det).abs().max() < 0.3, f
        # Each texture of the batch is its own: the second is 1 - the first.
        torch.testing.assert_close(det[0] + det[1], torch.ones_like(det[0]), atol=1e-5, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_runs_the_torch_path():
    uv, dx, dy = (t.cuda() for t in swirl())
    tex = TEXTURE.cuda()
    g = torch.Generator(device="cuda").manual_seed(0)
    for f in st.STOCHASTIC_FILTERS:
        det = sample(tex, uv, filter=f, uv_dx=dx, uv_dy=dy)
        sto = sample(tex, uv, filter=f, uv_dx=dx, uv_dy=dy, stochastic=512, generator=g)
        assert (sto - det).abs().max() < 0.3, f


def test_bad_input_names_the_argument():
    uv, dx, dy = swirl()
    kw = dict(filter="trilinear", uv_dx=dx, uv_dy=dy)
    with pytest.raises(ValueError, match="stochastic"):
        sample(TEXTURE, uv, **kw, stochastic=-1)
    with pytest.raises(TypeError, match="stochastic: expected an int >= 0"):
        sample(TEXTURE, uv, **kw, stochastic=1.5)
    with pytest.raises(ValueError, match="stochastic"):
        sample(TEXTURE, uv, filter="sat", uv_dx=dx, uv_dy=dy, stochastic=1)
    with pytest.raises(TypeError, match="generator"):
        sample(TEXTURE, uv, **kw, stochastic=1, generator=3)
    # Off: no draws, the deterministic filter bit for bit, the generator untouched.
    g = torch.Generator().manual_seed(0)
    state = g.get_state()
    assert torch.equal(sample(TEXTURE, uv, **kw, stochastic=0, generator=g), sample(TEXTURE, uv, **kw))
    assert torch.equal(g.get_state(), state)

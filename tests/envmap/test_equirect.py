"""Tests for difftex.envmap.equirect (lat-long environment lookups) and equirect_to_cube."""
import math

import pytest
import torch

import difftex
from difftex.envmap import (
    cube_to_direction, direction_to_equirect_uv, equirect, equirect_to_cube, equirect_uv_to_direction,
)
from difftex.metrics import psnr
from difftex.texture.options import FILTERS, MIP_FILTERS

F64 = torch.float64
WRAP = ("repeat", "clamp")


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _dirs(B, H, W, seed, dtype=F64, scale=1.0):
    """Random directions away from the poles (|y| < 0.95 after normalising), lengths in [0.5, 2], and derivatives."""
    g = _gen(seed)
    d = torch.randn(B, H, W, 3, generator=g, dtype=dtype)
    d = d / d.norm(dim=-1, keepdim=True)
    d[..., 1] = d[..., 1].clamp(-0.95, 0.95)
    d = d * (0.5 + 1.5 * torch.rand(B, H, W, 1, generator=g, dtype=dtype))
    dx = scale * torch.randn(B, H, W, 3, generator=g, dtype=dtype)
    dy = scale * torch.randn(B, H, W, 3, generator=g, dtype=dtype)
    return d, dx, dy


def _smooth(d: torch.Tensor) -> torch.Tensor:
    """A closed-form smooth function of unit directions [..., 3] -> [..., 2], not symmetric about any axis."""
    x, y, z = d.unbind(-1)
    return torch.stack([1.0 + 0.5 * x - 0.3 * y + 0.2 * z + 0.4 * x * z,
                        0.5 + 0.25 * y * y - 0.3 * x * y + 0.1 * z], dim=-1)


def _smooth_env(He: int, We: int, dtype=F64) -> torch.Tensor:
    """_smooth sampled at the texel centres of an He x We equirect map: [1, 2, He, We]."""
    v = (torch.arange(He, dtype=dtype) + 0.5) / He
    u = (torch.arange(We, dtype=dtype) + 0.5) / We
    uv = torch.stack(torch.meshgrid(u, v, indexing="xy"), dim=-1)  # [He, We, 2]
    return _smooth(equirect_uv_to_direction(uv)).permute(2, 0, 1)[None]


def _unit_dirs(n: int, seed: int, dtype=F64) -> torch.Tensor:
    d = torch.randn(1, n, n, 3, generator=_gen(seed), dtype=dtype)
    return d / d.norm(dim=-1, keepdim=True)


# --------------------------------------------------------------------------
# values
# --------------------------------------------------------------------------


@pytest.mark.parametrize("filter", FILTERS)
def test_matches_sample_at_direction_uv(filter):
    # The uv and derivatives of direction_to_equirect_uv, read with wrap (repeat, clamp): the same image.
    env = torch.rand(2, 3, 16, 32, generator=_gen(1), dtype=F64)
    d, dx, dy = _dirs(2, 5, 7, seed=2, scale=0.05)
    uv, uv_dx, uv_dy = direction_to_equirect_uv(d, dirs_dx=dx, dirs_dy=dy)
    want = difftex.sample(env, uv, filter=filter, wrap=WRAP, uv_dx=uv_dx, uv_dy=uv_dy, lod_bias=0.3)
    got = equirect(env, d, filter=filter, dirs_dx=dx, dirs_dy=dy, lod_bias=0.3)
    assert got.shape == (2, 3, 5, 7)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    if filter not in MIP_FILTERS:
        torch.testing.assert_close(equirect(env, d, filter=filter), want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("filter", ["bilinear", "trilinear", "anisotropic", "ewa"])
def test_length_of_directions_does_not_matter(filter):
    env = torch.rand(1, 2, 16, 32, generator=_gen(3), dtype=F64)
    d, dx, dy = _dirs(1, 4, 6, seed=4, scale=0.1)
    ref = equirect(env, d, filter=filter, dirs_dx=dx, dirs_dy=dy)
    # A pixel-dependent length s(x, y): the derivatives of s d are s dd + ds d, the radial part ds d changes nothing.
    s = 0.1 + 5 * torch.rand(1, 4, 6, 1, generator=_gen(5), dtype=F64)
    ds = torch.randn(1, 4, 6, 1, generator=_gen(6), dtype=F64)
    got = equirect(env, s * d, filter=filter, dirs_dx=s * dx + ds * d, dirs_dy=s * dy - ds * d)
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)


def test_smooth_function_error_shrinks_with_resolution():
    d = _unit_dirs(24, seed=7)
    want = _smooth(d).permute(0, 3, 1, 2)
    errs = []
    for He in (16, 32, 64, 128):
        errs.append((equirect(_smooth_env(He, 2 * He), d) - want).abs().max().item())
    # Bilinear is second order inside; the clamped polar half-rows are first order, so at least 2x per doubling.
    for coarse, fine in zip(errs, errs[1:]):
        assert fine < coarse / 2, errs
    assert errs[-1] < 0.01, errs


def test_seam_is_continuous():
    # phi = atan2(x, -z) = +-pi at +z: u = 1 and u = 0, columns We - 1 and 0 of the map.
    env = torch.rand(1, 3, 32, 64, generator=_gen(8), dtype=F64)
    theta = torch.linspace(0.3, 2.8, 9, dtype=F64)
    eps = 1e-3

    def at(phi):
        s = torch.sin(theta)
        d = torch.stack([s * math.sin(phi), torch.cos(theta), -s * math.cos(phi)], dim=-1)[None, None]
        dx = torch.stack([s * math.cos(phi), 0 * s, s * math.sin(phi)], dim=-1)[None, None] * 0.3
        dy = torch.stack([torch.cos(theta) * math.sin(phi), -s, -torch.cos(theta) * math.cos(phi)],
                         dim=-1)[None, None] * 0.05
        return {f: equirect(env, d, filter=f, dirs_dx=dx, dirs_dy=dy) for f in ("bilinear", "trilinear", "ewa")}

    seam_lo, seam_hi = at(math.pi - eps), at(-math.pi + eps)
    for f in seam_lo:
        seam = (seam_lo[f] - seam_hi[f]).abs().max()
        inner = max((at(p - eps)[f] - at(p + eps)[f]).abs().max() for p in (-2.0, -0.7, 0.4, 1.9))
        # Without wrapping, column 0 against column 63 of noise: differences ~0.5.
        assert seam < 1.5 * inner + 1e-12, (f, seam, inner)
        assert seam < 0.05, (f, seam)


def test_seam_derivative_keeps_the_level():
    # A view straddling the seam: finite differences of u would jump by 1 there, the analytic ones do not,
    # so a magnified view reads level 0 (trilinear = bilinear), as it does away from the seam.
    env = torch.rand(1, 1, 32, 64, generator=_gen(9), dtype=F64)
    phi = torch.tensor([math.pi - 1e-3, -math.pi + 1e-3, 0.5], dtype=F64)
    d = torch.stack([torch.sin(phi), 0 * phi, -torch.cos(phi)], dim=-1)[None, None]
    dx = torch.stack([torch.cos(phi), 0 * phi, torch.sin(phi)], dim=-1)[None, None] * 0.01
    dy = torch.tensor([0.0, -0.01, 0.0], dtype=F64).expand_as(dx)
    tri = equirect(env, d, filter="trilinear", dirs_dx=dx, dirs_dy=dy)
    torch.testing.assert_close(tri, equirect(env, d), rtol=0, atol=1e-12)


def _ring_env(He=32, We=64):
    # 1 + 0.5 cos(2 pi u) on the top and bottom 8 rows (average 1 around any latitude circle), 5 in between.
    u = (torch.arange(We, dtype=F64) + 0.5) / We
    env = torch.full((1, 1, He, We), 5.0, dtype=F64)
    env[..., :8, :] = env[..., -8:, :] = 1 + 0.5 * torch.cos(2 * math.pi * u)
    return env


@pytest.mark.parametrize("theta", [0.0, 1e-6, 1e-3, 0.02])
@pytest.mark.parametrize("north", [True, False])
def test_pole_reads_the_circle(theta, north):
    env = _ring_env()
    c = math.cos(theta) if north else -math.cos(theta)
    d = torch.tensor([[[[math.sin(theta), c, 0.0]]]], dtype=F64)
    dx = torch.tensor([[[[0.0, 0.0, 0.02]]]], dtype=F64)
    dy = torch.tensor([[[[0.02, 0.0, 0.0]]]], dtype=F64)
    # At / near the pole the footprint spans the whole circle of longitudes (u capped at one turn): the
    # anisotropic and EWA filters average the polar rows around it (1), not the whole map (~3.5).
    for f in ("anisotropic", "ewa"):
        v = equirect(env, d, filter=f, dirs_dx=dx, dirs_dy=dy).item()
        assert abs(v - 1.0) < 0.02, (f, v)
    tri = equirect(env, d, filter="trilinear", dirs_dx=dx, dirs_dy=dy).item()
    if theta < 0.02 / (2 * math.pi):
        # A footprint of a turn or more: trilinear takes that length for both axes, the coarsest level
        # of a 64-wide map (its mean).
        assert tri == pytest.approx(env.mean().item(), abs=0.01)
    else:
        assert 1.2 < tri < env.mean().item() - 0.5  # 0.16 turn: still blurred far across latitudes
    if theta == 0.0:
        # u = 0.5 at the pole, between columns 31 and 32: -cos(pi / 64) there.
        assert equirect(env, d).item() == pytest.approx(1 - 0.5 * math.cos(math.pi / 64), abs=1e-12)


def test_u_derivative_capped_at_one_turn():
    # Off the pole, the cap leaves the value of a footprint under one turn alone and makes a longer one
    # read like exactly one turn.
    env = torch.rand(1, 2, 32, 64, generator=_gen(21), dtype=F64)
    theta = 1e-4
    d = torch.tensor([[[[math.sin(theta), math.cos(theta), 0.0]]]], dtype=F64)
    dy = torch.tensor([[[[0.0, 0.0, 0.0]]]], dtype=F64)
    # dx = a along z: du = a / (2 pi sin(theta)) turns.
    turns = lambda k: torch.tensor([[[[0.0, 0.0, k * 2 * math.pi * math.sin(theta)]]]], dtype=F64)
    for f in ("anisotropic", "ewa", "trilinear"):
        one = equirect(env, d, filter=f, dirs_dx=turns(1.0), dirs_dy=dy)
        torch.testing.assert_close(equirect(env, d, filter=f, dirs_dx=turns(40.0), dirs_dy=dy), one,
                                   rtol=0, atol=1e-12)
        assert (equirect(env, d, filter=f, dirs_dx=turns(0.25), dirs_dy=dy) - one).abs().max() > 1e-3


def test_near_pole_footprint_is_long_and_thin():
    # Latitude bands (a function of v only): the footprint near the pole is long along the latitude circle
    # and thin across it, so the anisotropic filter keeps the band's value; trilinear, isotropic, takes the
    # long side for both and blurs across the bands.
    He, We = 64, 128
    v = (torch.arange(He, dtype=F64) + 0.5) / He
    env = torch.cos(4 * math.pi * v)[:, None].expand(1, 1, He, We).clone()
    theta = torch.tensor([0.05, 0.1, 0.2], dtype=F64)
    d = torch.stack([torch.sin(theta), torch.cos(theta), 0 * theta], dim=-1)[None, None]
    # A pixel of 0.05 rad (one texel of v) each way: along the circle that is 0.05 / sin(theta) rad of longitude.
    dx = torch.tensor([0.0, 0.0, 0.05], dtype=F64).expand_as(d)
    dy = torch.stack([torch.cos(theta), -torch.sin(theta), 0 * theta], dim=-1)[None, None] * 0.05
    want = torch.cos(4 * theta)
    aniso = equirect(env, d, filter="anisotropic", dirs_dx=dx, dirs_dy=dy)[0, 0, 0]
    tri = equirect(env, d, filter="trilinear", dirs_dx=dx, dirs_dy=dy)[0, 0, 0]
    # Measured: anisotropic within 0.005 of the bands; trilinear off by 0.98, 0.51, 0.07
    # (footprints 20 x 1, 10 x 1, 5 x 1 texels: levels 4.4, 3.4, 2.4).
    assert (aniso - want).abs().max() < 0.01, (aniso, want)
    assert ((tri - want).abs() > 5 * (aniso - want).abs()).all(), (tri, aniso, want)


def test_pole_derivative_and_gradients_finite():
    env = torch.rand(1, 2, 16, 32, generator=_gen(10), dtype=F64, requires_grad=True)
    d = torch.tensor([[[[0.0, 2.0, 0.0], [0.0, -1.0, 0.0]]]], dtype=F64, requires_grad=True)
    dx = torch.tensor([[[[2.0, 0.3, 0.0], [0.0, 0.0, 0.8]]]], dtype=F64, requires_grad=True)
    dy = torch.tensor([[[[0.0, 0.0, 0.01], [0.0, 0.5, 0.0]]]], dtype=F64, requires_grad=True)
    # EWA: the minor axis (here the v extent, 5 and 4 texels, over the max_aniso cap of 32 / 16) picks the level.
    out = equirect(env, d, filter="ewa", dirs_dx=dx, dirs_dy=dy)
    out.sum().backward()
    assert torch.isfinite(out).all()
    for t in (env, d, dx, dy):
        assert torch.isfinite(t.grad).all()
    assert dx.grad[..., [0, 2]].abs().sum() > 0  # the tangential derivative sets the footprint's v extent
    # The pole's uv has no gradient w.r.t. the direction: bilinear (no footprint) passes none to it.
    d.grad = None
    equirect(env, d).sum().backward()
    assert (d.grad == 0).all()


def test_zero_direction_gives_zero_and_no_gradient():
    env = torch.rand(1, 2, 8, 16, generator=_gen(11), dtype=F64, requires_grad=True)
    d, dx, dy = _dirs(1, 2, 3, seed=12, scale=0.1)
    d[0, 1, 2] = 0.0
    d.requires_grad_(True), dx.requires_grad_(True), dy.requires_grad_(True)
    for f in ("bilinear", "trilinear", "ewa"):
        for t in (env, d, dx, dy):
            t.grad = None
        out = equirect(env, d, filter=f, dirs_dx=dx, dirs_dy=dy)
        assert (out[0, :, 1, 2] == 0).all() and (out[0, :, :1] != 0).all()
        (out * torch.arange(1, 3, dtype=F64)[:, None, None]).sum().backward()
        for t in (d, dx, dy):
            if t.grad is not None or t is d:  # bilinear does not read the derivatives
                assert torch.isfinite(t.grad).all() and (t.grad[0, 1, 2] == 0).all()
        assert d.grad[0, 0].abs().sum() > 0
        # The env gradient is that of the other pixels alone.
        g = env.grad.clone()
        env.grad = None
        keep = torch.ones(1, 1, 2, 3, dtype=F64)
        keep[0, 0, 1, 2] = 0
        (equirect(env, d.detach(), filter=f, dirs_dx=dx.detach(), dirs_dy=dy.detach())
         * keep * torch.arange(1, 3, dtype=F64)[:, None, None]).sum().backward()
        torch.testing.assert_close(g, env.grad, rtol=0, atol=1e-12)


def test_nan_direction_stays_in_its_pixel():
    env = torch.rand(1, 2, 8, 16, generator=_gen(13), dtype=F64, requires_grad=True)
    d, dx, dy = _dirs(1, 2, 3, seed=14, scale=0.1)
    d[0, 0, 1, 0] = float("nan")
    d[0, 1, 0, 2] = float("inf")
    out = equirect(env, d, filter="trilinear", dirs_dx=dx, dirs_dy=dy)
    bad = torch.zeros(2, 3, dtype=torch.bool)
    bad[0, 1] = bad[1, 0] = True
    assert torch.isnan(out[0][:, bad]).all() and torch.isfinite(out[0][:, ~bad]).all()
    torch.where(bad, 0.0, out).sum().backward()
    g = env.grad.clone()
    env.grad = None
    d_ok = torch.where(bad[None, ..., None], torch.tensor([1.0, 0.0, 0.0], dtype=F64), d)
    torch.where(bad, 0.0, equirect(env, d_ok, filter="trilinear", dirs_dx=dx, dirs_dy=dy)).sum().backward()
    assert torch.isfinite(g).all()
    torch.testing.assert_close(g, env.grad, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------
# gradients
# --------------------------------------------------------------------------


@pytest.mark.parametrize("filter", ["bilinear", "trilinear"])
def test_gradcheck(filter):
    env = torch.rand(1, 2, 6, 12, generator=_gen(15), dtype=F64, requires_grad=True)
    d, dx, dy = _dirs(1, 2, 3, seed=16, scale=0.3)
    for t in (d, dx, dy):
        t.requires_grad_(True)
    fn = lambda e, a, b, c: equirect(e, a, filter=filter, dirs_dx=b, dirs_dy=c)
    assert torch.autograd.gradcheck(fn, (env, d, dx, dy), eps=1e-6, atol=1e-6)


def test_gradcheck_equirect_to_cube_env():
    env = torch.rand(1, 1, 4, 8, generator=_gen(17), dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda e: equirect_to_cube(e, 2), (env,), eps=1e-6, atol=1e-6)


# --------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------


def test_bad_input():
    env = torch.rand(1, 3, 8, 16)
    d = torch.randn(1, 2, 2, 3)
    with pytest.raises(TypeError, match="env"):
        equirect([[1.0]], d)
    with pytest.raises(ValueError, match=r"env: expected 4-D"):
        equirect(env[0], d)
    with pytest.raises(TypeError, match="dirs"):
        equirect(env, d.long())
    with pytest.raises(ValueError, match=r"dirs: expected last dimension 3"):
        equirect(env, d[..., :2])
    with pytest.raises(ValueError, match=r"dirs: expected 4-D"):
        equirect(env, d[0])
    with pytest.raises(TypeError, match=r"dirs: expected dtype torch.float32 like env"):
        equirect(env, d.double())
    with pytest.raises(ValueError, match=r"dirs_dx: required by filter 'trilinear'"):
        equirect(env, d, filter="trilinear")
    with pytest.raises(ValueError, match=r"dirs_dy: required by given dirs_dx"):
        equirect(env, d, dirs_dx=d)
    with pytest.raises(ValueError,
                       match=r"dirs_dx: expected shape \[B, H, W, 3\] = \[1, 2, 2, 3\] like dirs, got shape \(1, 1, 2, 3\)"):
        equirect(env, d, filter="trilinear", dirs_dx=d[:, :1], dirs_dy=d)
    with pytest.raises(TypeError, match=r"dirs_dy: expected dtype torch.float32"):
        equirect(env, d, filter="trilinear", dirs_dx=d, dirs_dy=d.double())
    with pytest.raises(ValueError, match=r"batch sizes do not match \(env 1, dirs 2, dirs_dx 3"):
        equirect(env, d.expand(2, -1, -1, -1), filter="trilinear", dirs_dx=d.expand(3, -1, -1, -1), dirs_dy=d)
    with pytest.raises(ValueError, match=r"batch sizes do not match \(env 2, dirs 3\)"):
        equirect(env.expand(2, -1, -1, -1), d.expand(3, -1, -1, -1))
    with pytest.raises(ValueError, match="filter"):
        equirect(env, d, filter="box")
    with pytest.raises(ValueError, match="max_aniso"):
        equirect(env, d, filter="anisotropic", dirs_dx=d, dirs_dy=d, max_aniso=0.5)
    with pytest.raises(ValueError, match=r"size: expected an int >= 1"):
        equirect_to_cube(env, 0)
    with pytest.raises(TypeError, match=r"size: expected an int >= 1"):
        equirect_to_cube(env, 2.5)
    with pytest.raises(ValueError, match=r"env: expected 4-D"):
        equirect_to_cube(env[0], 4)


# --------------------------------------------------------------------------
# batch / dtype / Mipmap
# --------------------------------------------------------------------------


def test_batch_broadcast_dtype_and_mipmap():
    env = torch.rand(2, 3, 16, 32, generator=_gen(18), dtype=F64)
    d, dx, dy = _dirs(1, 3, 4, seed=19, scale=0.2)
    both = equirect(env, d, filter="trilinear", dirs_dx=dx, dirs_dy=dy)
    assert both.shape == (2, 3, 3, 4)
    for i in range(2):
        torch.testing.assert_close(both[i:i + 1], equirect(env[i:i + 1], d, filter="trilinear", dirs_dx=dx,
                                                           dirs_dy=dy), rtol=0, atol=1e-12)
    # B = 1 env over two views.
    d2, dx2, dy2 = (torch.cat([t, t.flip(1)]) for t in (d, dx, dy))
    views = equirect(env[:1], d2, filter="anisotropic", dirs_dx=dx2, dirs_dy=dy2)
    torch.testing.assert_close(views[1:], equirect(env[:1], d.flip(1), filter="anisotropic", dirs_dx=dx.flip(1),
                                                   dirs_dy=dy.flip(1)), rtol=0, atol=1e-12)
    # A Mipmap reads the same pyramid as the tensor.
    torch.testing.assert_close(equirect(difftex.mipmap(env), d, filter="trilinear", dirs_dx=dx, dirs_dy=dy), both,
                               rtol=0, atol=1e-12)
    # float32 follows float64.
    f32 = equirect(env.float(), d.float(), filter="trilinear", dirs_dx=dx.float(), dirs_dy=dy.float())
    assert f32.dtype == torch.float32
    torch.testing.assert_close(f32.double(), both, rtol=0, atol=1e-4)
    cube = equirect_to_cube(env.float(), 4)
    assert cube.shape == (2, 6, 3, 4, 4) and cube.dtype == torch.float32


# --------------------------------------------------------------------------
# the bundled HDR environment
# --------------------------------------------------------------------------


def test_venice_sunset_hdr_statistics():
    env = difftex.load_texture(difftex.io.data_path("envmap/venice_sunset_1k.hdr"), dtype=F64)
    assert env.shape == (1, 3, 512, 1024)
    assert torch.isfinite(env).all() and (env >= 0).all()
    assert env.max() > 1  # high dynamic range: the sun
    # Per-channel means (computed once with OpenCV's RGBE decoder), to 3 significant digits.
    torch.testing.assert_close(env.mean(dim=(0, 2, 3)), torch.tensor([0.40466, 0.41624, 0.57343], dtype=F64),
                               rtol=1e-3, atol=0)
    # Row 0 is up (the convention of direction_to_equirect_uv): the sky half is brighter than the ground half.
    assert (env[0, :, :256].mean(dim=(1, 2)) > 2 * env[0, :, 256:].mean(dim=(1, 2))).all()


# --------------------------------------------------------------------------
# equirect_to_cube
# --------------------------------------------------------------------------


def _texel_directions(size: int) -> torch.Tensor:
    c = (torch.arange(size, dtype=F64) + 0.5) / size
    uv = torch.stack(torch.meshgrid(c, c, indexing="xy"), dim=-1).expand(6, size, size, 2)
    d = cube_to_direction(torch.arange(6)[:, None, None].expand(6, size, size), uv)
    return d / d.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("filter", ["bilinear", "trilinear", "anisotropic"])
def test_equirect_to_cube_matches_smooth_function(filter):
    # Map and cube refined together (He = 4 size): the error of bilinear and of the prefilters is second order.
    errs, side = [], []
    for size in (4, 8, 16, 32):
        cube = equirect_to_cube(_smooth_env(4 * size, 8 * size), size, filter=filter)
        want = _smooth(_texel_directions(size)).permute(0, 3, 1, 2)[None]
        assert cube.shape == (1, 6, 2, size, size)
        err = (cube - want).abs()[0].amax(1)  # [6, size, size]
        errs.append(err.max().item())
        side.append(err[[0, 1, 4, 5]].max().item())  # the faces around the equator
    for coarse, fine in zip(side, side[1:]):
        assert fine < coarse / 2.5, side
    assert side[-1] < 1.5e-3, side
    if filter == "trilinear":
        # Isotropic trilinear on the polar faces: the longitude derivative grows like 1 / sin(theta), so the texels
        # next to the pole read a level that blurs across latitudes; it does not converge there.
        assert 0.2 < errs[-1] < 0.35, errs
    else:
        for coarse, fine in zip(errs, errs[1:]):
            assert fine < coarse / 2.5, errs
        assert errs[-1] < 1.5e-3, errs


def test_equirect_to_cube_minified_noise_filters():
    # 1024 x 512 noise into a 16^2 cube: ~16 map texels per cube texel along the equator, many more near the poles.
    env = torch.rand(1, 1, 512, 1024, generator=_gen(20))
    size, k = 16, 16
    # Reference: the mean of k x k bilinear lookups spread over each cube texel.
    c = (torch.arange(size * k, dtype=torch.float32) + 0.5) / (size * k)
    uv = torch.stack(torch.meshgrid(c, c, indexing="xy"), dim=-1).expand(6, size * k, size * k, 2)
    d = cube_to_direction(torch.arange(6)[:, None, None].expand(6, size * k, size * k), uv)
    fine = equirect(env, d.reshape(1, 6 * size * k, size * k, 3)).view(1, 6, size, k, size, k)
    ref = fine.mean(dim=(3, 5))[:, :, None]
    scores = {f: psnr(equirect_to_cube(env, size, filter=f), ref) for f in ("bilinear", "trilinear", "anisotropic")}
    assert scores["trilinear"] > scores["bilinear"] + 10, scores
    assert scores["anisotropic"] > scores["trilinear"], scores


def test_gradcheck_capped_footprint_near_pole():
    # du over one turn (scaled down to it): the level is log2 of the capped length, still differentiable.
    env = torch.rand(1, 1, 16, 64, generator=_gen(22), dtype=F64, requires_grad=True)
    d = torch.tensor([[[[0.003, 1.0, 0.001], [-0.0021, -1.0, 0.0017]]]], dtype=F64, requires_grad=True)
    dx = torch.tensor([[[[0.01, 0.002, 0.04], [0.03, 0.0, -0.01]]]], dtype=F64, requires_grad=True)
    dy = torch.tensor([[[[0.02, 0.0, -0.01], [0.01, 0.003, 0.02]]]], dtype=F64, requires_grad=True)
    fn = lambda e, a, b, c: equirect(e, a, filter="trilinear", dirs_dx=b, dirs_dy=c, lod_bias=-1.3)
    uv, ux, uy = direction_to_equirect_uv(d, dirs_dx=dx, dirs_dy=dy)
    assert (torch.hypot(ux[..., 0], uy[..., 0]) > 1.4).all()  # the cap is active
    assert torch.autograd.gradcheck(fn, (env, d, dx, dy), eps=1e-7, atol=1e-6)

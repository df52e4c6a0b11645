"""bump and normal_map: identity cases, the ramp's tilt of atan(s * scale), agreement, gradients, bad input."""
import math

import pytest
import torch

from difftex.shading import bump, height_slope, normal_map
from tests.shading.helpers import random_frames


def _uv(n=5, lo=0.3, hi=0.7, dtype=torch.float64):
    """An n x n grid of uv in [lo, hi]^2 (interior: clamp and the mip edges never reach it), [1, n, n, 2]."""
    t = torch.linspace(lo, hi, n, dtype=dtype)
    v, u = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([u, v], -1)[None]


def _derivs(uv, texels):
    """Screen derivatives of ``texels`` level-0 texels per pixel along u and v (a footprint that picks level log2)."""
    dx, dy = torch.zeros_like(uv), torch.zeros_like(uv)
    dx[..., 0], dy[..., 1] = texels, texels
    return dict(uv_dx=dx, uv_dy=dy)


FILTERS = [("bilinear", False), ("bicubic", False), ("trilinear", True), ("anisotropic", True)]


@pytest.mark.parametrize("method", ["analytic", "difference"])
@pytest.mark.parametrize("filter,mip", FILTERS)
def test_constant_height_leaves_normals_unchanged(filter, mip, method, device):
    uv = _uv().to(device)
    frames = random_frames((1, 5, 5)).to(device)
    kw = _derivs(uv, 4 / 64) if mip else {}
    out = bump(torch.full((1, 1, 64, 64), 0.7, dtype=torch.float64, device=device), uv, frames, 3.0,
               method=method, filter=filter, **kw)
    torch.testing.assert_close(out, frames[..., 2, :], atol=1e-12, rtol=0)


# Keys' cubic with a = -0.75 (grid_sample's) does not reproduce a linear function: its slope on a ramp
# oscillates around s within each texel, so bicubic joins only the difference form (exact over one texel).
RAMP_CASES = [(f, m, "analytic") for f, m in FILTERS if f != "bicubic"] + [(f, m, "difference") for f, m in FILTERS]


@pytest.mark.parametrize("filter,mip,method", RAMP_CASES)
@pytest.mark.parametrize("axis", [0, 1])
def test_linear_ramp_tilts_by_atan_of_slope_times_scale(axis, filter, mip, method, device):
    s, scale, W = 0.8, 1.5, 64
    x = (torch.arange(W, dtype=torch.float64, device=device) + 0.5) / W  # texel centres: the interpolant is s * u
    ramp = (s * x).expand(W, W)
    height = (ramp if axis == 0 else ramp.T)[None, None].contiguous()
    uv = _uv().to(device)
    frames = random_frames((1, 5, 5), seed=4).to(device)
    kw = _derivs(uv, 4 / W) if mip else {}
    n = bump(height, uv, frames, scale, method=method, filter=filter, wrap="clamp", **kw)
    local = (frames @ n.unsqueeze(-1)).squeeze(-1)  # tangent-space components (T, B, N)
    tilt = torch.atan2(local[..., :2].norm(dim=-1), local[..., 2])
    torch.testing.assert_close(tilt, torch.full_like(tilt, math.atan(s * scale)), atol=1e-9, rtol=0)
    # Downhill: the normal leans towards minus the ramp's axis, with nothing along the other one.
    torch.testing.assert_close(local[..., axis], torch.full_like(tilt, -math.sin(math.atan(s * scale))),
                               atol=1e-9, rtol=0)
    assert local[..., 1 - axis].abs().max() < 1e-9
    slope = height_slope(height, uv, method=method, filter=filter, wrap="clamp", **kw)
    torch.testing.assert_close(slope[..., axis], torch.full_like(tilt, s), atol=1e-9, rtol=0)


def test_analytic_slope_is_the_interpolant_derivative_and_differs_from_the_difference():
    # h = sin-bumps: the analytic bilinear slope equals the texel difference of the cell the point is in,
    # the seed's forward difference reads the next texel over (one texel ahead): they differ.
    g = torch.Generator().manual_seed(0)
    h = torch.rand(1, 1, 8, 8, dtype=torch.float64, generator=g)
    uv = torch.tensor([[[[(2.5 + 0.3) / 8, (4.5 + 0.6) / 8]]]], dtype=torch.float64)  # cell (2..3, 4..5)
    a = height_slope(h, uv, method="analytic")
    fu, fv = 0.3, 0.6
    row = lambda r: h[0, 0, r, 2] * (1 - fu) + h[0, 0, r, 3] * fu
    dh_du = ((h[0, 0, 4, 3] - h[0, 0, 4, 2]) * (1 - fv) + (h[0, 0, 5, 3] - h[0, 0, 5, 2]) * fv) * 8
    dh_dv = (row(5) - row(4)) * 8
    torch.testing.assert_close(a[0, 0, 0], torch.stack([dh_du, dh_dv]), atol=1e-12, rtol=0)
    d = height_slope(h, uv, method="difference")
    assert (a - d).abs().max() > 1e-3


def test_flat_normal_map_is_the_identity_and_a_tilted_one_rotates():
    uv = _uv()
    frames = random_frames((1, 5, 5), seed=2)
    flat = torch.tensor([0.5, 0.5, 1.0], dtype=torch.float64)[None, :, None, None].expand(1, 3, 16, 16)
    for filter, kw in (("bilinear", {}), ("trilinear", _derivs(uv, 0.25))):
        out = normal_map(flat, uv, frames, filter=filter, **kw)
        torch.testing.assert_close(out, frames[..., 2, :], atol=1e-12, rtol=0)
    a = 0.4
    tilted = torch.tensor([(math.sin(a) + 1) / 2, 0.5, (math.cos(a) + 1) / 2], dtype=torch.float64)
    tex = tilted[None, :, None, None].expand(1, 3, 4, 4)
    out = normal_map(tex, uv, frames)
    torch.testing.assert_close(out, math.sin(a) * frames[..., 0, :] + math.cos(a) * frames[..., 2, :])
    g = torch.tensor([0.5, (math.sin(a) + 1) / 2, (math.cos(a) + 1) / 2], dtype=torch.float64)[None, :, None, None]
    up = normal_map(g.expand(1, 3, 4, 4), uv, frames, green="up")
    torch.testing.assert_close(up, -math.sin(a) * frames[..., 1, :] + math.cos(a) * frames[..., 2, :])


def test_normal_map_encoding_a_bump_gives_the_same_normals():
    # A ramp's bump normal, written into a constant normal map, shades the same.
    s, scale = 0.5, 2.0
    x = (torch.arange(16, dtype=torch.float64) + 0.5) / 16
    height = (s * x).expand(16, 16)[None, None].contiguous()
    uv = _uv(3)
    frames = random_frames((1, 3, 3), seed=5)
    b = bump(height, uv, frames, scale, wrap="clamp")
    t = torch.tensor([-s * scale, 0.0, 1.0], dtype=torch.float64)
    t = t / t.norm()
    nm = normal_map(((t + 1) / 2)[None, :, None, None].expand(1, 3, 16, 16), uv, frames)
    torch.testing.assert_close(nm, b, atol=1e-12, rtol=0)


def test_gradcheck_bump_and_normal_map():
    g = torch.Generator().manual_seed(7)
    h = torch.rand(1, 1, 6, 6, dtype=torch.float64, generator=g, requires_grad=True)
    uv = (torch.rand(1, 2, 3, 2, dtype=torch.float64, generator=g) * 0.9 + 0.05).requires_grad_()
    frames = random_frames((1, 2, 3), seed=1).requires_grad_()
    scale = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
    for method in ("analytic", "difference"):
        f = lambda h, uv, fr, s: bump(h, uv, fr, s, method=method, filter="bicubic")
        assert torch.autograd.gradcheck(f, (h, uv, frames, scale))
    kw = _derivs(uv.detach(), 0.3)
    assert torch.autograd.gradcheck(lambda h, s: bump(h, uv.detach(), frames.detach(), s, filter="trilinear", **kw),
                                    (h, scale))
    tex = torch.rand(1, 3, 5, 5, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t, uv, fr: normal_map(t, uv, fr), (tex, uv, frames))


def test_a_mipmap_height_reads_like_the_plain_tensor():
    import difftex

    g = torch.Generator().manual_seed(2)
    h = torch.rand(1, 1, 16, 16, dtype=torch.float64, generator=g)
    uv = _uv()
    frames = random_frames((1, 5, 5), seed=3)
    kw = dict(filter="trilinear", **_derivs(uv, 0.2))
    torch.testing.assert_close(bump(difftex.mipmap(h), uv, frames, 0.5, **kw), bump(h, uv, frames, 0.5, **kw))


def test_no_grad_and_batches():
    h = torch.rand(2, 1, 8, 8)
    uv = _uv(dtype=torch.float32)
    frames = random_frames((1, 5, 5), dtype=torch.float32)
    with torch.no_grad():
        out = bump(h, uv, frames, 1.0)
    assert out.shape == (2, 5, 5, 3) and not out.requires_grad
    each = torch.cat([bump(h[i:i + 1], uv, frames, 1.0) for i in range(2)])
    torch.testing.assert_close(out, each)


def test_bad_input():
    uv = _uv()
    frames = random_frames((1, 5, 5))
    h = torch.rand(1, 1, 8, 8, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"height: expected 1 channel \[B, 1, H, W\], got shape \(1, 3, 8, 8\)"):
        bump(torch.rand(1, 3, 8, 8, dtype=torch.float64), uv, frames)
    with pytest.raises(ValueError, match=r"frames: expected \[B, Ho, Wo, 3, 3\] = \[B, 5, 5, 3, 3\]"):
        bump(h, uv, frames[:, :4])
    with pytest.raises(ValueError, match=r"method: unknown slope method 'sobel'"):
        bump(h, uv, frames, method="sobel")
    with pytest.raises(ValueError, match=r"filter: 'nearest' has a zero slope"):
        bump(h, uv, frames, filter="nearest")
    with pytest.raises(ValueError, match=r"uv_dx: required by filter 'trilinear'"):
        bump(h, uv, frames, filter="trilinear")
    with pytest.raises(TypeError, match=r"scale: expected dtype torch.float64 like uv"):
        bump(h, uv, frames, torch.tensor(1.0))
    with pytest.raises(ValueError, match=r"shapes do not broadcast \(scale \(3,\), uv's \[B, Ho, Wo\] \(1, 5, 5\)\)"):
        bump(h, uv, frames, torch.ones(3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"scale: expected a number or a tensor broadcasting to \[B, Ho, Wo\]"):
        bump(h, uv, frames, torch.ones(1, 5, 5, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"texture: expected 3 channels"):
        normal_map(h, uv, frames)
    with pytest.raises(ValueError, match=r"green: expected one of \('down', 'up'\)"):
        normal_map(torch.rand(1, 3, 4, 4, dtype=torch.float64), uv, frames, green="left")
    with pytest.raises(TypeError, match=r"frames: expected dtype torch.float64 like uv"):
        normal_map(torch.rand(1, 3, 4, 4, dtype=torch.float64), uv, frames.float())

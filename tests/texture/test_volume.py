"""sample3d: 3D textures against F.grid_sample on 5-D input, gradients, batches, bad input."""
import pytest
import torch
import torch.nn.functional as F

from difftex.texture.volume import sample3d

# grid_sample's padding mode for each wrap (align_corners=False); repeat goes through a circular pad.
PADDING = {"clamp": "border", "mirror": "reflection", "border": "zeros"}


def _grid_sample(volume, uvw, mode, wrap):
    """grid_sample reading like sample3d: [B, C, ...]; repeat as a one-texel circular pad and folded uvw."""
    B = uvw.shape[0]
    pts = uvw.reshape(B, 1, 1, -1, 3)
    if wrap == "repeat":
        D, H, W = volume.shape[2:]
        volume = F.pad(volume, (1, 1, 1, 1, 1, 1), mode="circular")
        n = pts.new_tensor([W, H, D])
        pts = ((pts - torch.floor(pts)) * n + 1) / (n + 2)
        pad = "border"
    else:
        pad = PADDING[wrap]
    out = F.grid_sample(volume.expand(B, -1, -1, -1, -1), 2 * pts - 1, mode=mode, padding_mode=pad,
                        align_corners=False)
    return out.reshape(B, volume.shape[1], *uvw.shape[1:-1])


@pytest.mark.parametrize("wrap", ["repeat", "clamp", "mirror", "border"])
@pytest.mark.parametrize("filt", ["nearest", "linear"])
def test_matches_grid_sample(filt, wrap, device, dtype):
    g = torch.Generator().manual_seed(0)
    vol = torch.rand(2, 3, 4, 5, 6, generator=g, dtype=dtype).to(device)
    uvw = (torch.rand(2, 7, 9, 3, generator=g, dtype=dtype) * 2.4 - 0.7).to(device)
    got = sample3d(vol, uvw, filter=filt, wrap=wrap)
    ref = _grid_sample(vol, uvw, "bilinear" if filt == "linear" else "nearest", wrap)
    assert got.shape == (2, 3, 7, 9) and got.dtype == dtype
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert torch.allclose(got, ref, atol=tol, rtol=0)


def test_texel_centres_read_their_texel_and_axes_order():
    vol = torch.arange(2 * 3 * 4, dtype=torch.float64).view(1, 1, 2, 3, 4)
    d, i, j = torch.meshgrid(*(torch.arange(n, dtype=torch.float64) for n in (2, 3, 4)), indexing="ij")
    uvw = torch.stack(((j + 0.5) / 4, (i + 0.5) / 3, (d + 0.5) / 2), -1).unsqueeze(0)
    for filt in ("nearest", "linear"):
        assert torch.allclose(sample3d(vol, uvw, filter=filt), vol, atol=1e-12, rtol=0)


def test_wrap_per_axis_gradients_agree_with_grid_sample():
    g = torch.Generator().manual_seed(1)
    vol = torch.rand(1, 2, 3, 4, 5, generator=g, dtype=torch.float64, requires_grad=True)
    uvw = (torch.rand(1, 40, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    # Inside [0.1, 0.9] clamp and border agree with grid_sample's border except past the outer texel centres.
    wrap = ("clamp", "clamp", "clamp")
    a = sample3d(vol, uvw, wrap=wrap)
    b = _grid_sample(vol, uvw, "bilinear", "clamp")
    w = torch.randn(a.shape, generator=g, dtype=torch.float64)
    ga = torch.autograd.grad((a * w).sum(), (vol, uvw))
    gb = torch.autograd.grad((b * w).sum(), (vol, uvw))
    assert torch.allclose(ga[0], gb[0], atol=1e-12) and torch.allclose(ga[1], gb[1], atol=1e-10)


def test_gradcheck():
    g = torch.Generator().manual_seed(2)
    vol = torch.rand(2, 1, 2, 2, 3, generator=g, dtype=torch.float64, requires_grad=True)
    uvw = (torch.rand(2, 3, 3, generator=g, dtype=torch.float64) * 2 - 0.5).requires_grad_()
    assert torch.autograd.gradcheck(lambda v, u: sample3d(v, u, wrap=("repeat", "mirror", "border"),
                                                          border_value=0.3), (vol, uvw))
    assert torch.autograd.gradcheck(lambda v, u: sample3d(v, u, filter="nearest", wrap="clamp"), (vol, uvw))
    assert torch.autograd.gradgradcheck(lambda v, u: sample3d(v, u, wrap="clamp"), (vol[:1], uvw[:1, :2]))


def test_batches_broadcast():
    g = torch.Generator().manual_seed(3)
    vol = torch.rand(3, 2, 3, 4, 5, generator=g)
    uvw = torch.rand(3, 6, 3, generator=g)
    one_vol = sample3d(vol[:1], uvw)
    assert torch.allclose(one_vol, sample3d(vol[:1].expand(3, -1, -1, -1, -1), uvw))
    one_uvw = sample3d(vol, uvw[:1])
    assert torch.allclose(one_uvw, sample3d(vol, uvw[:1].expand(3, -1, -1)))
    per = torch.cat([sample3d(vol[k:k + 1], uvw[k:k + 1]) for k in range(3)])
    assert torch.allclose(sample3d(vol, uvw), per)


def test_border_value_and_non_finite():
    vol = torch.ones(1, 1, 2, 2, 2)
    uvw = torch.tensor([[[5.0, 0.5, 0.5], [0.5, 0.5, 0.5], [float("nan"), 0.5, 0.5]]])
    out = sample3d(vol, uvw, wrap="border", border_value=0.25)
    assert out[0, 0, 0] == 0.25 and out[0, 0, 1] == 1 and torch.isnan(out[0, 0, 2])
    v = torch.rand(1, 1, 2, 2, 2, dtype=torch.float64, requires_grad=True)
    u = torch.tensor([[[0.3, 0.4, 0.5], [float("inf"), 0.5, 0.5]]], dtype=torch.float64, requires_grad=True)
    out = sample3d(v, u)
    assert torch.isfinite(out[0, 0, 0]) and torch.isnan(out[0, 0, 1])
    gv, gu = torch.autograd.grad(out, (v, u), torch.ones_like(out))  # the NaN output's gradient is 1 too
    assert torch.isfinite(gv).all() and torch.isfinite(gu).all() and torch.all(gu[0, 1] == 0)
    assert torch.allclose(gv.sum(), torch.tensor(1.0, dtype=torch.float64))  # the finite point's weights
    huge = torch.tensor([[[1e30, -1e30, 3e38]]])
    assert torch.isfinite(sample3d(vol, huge, wrap="repeat")).all()


def test_bad_input():
    vol = torch.zeros(1, 1, 2, 2, 2)
    with pytest.raises(ValueError, match=r"volume: expected 5-D \[B, C, D, H, W\], got shape \(1, 2, 2\)"):
        sample3d(torch.zeros(1, 2, 2), torch.zeros(1, 4, 3))
    with pytest.raises(ValueError, match=r"uvw: expected last dimension 3"):
        sample3d(vol, torch.zeros(1, 4, 2))
    with pytest.raises(TypeError, match=r"uvw: expected dtype torch.float32 like volume"):
        sample3d(vol, torch.zeros(1, 4, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"batch sizes do not match \(volume 2, uvw 3\)"):
        sample3d(torch.zeros(2, 1, 2, 2, 2), torch.zeros(3, 4, 3))
    with pytest.raises(ValueError, match=r"filter: expected one of \('nearest', 'linear'\) for sample3d"):
        sample3d(vol, torch.zeros(1, 4, 3), filter="bicubic")
    with pytest.raises(ValueError, match=r"wrap: unknown mode 'wrap'"):
        sample3d(vol, torch.zeros(1, 4, 3), wrap=("repeat", "wrap", "clamp"))
    with pytest.raises(ValueError, match=r"wrap: expected one mode or a triple"):
        sample3d(vol, torch.zeros(1, 4, 3), wrap=("repeat", "clamp"))
    with pytest.raises(TypeError, match=r"border_value: expected a number"):
        sample3d(vol, torch.zeros(1, 4, 3), border_value="0")


def test_volume_mipmap_sizes_and_mean():
    from difftex.texture.volume import volume_mipmap

    g = torch.Generator().manual_seed(4)
    vol = torch.rand(2, 3, 5, 4, 3, generator=g, dtype=torch.float64)
    levels = volume_mipmap(vol)
    assert [tuple(v.shape[2:]) for v in levels] == [(5, 4, 3), (3, 2, 2), (2, 1, 1), (1, 1, 1)]
    for v in levels:  # the area-weighted boxes keep the mean of every channel exactly
        assert torch.allclose(v.mean((2, 3, 4)), vol.mean((2, 3, 4)), atol=1e-14)
    # An even axis halves with the 2-texel box: level 1 of a 2x2x2 volume is its mean.
    assert torch.allclose(volume_mipmap(vol[:, :, :2, :2, :2])[1][..., 0, 0, 0], vol[:, :, :2, :2, :2].mean((2, 3, 4)))
    assert len(volume_mipmap(vol, max_levels=2)) == 2
    with pytest.raises(ValueError, match=r"max_levels: expected None or an int >= 1, got 0"):
        volume_mipmap(vol, max_levels=0)


def test_lod_blends_levels():
    from difftex.texture.volume import volume_mipmap

    g = torch.Generator().manual_seed(5)
    vol = torch.rand(2, 2, 6, 5, 4, generator=g, dtype=torch.float64)
    uvw = torch.rand(2, 7, 3, generator=g, dtype=torch.float64)
    levels = volume_mipmap(vol)
    read = [sample3d(v, uvw, wrap="clamp") for v in levels]
    assert torch.equal(sample3d(vol, uvw, wrap="clamp", lod=0.0), read[0])
    assert torch.allclose(sample3d(vol, uvw, wrap="clamp", lod=2.0), read[2], atol=1e-14)
    assert torch.allclose(sample3d(vol, uvw, wrap="clamp", lod=-3.0), read[0], atol=1e-14)
    assert torch.allclose(sample3d(vol, uvw, wrap="clamp", lod=99.0), read[-1], atol=1e-14)
    lod = torch.rand(2, 7, generator=g, dtype=torch.float64) * 2.5
    lo = lod.floor().long()
    f = (lod - lo).unsqueeze(1)
    stack = torch.stack(read)  # [levels, B, C, M]

    def pick(k):
        return stack.gather(0, k.clamp(max=len(read) - 1).view(1, 2, 1, 7).expand(1, 2, 2, 7))[0]

    want = (1 - f) * pick(lo) + f * pick(lo + 1)
    assert torch.allclose(sample3d(vol, uvw, wrap="clamp", lod=lod), want, atol=1e-14)
    assert torch.allclose(sample3d(levels, uvw, wrap="clamp", lod=lod), want, atol=1e-14)
    # At an integer D = k > 0 the gradient in D is the derivative from below, v_k - v_(k-1) (DESIGN.md).
    d = torch.full((2, 7), 2.0, dtype=torch.float64, requires_grad=True)
    (gd,) = torch.autograd.grad(sample3d(vol, uvw, wrap="clamp", lod=d).sum(), d)
    assert torch.allclose(gd, (read[2] - read[1]).sum(1), atol=1e-14)


def test_lod_gradcheck_and_bad_input():
    g = torch.Generator().manual_seed(6)
    vol = torch.rand(1, 1, 4, 3, 2, generator=g, dtype=torch.float64, requires_grad=True)
    uvw = torch.rand(1, 2, 3, generator=g, dtype=torch.float64, requires_grad=True)
    lod = torch.tensor([[0.4, 1.3]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v, u, d: sample3d(v, u, lod=d), (vol, uvw, lod))
    with pytest.raises(ValueError, match=r"lod: expected a number or \[B, ...\] = \(1, 2\)"):
        sample3d(vol, uvw, lod=torch.zeros(1, 3, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"lod: expected None, a number or a tensor, got str"):
        sample3d(vol, uvw, lod="1")
    with pytest.raises(TypeError, match=r"volume: a list of levels needs lod"):
        sample3d([vol], uvw)


@pytest.mark.parametrize("wrap", ["repeat", "clamp", "mirror", "border"])
def test_a_volume_of_equal_slices_reads_like_the_2d_sampler(wrap):
    """Every slice the same texture: sample3d at (u, v, any w) is difftex.sample at (u, v), same wrap rules."""
    import difftex

    g = torch.Generator().manual_seed(7)
    tex = torch.rand(2, 3, 5, 6, generator=g, dtype=torch.float64)
    vol = tex.unsqueeze(2).expand(-1, -1, 4, -1, -1)
    uv = torch.rand(2, 4, 5, 2, generator=g, dtype=torch.float64) * 3 - 1
    w = torch.rand(2, 4, 5, 1, generator=g, dtype=torch.float64) * 0.75 + 0.125  # inside: border reads no zeros
    for filt, filt2d in (("linear", "bilinear"), ("nearest", "nearest")):
        got = sample3d(vol, torch.cat((uv, w), -1), filter=filt, wrap=(wrap, wrap, "clamp"), border_value=0.5)
        want = difftex.sample(tex, uv, filter=filt2d, wrap=wrap, border_value=0.5)
        assert torch.allclose(got, want, atol=1e-12), filt

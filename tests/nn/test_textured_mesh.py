"""TexturedMesh: the pipeline as an nn.Module."""
from pathlib import Path

import pytest
import torch

import difftex
from difftex import camera

DATA = Path(__file__).resolve().parents[2] / "data" / "spot"


@pytest.fixture(scope="module")
def spot():
    return difftex.load_mesh(DATA / "spot_triangulated.obj")


def _mvp(n=2, dtype=torch.float32):
    eye = torch.tensor([[2.0, 0.6, 2.0], [-1.5, 0.3, -2.5]], dtype=dtype)[:n]
    proj = camera.perspective(40.0, 1.0, 0.1, 100.0, degrees=True, dtype=dtype)
    return proj @ camera.look_at(eye, torch.zeros(n, 3, dtype=dtype), torch.tensor([0.0, 1.0, 0.0], dtype=dtype))


@pytest.mark.parametrize("filter", ["nearest", "bilinear", "bicubic", "trilinear", "anisotropic", "ewa"])
def test_constant_texture_renders_constant(spot, filter):
    color = torch.tensor([0.2, 0.5, 0.9])
    tex = color.view(3, 1, 1).expand(3, 16, 16).clone()
    model = difftex.TexturedMesh(spot, tex, filter=filter, background=0.25)
    img, mask = model(_mvp(), (48, 40))
    assert img.shape == (2, 3, 48, 40) and mask.shape == (2, 1, 48, 40)
    covered = mask.bool().expand_as(img)
    assert 0.1 < mask.mean() < 0.9
    expect = color.view(1, 3, 1, 1).expand_as(img)
    torch.testing.assert_close(img[covered], expect[covered], atol=1e-5, rtol=0)
    assert (img[~covered] == 0.25).all()


def test_mask_matches_rasterize_and_grad_reaches_seen_texels_only(spot):
    tex = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(0))
    model = difftex.TexturedMesh(spot, tex, filter="bilinear")
    frags = model.rasterize(_mvp(1), (32, 32))
    img, mask = model(frags=frags)
    assert torch.equal(mask[:, 0].bool(), frags.mask)
    img.sum().backward()
    g = model.texture.grad
    touched = (g.abs().sum(1) > 0).float().mean()
    # One 32x32 view sees part of spot's atlas: some texels, not all.
    assert 0.005 < touched < 0.6
    assert torch.isfinite(g).all()


def test_gradcheck_texture_and_uv_float64(spot):
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(2, 6, 6, generator=g, dtype=torch.float64)
    mesh = spot.to(dtype=torch.float64)
    model = difftex.TexturedMesh(mesh, tex, filter="trilinear", learn_uv=True).double()
    frags = model.rasterize(_mvp(1, torch.float64), (8, 8))
    assert frags.mask.any()
    base_uv = model.uv.detach().clone()
    # A uv shift shared by every vertex stands in for the 6450 uv entries,
    # which would make the numerical Jacobian slow: it exercises the same path.
    shift = torch.tensor([0.013, -0.021], dtype=torch.float64, requires_grad=True)
    texture = model.texture.detach().clone().requires_grad_()

    def fn(t, d):
        # Swap a plain tensor in for the Parameter so the graph runs through t.
        saved = model.texture
        del model.texture
        model.texture = t
        try:
            return model(frags=frags, uv=base_uv + d)[0]
        finally:
            del model.texture
            model.texture = saved

    assert torch.autograd.gradcheck(fn, (texture, shift), atol=1e-6)


def test_parameters_and_buffers(spot):
    m = difftex.TexturedMesh(spot, torch.rand(1, 3, 8, 8))
    assert [n for n, _ in m.named_parameters()] == ["texture"]
    m = difftex.TexturedMesh(spot, torch.rand(1, 3, 8, 8), learn_texture=False, learn_uv=True)
    assert [n for n, _ in m.named_parameters()] == ["uv"]
    assert "texture" in dict(m.named_buffers())


def test_bad_input(spot):
    with pytest.raises(TypeError, match="mesh: expected a difftex.Mesh"):
        difftex.TexturedMesh("spot.obj", torch.rand(3, 8, 8))
    with pytest.raises(ValueError, match=r"texture: expected 3-D or 4-D"):
        difftex.TexturedMesh(spot, torch.rand(8, 8))
    with pytest.raises(ValueError, match=r"texture: expected one texture \[1, C, H, W\], got shape \(2, 3, 8, 8\)"):
        difftex.TexturedMesh(spot, torch.rand(2, 3, 8, 8))
    m = difftex.TexturedMesh(spot, torch.rand(3, 8, 8))
    with pytest.raises(ValueError, match="forward: expected mvp and resolution"):
        m()
    with pytest.raises(ValueError, match=r"mvp: expected \[B, 4, 4\] or \[4, 4\], got shape \(2, 3, 3\)"):
        m(torch.rand(2, 3, 3), (8, 8))
    with pytest.raises(ValueError, match=r"uv: expected shape \(3225, 2\)"):
        m(_mvp(1), (8, 8), uv=torch.rand(10, 2))
    with pytest.raises(TypeError, match=r"uv: expected a float tensor \(3225, 2\).*got list"):
        m(_mvp(1), (8, 8), uv=[[0.5, 0.5]])


def test_bad_input_names_the_argument(spot):
    with pytest.raises(TypeError, match=r"background: expected a number, got str"):
        difftex.TexturedMesh(spot, torch.rand(3, 8, 8), background="white")
    with pytest.raises(ValueError, match=r"background: expected a finite number, got nan"):
        difftex.TexturedMesh(spot, torch.rand(3, 8, 8), background=float("nan"))
    # float16 used to reach the rasterizer as the positions' dtype and blame pos
    with pytest.raises(TypeError, match=r"texture: expected float32 or float64 .*dtype torch.float16"):
        difftex.TexturedMesh(spot, torch.rand(3, 8, 8).half())
    m = difftex.TexturedMesh(spot, torch.rand(3, 8, 8))
    # an int uv used to blame interpolate's attr
    with pytest.raises(TypeError, match=r"uv: expected a floating-point tensor .*\(3225, 2\).*dtype torch.int64"):
        m(_mvp(1), (8, 8), uv=torch.zeros(3225, 2, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"uv: expected dtype torch.float32 like the texture, got .*float64"):
        m(_mvp(1), (8, 8), uv=torch.zeros(3225, 2, dtype=torch.float64))


@pytest.mark.parametrize("filter", ["nearest", "bilinear", "bicubic", "trilinear", "nearest-mip", "anisotropic",
                                    "ewa", "auto"])
def test_no_covered_pixel_gives_zero_gradients(spot, filter):
    # The camera looks away from spot: no pixel covered. Every filter must give the
    # texture (and a learned uv) a zero gradient, not None (the native mip taps
    # reported "no texel read" as None, so trilinear / anisotropic left it None).
    model = difftex.TexturedMesh(spot, torch.rand(3, 8, 8), filter=filter, learn_uv=True, background=0.25)
    eye = torch.tensor([[2.0, 0.6, 2.0]])
    proj = camera.perspective(40.0, 1.0, 0.1, 100.0, degrees=True)
    mvp = proj @ camera.look_at(eye, 2 * eye, torch.tensor([0.0, 1.0, 0.0]))
    img, mask = model(mvp, (6, 5))
    assert not mask.any() and img.shape == (1, 3, 6, 5)
    assert (img == 0.25).all()
    img.sum().backward()
    for name in ("texture", "uv"):
        g = getattr(model, name).grad
        assert g is not None, name
        assert torch.equal(g, torch.zeros_like(g)), name


def test_resolution_that_cannot_fit_names_resolution(spot):
    # 30000^2 asked the allocator for tens of GB; the rasterizer's limit (16 GiB) names the resolution first.
    model = difftex.TexturedMesh(spot, torch.rand(3, 8, 8))
    with pytest.raises(ValueError, match=r"resolution 30000x30000 with batch 2 needs at least 93\.9 GiB"):
        model(_mvp(2), (30000, 30000))


def test_stochastic_draws_travel_with_the_state_dict(spot):
    tex = torch.rand(1, 3, 32, 32)
    a = difftex.TexturedMesh(spot, tex, filter="anisotropic", stochastic=1, seed=3)
    a(_mvp(), (24, 24))[0].sum().backward()  # advances a's generator
    b = difftex.TexturedMesh(spot, tex, filter="anisotropic", stochastic=1, seed=99)
    b.load_state_dict(a.state_dict())
    with torch.no_grad():
        x, y = a(_mvp(), (24, 24))[0], b(_mvp(), (24, 24))[0]
    assert torch.equal(x, y)
    # A fresh module of the same seed draws otherwise than one that has drawn before.
    fresh = difftex.TexturedMesh(spot, tex, filter="anisotropic", stochastic=1, seed=3)
    with torch.no_grad():
        assert not torch.equal(fresh(_mvp(), (24, 24))[0], x)


def test_decorrelated_stochastic_value_is_the_first_draw_and_gradient_another(spot):
    tex = torch.rand(1, 3, 32, 32)
    kw = dict(filter="trilinear", stochastic=1, seed=5)
    one = difftex.TexturedMesh(spot, tex, decorrelate=False, **kw)
    two = difftex.TexturedMesh(spot, tex, decorrelate=True, **kw)
    img1, img2 = one(_mvp(), (24, 24))[0], two(_mvp(), (24, 24))[0]
    assert torch.equal(img1, img2)  # the value: the same first draws
    img1.sum().backward()
    img2.sum().backward()
    g1, g2 = one.texture.grad, two.texture.grad
    assert g2.abs().sum() > 0 and not torch.equal(g1, g2)  # the gradient: a second, independent set of draws
    # The one check of sample's stochastic (difftex.texture.options.check_stochastic), the same messages.
    with pytest.raises(ValueError, match="stochastic: expected an int >= 0"):
        difftex.TexturedMesh(spot, tex, stochastic=-1)
    with pytest.raises(TypeError, match="stochastic: expected an int >= 0"):
        difftex.TexturedMesh(spot, tex, stochastic=1.5)
    with pytest.raises(ValueError, match="stochastic: filter 'sat' has no stochastic mode"):
        difftex.TexturedMesh(spot, tex, filter="sat", stochastic=1)
    assert difftex.TexturedMesh(spot, tex, stochastic=True).stochastic == 1

"""composite: the front-to-back alpha buffer; values, the opaque stop, gradients, and a learned alpha texture."""
from __future__ import annotations

import pytest
import torch

import difftex
from difftex import composite, interpolate, rasterize, sample
from tests.conftest import DEVICES


def _explicit(colors, alphas):
    out = torch.zeros_like(colors[0])
    for i in range(colors.shape[0]):
        t = torch.ones_like(alphas[0])
        for j in range(i):
            t = t * (1 - alphas[j])
        out = out + alphas[i] * t * colors[i]
    return out


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_values_match_the_formula(device, dtype):
    g = torch.Generator().manual_seed(0)
    colors = torch.rand(4, 2, 3, 5, 6, generator=g, dtype=dtype).to(device)
    alphas = torch.rand(4, 2, 1, 5, 6, generator=g, dtype=dtype).to(device)
    out, acc = composite(colors, alphas)
    assert out.dtype == dtype and out.shape == (2, 3, 5, 6) and acc.shape == (2, 1, 5, 6)
    tol = 1e-6 if dtype == torch.float32 else 1e-13
    assert torch.allclose(out, _explicit(colors, alphas), atol=tol)
    assert torch.allclose(acc, 1 - torch.prod(1 - alphas, 0), atol=tol)


def test_order_matters_as_the_seed_says():
    # a C_front + (1 - a) C_back differs from the swapped order.
    c = torch.tensor([1.0, 0.0]).view(2, 1, 1, 1, 1)
    a = torch.full((2, 1, 1, 1, 1), 0.25)
    front_first, _ = composite(c, a)
    back_first, _ = composite(c.flip(0), a)
    assert float(front_first) == pytest.approx(0.25)
    assert float(back_first) == pytest.approx(0.0 + 0.75 * 0.25)


def test_an_opaque_layer_stops_the_buffer():
    # Pixel 0 has an opaque first layer, pixel 1 does not.
    colors = torch.rand(3, 1, 2, 1, 2, dtype=torch.float64, requires_grad=True)
    alphas = torch.tensor([[1.0, 0.5], [0.7, 0.7], [0.3, 0.3]], dtype=torch.float64).view(3, 1, 1, 1, 2)
    alphas.requires_grad_(True)
    out, acc = composite(colors, alphas)
    assert torch.equal(out[..., 0], colors[0, ..., 0].detach())
    assert float(acc[..., 0].detach()) == 1.0
    out.sum().backward()
    # Behind the opaque layer: exactly zero gradient to colours and alphas.
    assert torch.equal(colors.grad[1:, ..., 0], torch.zeros_like(colors.grad[1:, ..., 0]))
    assert torch.equal(alphas.grad[1:, ..., 0], torch.zeros_like(alphas.grad[1:, ..., 0]))
    assert (colors.grad[1:, ..., 1] != 0).all() and (alphas.grad[1:, ..., 1] != 0).all()


def test_layers_behind_an_opaque_image_are_not_read():
    # Every pixel opaque after layer 0: layer 1 is never evaluated (NaN there would show otherwise).
    colors = torch.stack([torch.rand(1, 3, 4, 4), torch.full((1, 3, 4, 4), float("nan"))])
    alphas = torch.stack([torch.ones(1, 1, 4, 4), torch.full((1, 1, 4, 4), float("nan"))])
    out, acc = composite(colors, alphas)
    assert torch.equal(out, colors[0]) and torch.equal(acc, torch.ones(1, 1, 4, 4))


def test_gradcheck_float64():
    # Alphas inside (0, 1): at an alpha of exactly 1 the layers behind are not read, so the gradient there
    # omits them (test_opaque_alpha_gradient_does_not_read_behind) while a finite difference would see them.
    g = torch.Generator().manual_seed(1)
    colors = torch.rand(3, 2, 2, 3, 3, generator=g, dtype=torch.float64, requires_grad=True)
    alphas = (0.05 + 0.9 * torch.rand(3, 1, 1, 3, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(composite, (colors, alphas))


# --------------------------------------------------------------------------
# occluded layers are not read (issue 42, point 2): a NaN behind an opaque layer stays out


def _occluded_case(dtype: torch.dtype, behind: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Three layers [3, 1, 3, 2, 2]: pixel (0, 0) opaque in layer 0 with ``behind`` (NaN, inf, or a number) in
    every colour and alpha of layers 1 and 2; the other pixels translucent, finite (so no early stop)."""
    g = torch.Generator().manual_seed(3)
    colors = torch.rand(3, 1, 3, 2, 2, generator=g, dtype=torch.float64)
    alphas = 0.1 + 0.8 * torch.rand(3, 1, 1, 2, 2, generator=g, dtype=torch.float64)
    alphas[0, 0, 0, 0, 0] = 1.0
    colors[1:, 0, :, 0, 0] = behind
    alphas[1:, 0, 0, 0, 0] = behind
    return colors.to(dtype), alphas.to(dtype)


def _blend_and_grads(colors: torch.Tensor, alphas: torch.Tensor):
    """(color [1, 3, 2, 2], alpha [1, 1, 2, 2], d/dcolors, d/dalphas) of a fixed uneven loss."""
    colors = colors.clone().requires_grad_(True)
    alphas = alphas.clone().requires_grad_(True)
    out, acc = composite(colors, alphas)
    w = torch.arange(1, out.numel() + 1, dtype=out.dtype).view_as(out) / out.numel()
    ((out * w).sum() + (acc * 0.5).sum()).backward()
    return out.detach(), acc.detach(), colors.grad, alphas.grad


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("behind", [float("nan"), float("inf"), -float("inf")], ids=["nan", "inf", "-inf"])
def test_nan_behind_an_opaque_layer_stays_out(dtype, behind):
    out, acc, gc, ga = _blend_and_grads(*_occluded_case(dtype, behind))
    # The same layers with ordinary numbers behind: the occluded layers are not read, so every value and
    # gradient is bit-identical (with reading-and-multiplying-by-0 the opaque pixel was NaN, and its gradients).
    ref = _blend_and_grads(*_occluded_case(dtype, 0.5))
    for got, want in zip((out, acc, gc, ga), ref):
        assert torch.isfinite(got).all()
        assert torch.equal(got, want)
    colors, _ = _occluded_case(dtype, behind)
    assert torch.equal(out[0, :, 0, 0], colors[0, 0, :, 0, 0])  # the opaque layer alone
    assert float(acc[0, 0, 0, 0]) == 1.0
    # Behind the opaque layer: exactly zero gradient, not 0 * NaN.
    assert torch.equal(gc[1:, 0, :, 0, 0], torch.zeros(2, 3, dtype=dtype))
    assert torch.equal(ga[1:, 0, :, 0, 0], torch.zeros(2, 1, dtype=dtype))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_nan_in_a_visible_layer_stays_in_its_pixel(dtype):
    # Pixel (1, 1): layer 1 is seen through a translucent layer 0 and has a NaN colour and alpha.
    colors, alphas = _occluded_case(dtype, 0.5)
    colors[1, 0, 1, 1, 1] = float("nan")
    alphas[1, 0, 0, 1, 1] = float("nan")
    out, acc, gc, ga = _blend_and_grads(colors, alphas)
    ref = _blend_and_grads(*_occluded_case(dtype, 0.5))
    nan_pixel = torch.zeros(2, 2, dtype=torch.bool)
    nan_pixel[1, 1] = True
    # The value is NaN there (every channel: the alpha is NaN), and only there.
    assert torch.isnan(out[0, :, 1, 1]).all() and torch.isnan(acc[0, 0, 1, 1])
    for got, want in zip((out, acc, gc, ga), ref):
        assert not torch.isnan(got[..., ~nan_pixel]).any()
        assert torch.equal(got[..., ~nan_pixel], want[..., ~nan_pixel])
    # Its gradients are NaN where the NaN meets them: the alphas of the layers in front, whose gradient
    # reads the layers behind them.
    assert torch.isnan(ga[0, 0, 0, 1, 1])


def test_opaque_alpha_gradient_does_not_read_behind():
    # d out / d a_0 at an alpha of exactly 1 is c_0 (times the output gradient): the layers behind are not
    # read. Where layer 0 is opaque in every pixel they are not even evaluated (the early stop), and one
    # opaque pixel among translucent ones now gives the same gradient (before: c_0 - a_1 c_1 - ...).
    g = torch.Generator().manual_seed(4)
    colors = torch.rand(2, 1, 3, 1, 2, generator=g, dtype=torch.float64)
    alphas = torch.tensor([1.0, 0.6, 0.7, 0.8], dtype=torch.float64).view(2, 1, 1, 1, 2)
    _, _, gc, ga = _blend_and_grads(colors, alphas)
    _, _, gc_all, ga_all = _blend_and_grads(colors, torch.ones_like(alphas))
    w = torch.tensor([1.0, 3.0, 5.0], dtype=torch.float64) / 6  # the loss weights of pixel 0's channels
    assert float(ga[0, 0, 0, 0, 0]) == pytest.approx(float((colors[0, 0, :, 0, 0] * w).sum()) + 0.5, abs=1e-15)
    assert torch.equal(ga[0, ..., 0], ga_all[0, ..., 0]) and torch.equal(gc[:, ..., 0], gc_all[:, ..., 0])
    assert torch.equal(ga[1, ..., 0], torch.zeros(1, 1, 1, dtype=torch.float64))


def _peeled_scene(dtype: torch.dtype, hidden: bool):
    """A front quad (opaque, finite RGBA) and, with ``hidden``, behind it a sliver triangle and a zero-area one
    whose vertex attributes are NaN (a degenerate triangle's shading, say); rendered by depth_peel (2 layers),
    interpolate and composite at 16 x 16. Returns (image, alpha, d/dattr, d/dpos) of a fixed loss."""
    pos = torch.tensor([[-0.8, 0.8, -0.5, 1], [-0.8, -0.8, -0.5, 1], [0.8, -0.8, -0.5, 1], [0.8, 0.8, -0.5, 1],
                        [-0.6, 0.1, 0.5, 1], [0.6, 0.05, 0.5, 1], [0.6, 0.18, 0.5, 1],  # the sliver
                        [-0.5, -0.3, 0.6, 1], [0.0, -0.3, 0.6, 1], [0.5, -0.3, 0.6, 1]],  # collinear
                       dtype=dtype, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]] + ([[4, 5, 6], [7, 8, 9]] if hidden else []))
    g = torch.Generator().manual_seed(5)
    attr = torch.rand(10, 4, generator=g, dtype=torch.float64).to(dtype)
    attr[:4, 3] = 1.0  # the quad is opaque
    attr[4:] = float("nan")
    attr.requires_grad_(True)
    layers = difftex.depth_peel(pos[None], faces, (16, 16), 2)
    if hidden:  # the sliver is peeled (layer 1), so its NaN reaches composite
        assert int((layers[1].tri_id == 2).sum()) > 0 and int((layers[0].tri_id >= 2).sum()) == 0
    cols, alps = [], []
    for fr in layers:
        v = interpolate(attr, faces, fr).permute(0, 3, 1, 2)  # [1, 4, 16, 16]
        cols.append(v[:, :3])
        alps.append(v[:, 3:] * fr.mask[:, None].to(dtype))
    out, acc = composite(torch.stack(cols), torch.stack(alps))
    w = torch.linspace(0.5, 1.5, out.numel(), dtype=dtype).view_as(out)
    ((out * w).sum() + acc.sum()).backward()
    return out.detach(), acc.detach(), attr.grad, pos.grad


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_peel_interpolate_composite_ignores_a_hidden_nan_triangle(dtype):
    out, acc, g_attr, g_pos = _peeled_scene(dtype, hidden=True)
    ref_out, ref_acc, ref_attr, ref_pos = _peeled_scene(dtype, hidden=False)
    for got in (out, acc, g_attr, g_pos):
        assert torch.isfinite(got).all()
    # The hidden triangles change nothing: the image and the quad's gradients are those of the quad alone
    # (to rounding: the peeled layer 1 holds the sliver's fragments instead of background there).
    tol = dict(rtol=1e-6, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-13, atol=1e-13)
    assert torch.allclose(out, ref_out, **tol) and torch.allclose(acc, ref_acc, **tol)
    assert torch.allclose(g_attr[:4], ref_attr[:4], **tol) and torch.allclose(g_pos[:4], ref_pos[:4], **tol)
    # and get exactly zero gradient themselves, to their attributes and (through interpolate's barycentrics)
    # to their positions.
    assert torch.equal(g_attr[4:], torch.zeros(6, 4, dtype=dtype))
    assert torch.equal(g_pos[4:], torch.zeros(6, 4, dtype=dtype))


def test_bad_input_raises():
    c, a = torch.rand(2, 1, 3, 4, 4), torch.rand(2, 1, 1, 4, 4)
    with pytest.raises(ValueError, match=r"colors: expected 5-D \[L, B, C, H, W\]"):
        composite(c[0], a)
    with pytest.raises(TypeError, match="alphas: expected a floating-point tensor"):
        composite(c, a.long())
    with pytest.raises(ValueError, match="alphas: expected one channel"):
        composite(c, a.expand(2, 1, 3, 4, 4))
    with pytest.raises(ValueError, match="alphas: expected 2 layers like colors"):
        composite(c, a[:1])
    with pytest.raises(ValueError, match=r"alphas: expected the image size \(4, 4\)"):
        composite(c, a[..., :3])
    with pytest.raises(ValueError, match="must broadcast"):
        composite(c.expand(2, 2, 3, 4, 4), a.expand(2, 3, 1, 4, 4))
    assert difftex.composite is composite


# --------------------------------------------------------------------------
# texture alpha through the compositor: learning a cut-out


def _quad(z: float, half: float) -> torch.Tensor:
    """Clip-space corners (w = 1) of a screen-aligned square at NDC depth z; uv (0, 0) at the top left."""
    return torch.tensor([[-half, half, z, 1], [-half, -half, z, 1], [half, -half, z, 1], [half, half, z, 1]])


QUAD_FACES = torch.tensor([[0, 1, 2], [0, 2, 3]])
QUAD_UV = torch.tensor([[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]])


def _render(front_rgba: torch.Tensor, back_rgba: torch.Tensor, res: int = 32) -> torch.Tensor:
    """Two textured quads, an RGBA one in front of another, composited front to back over black."""
    # The quads do not overlap in depth, so each is one layer, nearest
    # first; one rasterize call renders both as a batch of two.
    # TODO(issue 16): take the layers from difftex.depth_peel once it lands.
    quads = torch.stack([_quad(-0.3, 0.7), _quad(0.4, 0.9)])
    frags = rasterize(quads, QUAD_FACES, (res, res))
    uv = interpolate(QUAD_UV, QUAD_FACES, frags)
    texel = sample(torch.cat([front_rgba, back_rgba]), uv, filter="bilinear", wrap="clamp")  # [2, 4, res, res]
    alpha = texel[:, 3:4] * frags.mask.to(texel.dtype)[:, None]
    out, _ = composite(texel[:, None, :3], alpha[:, None])
    return out


def test_fit_learns_an_alpha_texture():
    size = 12
    yy, xx = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    disk = (((xx - size / 2) ** 2 + (yy - size / 2) ** 2) < (size * 0.35) ** 2).float()
    true_alpha = (0.15 + 0.8 * disk)[None, None]  # a cut-out with a faint surround
    front_rgb = torch.tensor([0.95, 0.25, 0.1]).view(1, 3, 1, 1).expand(1, 3, size, size)
    checks = ((torch.arange(size)[:, None] // 3 + torch.arange(size)[None] // 3) % 2).float()
    back = torch.cat([(0.1 + 0.8 * checks)[None, None].expand(1, 3, size, size), torch.ones(1, 1, size, size)], 1)
    target = _render(torch.cat([front_rgb, true_alpha], 1), back)

    logit = torch.zeros(1, 1, size, size, requires_grad=True)  # alpha 0.5 everywhere
    opt = torch.optim.Adam([logit], lr=0.1)
    err0 = float((torch.sigmoid(logit.detach()) - true_alpha).abs().mean())
    for _ in range(80):
        img = _render(torch.cat([front_rgb, torch.sigmoid(logit)], 1), back)
        loss = torch.mean((img - target) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
    err = float((torch.sigmoid(logit.detach()) - true_alpha).abs().mean())
    print(err0, err)
    assert err0 > 0.3
    assert err < 0.02  # measured 0.006 (the sigmoid saturates slowly near the opaque 0.95)

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
    g = torch.Generator().manual_seed(1)
    colors = torch.rand(3, 2, 2, 3, 3, generator=g, dtype=torch.float64, requires_grad=True)
    alphas = torch.rand(3, 1, 1, 3, 3, generator=g, dtype=torch.float64)
    alphas[0, 0, 0, 0, 0] = 1.0  # one opaque pixel (the stop) among the rest
    alphas.requires_grad_(True)
    assert torch.autograd.gradcheck(composite, (colors, alphas))


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

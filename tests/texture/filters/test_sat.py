"""The "sat" filter (difftex/texture/filters/sat.py): exact box averages, precision, gradients, memory."""
from __future__ import annotations

import math

import pytest
import torch

import difftex
from difftex.texture.filters import sat

f64 = torch.float64
WRAPS = ("repeat", "clamp", "mirror", "border")
BORDER = -0.75


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _texel(i: int, n: int, mode: str) -> int | None:
    """The wrap rule written out (None: the border constant)."""
    if mode == "repeat":
        return i % n
    if mode == "mirror":
        r = i % (2 * n)
        return r if r < n else 2 * n - 1 - r
    if mode == "clamp":
        return min(max(i, 0), n - 1)
    return i if 0 <= i < n else None


def _axis(lo: float, hi: float, n: int, mode: str) -> tuple[torch.Tensor, list[int | None]]:
    """Per texel index met by [lo, hi]: its covered length and the texel it reads."""
    idx = range(math.floor(lo), math.ceil(hi))
    cover = torch.tensor([min(hi, i + 1) - max(lo, i) for i in idx], dtype=f64)
    return cover, [_texel(i, n, mode) for i in idx]


def direct_box_mean(tex: torch.Tensor, x0: float, x1: float, y0: float, y1: float, wrap_u: str, wrap_v: str,
                    border: float = BORDER) -> torch.Tensor:
    """Mean of the texel-constant texture [C, H, W] over [x0, x1] x [y0, y1] (texel units), texel by texel."""
    C, H, W = tex.shape
    ox, tx = _axis(x0, x1, W, wrap_u)
    oy, ty = _axis(y0, y1, H, wrap_v)
    inside_x = torch.tensor([t is not None for t in tx])
    inside_y = torch.tensor([t is not None for t in ty])
    vals = tex.double()[:, [t or 0 for t in ty]][:, :, [t or 0 for t in tx]]  # [C, ny, nx]
    inside = inside_y[:, None] & inside_x[None, :]
    vals = torch.where(inside, vals, torch.tensor(border, dtype=f64))
    return torch.einsum("y,x,cyx->c", oy, ox, vals) / ((x1 - x0) * (y1 - y0))


def _boxes(n: int, H: int, W: int, wrap: tuple[str, str], seed: int):
    """Random centres in [-1.5, 2.5] (crossing every edge) and box sides from 1 texel to a period, as the
    uv, uv_dx, uv_dy that ask for them: the box is the footprint's axis-aligned bounding box."""
    g = _gen(seed)
    uv = torch.rand(1, 1, n, 2, generator=g, dtype=f64) * 4 - 1.5
    period = torch.tensor([2.0 * W if wrap[0] == "mirror" else W, 2.0 * H if wrap[1] == "mirror" else H], dtype=f64)
    side = torch.exp(torch.rand(1, 1, n, 2, generator=g, dtype=f64) * torch.log(period))  # texels, in [1, period]
    # A parallelogram with that bounding box: split each side between the two vectors, with signs.
    t = torch.rand(1, 1, n, 2, generator=g, dtype=f64)
    sign = torch.randint(0, 2, (2, 1, 1, n, 2), generator=g).to(f64) * 2 - 1
    size = torch.tensor([W, H], dtype=f64)
    dx = sign[0] * side * t / size
    dy = sign[1] * side * (1 - t) / size
    return uv, dx, dy, side


@pytest.mark.parametrize("wrap", [("repeat", "repeat"), ("mirror", "mirror"), ("clamp", "clamp"),
                                  ("border", "border"), ("repeat", "border"), ("mirror", "clamp")])
def test_exact_box_averages_against_a_direct_mean(wrap):
    H, W = 7, 11
    tex = torch.rand(1, 2, H, W, dtype=f64, generator=_gen(1))
    uv, dx, dy, side = _boxes(40, H, W, wrap, seed=2)
    out = difftex.sample(tex, uv, filter="sat", wrap=wrap, border_value=BORDER, uv_dx=dx, uv_dy=dy)[0, :, 0]
    for k in range(uv.shape[2]):
        cx, cy = uv[0, 0, k, 0].item() * W, uv[0, 0, k, 1].item() * H
        hx, hy = side[0, 0, k, 0].item() / 2, side[0, 0, k, 1].item() / 2
        want = direct_box_mean(tex[0], cx - hx, cx + hx, cy - hy, cy + hy, *wrap)
        torch.testing.assert_close(out[:, k], want, atol=1e-12, rtol=0, msg=f"box {k}")


def test_box_sides_floor_at_one_texel_and_cap_at_one_period():
    H, W = 6, 5
    tex = torch.rand(1, 3, H, W, dtype=f64, generator=_gen(3))
    uv = torch.rand(1, 2, 3, 2, dtype=f64, generator=_gen(4)) * 3 - 1
    tiny = torch.full_like(uv, 1e-9)
    for wrap in WRAPS:  # below a texel: the one-texel box average, which is bilinear interpolation
        a = difftex.sample(tex, uv, filter="sat", wrap=wrap, border_value=BORDER, uv_dx=tiny, uv_dy=tiny)
        b = difftex.sample(tex, uv, filter="bilinear", wrap=wrap, border_value=BORDER)
        torch.testing.assert_close(a, b, atol=1e-13, rtol=0, msg=wrap)
    huge = torch.full_like(uv, 1e6)
    for wrap in ("repeat", "mirror"):  # one period: the texture's mean, wherever the centre
        out = difftex.sample(tex, uv, filter="sat", wrap=wrap, uv_dx=huge, uv_dy=-huge)
        torch.testing.assert_close(out, tex.mean((-1, -2), keepdim=True).expand_as(out), atol=1e-13, rtol=0)
    # lod_bias scales the box: a 2 x 2 texel footprint with bias 1 is the 4 x 4 box.
    two = torch.tensor([2 / W, 0.0], dtype=f64).expand_as(uv)
    a = difftex.sample(tex, uv, filter="sat", uv_dx=two, uv_dy=two.flip(-1) * W / H, lod_bias=1.0)
    b = difftex.sample(tex, uv, filter="sat", uv_dx=2 * two, uv_dy=2 * two.flip(-1) * W / H)
    torch.testing.assert_close(a, b, atol=1e-13, rtol=0)


def test_a_4096_texture_keeps_float32_precision():
    # The table is float64: a float32 table's sums reach 8e6 here, where its ulp (0.5) wipes out a small box.
    N = 4096
    tex = torch.rand(1, 1, N, N, generator=_gen(5))
    g = _gen(6)
    n = 48
    centre = torch.rand(n, 2, generator=g, dtype=f64) * N
    centre[:8] = N - torch.rand(8, 2, generator=g, dtype=f64) * 2  # far corner: the largest sums
    side = torch.cat([1 + torch.rand(n - 8, 2, generator=g, dtype=f64) * 3, 200 + torch.rand(8, 2, generator=g,
                                                                                           dtype=f64) * 800])
    uv = (centre / N).float().view(1, 1, n, 2)
    dx = torch.stack([side[:, 0] / N, torch.zeros(n, dtype=f64)], -1).float().view(1, 1, n, 2)
    dy = torch.stack([torch.zeros(n, dtype=f64), side[:, 1] / N], -1).float().view(1, 1, n, 2)
    out = difftex.sample(tex, uv, filter="sat", wrap="clamp", uv_dx=dx, uv_dy=dy)[0, 0, 0]
    t64 = tex[0, 0].double()
    c = uv[0, 0].double() * N  # the float32 inputs, as the filter sees them
    h = torch.stack([dx[0, 0, :, 0], dy[0, 0, :, 1]], -1).double() * N / 2
    for k in range(n):
        want = direct_box_mean(t64.unsqueeze(0), c[k, 0] - h[k, 0], c[k, 0] + h[k, 0], c[k, 1] - h[k, 1],
                               c[k, 1] + h[k, 1], "clamp", "clamp")
        assert abs(out[k].item() - want.item()) <= 3e-7, (k, out[k].item(), want.item())
    # The same box sums from a float32 table would be off by far more than the float64 table's 3e-7.
    S32 = torch.nn.functional.pad(tex[0, 0].cumsum(0).cumsum(1), (1, 0, 1, 0))
    i = c[:8].floor().long().clamp(1, N - 1)
    box = S32[i[:, 1] + 1, i[:, 0] + 1] - S32[i[:, 1], i[:, 0] + 1] - S32[i[:, 1] + 1, i[:, 0]] + S32[i[:, 1], i[:, 0]]
    assert (box.double() - t64[i[:, 1], i[:, 0]]).abs().max() > 1e-2


@pytest.mark.parametrize("wrap", WRAPS + (("mirror", "border"), ("clamp", "repeat")))
def test_gradcheck_texture_uv_derivatives_and_bias(wrap):
    g = _gen(7)
    tex = torch.rand(1, 2, 6, 9, dtype=f64, generator=g, requires_grad=True)
    uv = (torch.rand(1, 2, 4, 2, generator=g, dtype=f64) * 3 - 1).requires_grad_()
    dx = (torch.randn(1, 2, 4, 2, generator=g, dtype=f64) * 0.3).requires_grad_()
    dy = (torch.randn(1, 2, 4, 2, generator=g, dtype=f64) * 0.2).requires_grad_()
    bias = (torch.randn(1, 2, 4, dtype=f64, generator=g) * 0.5).requires_grad_()
    fn = lambda t, u, a, b, s: difftex.sample(t, u, filter="sat", wrap=wrap, border_value=BORDER, uv_dx=a,
                                               uv_dy=b, lod_bias=s)
    assert torch.autograd.gradcheck(fn, (tex, uv, dx, dy, bias), atol=1e-7)


def test_double_backward():
    # The backward is differentiable too: create_graph runs the torch reference of the box sums.
    g = _gen(17)
    tex = torch.rand(1, 1, 3, 4, dtype=f64, generator=g, requires_grad=True)
    uv = (torch.rand(1, 1, 2, 2, generator=g, dtype=f64) * 3 - 1).requires_grad_()
    dx = (torch.randn(1, 1, 2, 2, generator=g, dtype=f64) * 0.4).requires_grad_()
    dy = (torch.randn(1, 1, 2, 2, generator=g, dtype=f64) * 0.3).requires_grad_()
    fn = lambda t, u, a, b: difftex.sample(t, u, filter="sat", wrap=("mirror", "border"), border_value=BORDER,
                                           uv_dx=a, uv_dy=b)
    assert torch.autograd.gradgradcheck(fn, (tex, uv, dx, dy), atol=1e-6)


def test_the_backward_keeps_no_table():
    # What autograd saves for the backward: the texture (by reference) and [M, K] positions and coefficients,
    # never the (H + 1) x (W + 1) float64 table, which is rebuilt when a position gradient needs it.
    tex = torch.rand(1, 3, 256, 256, requires_grad=True)
    uv = torch.rand(1, 8, 8, 2, requires_grad=True)
    d = torch.full((1, 8, 8, 2), 0.02, requires_grad=True)
    saved: list[torch.Tensor] = []

    def pack(t):
        saved.append(t)
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = difftex.sample(tex, uv, filter="sat", uv_dx=d, uv_dy=d)
    biggest = max(t.numel() * t.element_size() for t in saved if t.data_ptr() != tex.data_ptr())
    table = 257 * 257 * 3 * 8
    assert biggest < table / 50, (biggest, table)
    out.sum().backward()
    # Every output weighs its texels by a box of positive weights summing to one.
    torch.testing.assert_close(tex.grad.sum(), torch.tensor(float(out.numel())), rtol=1e-5, atol=0)
    assert tex.grad.min() >= -1e-6


def test_custom_backward_matches_the_reference_autograd():
    g = _gen(8)
    tex = torch.rand(1, 2, 5, 7, dtype=f64, generator=g, requires_grad=True)
    M = 30
    pu = (torch.rand(M, 3, generator=g, dtype=f64) * 7).requires_grad_()
    pv = (torch.rand(M, 2, generator=g, dtype=f64) * 5).requires_grad_()
    cu = torch.randn(M, 3, generator=g, dtype=f64, requires_grad=True)
    cv = torch.randn(M, 2, generator=g, dtype=f64, requires_grad=True)
    w = torch.randn(2, M, generator=g, dtype=f64)
    a = sat._BoxSums.apply(tex, pu, cu, pv, cv)
    b = sat.box_sums_reference(tex, pu, cu, pv, cv)
    torch.testing.assert_close(a, b, atol=1e-13, rtol=0)
    ga = torch.autograd.grad((a * w).sum(), (tex, pu, cu, pv, cv))
    gb = torch.autograd.grad((b * w).sum(), (tex, pu, cu, pv, cv))
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, atol=1e-12, rtol=0)
    # The texture's gradient alone takes the path that rebuilds no table.
    g_tex, = torch.autograd.grad((sat._BoxSums.apply(tex, *(x.detach() for x in (pu, cu, pv, cv))) * w).sum(), tex)
    torch.testing.assert_close(g_tex, gb[0], atol=1e-12, rtol=0)
    # The table's ends and integer positions read the same values (there G_ext has a kink: no gradient compared).
    with torch.no_grad():
        pu[:6, 0] = torch.tensor([0.0, 7.0, 3.0, 0.0, 7.0, 1.0], dtype=f64)
        pv[:4, 1] = torch.tensor([5.0, 0.0, 2.0, 5.0], dtype=f64)
    torch.testing.assert_close(sat._BoxSums.apply(tex, pu, cu, pv, cv), sat.box_sums_reference(tex, pu, cu, pv, cv),
                               atol=1e-13, rtol=0)


def test_batches_and_dtypes():
    tex = torch.rand(2, 3, 10, 13, dtype=f64, generator=_gen(9))
    g = _gen(10)
    uv = torch.rand(2, 3, 5, 2, generator=g, dtype=f64) * 3 - 1
    dx, dy = (torch.randn(2, 3, 5, 2, generator=g, dtype=f64) * 0.3 for _ in range(2))
    out = difftex.sample(tex, uv, filter="sat", wrap="mirror", uv_dx=dx, uv_dy=dy)
    for b in range(2):
        one = difftex.sample(tex[b:b + 1], uv[b:b + 1], filter="sat", wrap="mirror", uv_dx=dx[b:b + 1],
                             uv_dy=dy[b:b + 1])
        torch.testing.assert_close(out[b:b + 1], one, atol=1e-14, rtol=0)
    shared = difftex.sample(tex[:1], uv, filter="sat", wrap="mirror", uv_dx=dx, uv_dy=dy)
    torch.testing.assert_close(shared[:1], out[:1], atol=1e-14, rtol=0)
    out32 = difftex.sample(tex.float(), uv.float(), filter="sat", wrap="mirror", uv_dx=dx.float(), uv_dy=dy.float())
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), out, atol=2e-6, rtol=0)


def test_large_uv_and_nan():
    tex = torch.rand(1, 2, 8, 8, generator=_gen(11))
    uv = torch.rand(1, 2, 3, 2, generator=_gen(12))
    d = torch.full_like(uv, 0.3)
    for wrap in WRAPS:  # float32 uv 1e4 periods away: the period is dropped before the texel coordinates form
        far = uv + (1e4 if wrap in ("repeat", "mirror") else 0.0)
        a = difftex.sample(tex, far, filter="sat", wrap=wrap, uv_dx=d, uv_dy=d)
        b = difftex.sample(tex.double(), far.double(), filter="sat", wrap=wrap, uv_dx=d.double(), uv_dy=d.double())
        torch.testing.assert_close(a.double(), b, atol=1e-6, rtol=0)
    # Boxes far outside a clamped texture: the edge texels, no huge coordinates.
    out = difftex.sample(tex, torch.full_like(uv, -1e30), filter="sat", wrap="clamp", uv_dx=d, uv_dy=d)
    torch.testing.assert_close(out, tex[:, :, :1, :1].expand_as(out), atol=1e-6, rtol=0)
    bad = uv.clone().requires_grad_()
    t = tex.clone().requires_grad_()
    with torch.no_grad():
        bad[0, 1, 2, 1] = float("nan")
    out = difftex.sample(t, bad, filter="sat", uv_dx=d, uv_dy=d)
    assert torch.isnan(out[0, :, 1, 2]).all() and torch.isfinite(out[0, :, 0]).all()
    torch.where(torch.isnan(out), 0.0, out).sum().backward()
    assert torch.isfinite(t.grad).all() and torch.isfinite(bad.grad).all()


def test_bad_input():
    tex = torch.rand(1, 1, 4, 4)
    uv = torch.rand(1, 2, 2, 2)
    with pytest.raises(ValueError, match=r"uv_dy: required by filter 'sat'"):
        difftex.sample(tex, uv, filter="sat", uv_dx=uv)
    with pytest.raises(TypeError, match=r"uv_dx: expected dtype torch.float32 like texture"):
        difftex.sample(tex, uv, filter="sat", uv_dx=uv.double(), uv_dy=uv)
    with pytest.raises(ValueError, match=r"filter: 'sat' is not supported by cubemap"):
        difftex.envmap.cubemap(torch.rand(1, 6, 1, 4, 4), torch.randn(1, 2, 2, 3), filter="sat",
                               dirs_dx=torch.zeros(1, 2, 2, 3), dirs_dy=torch.zeros(1, 2, 2, 3))

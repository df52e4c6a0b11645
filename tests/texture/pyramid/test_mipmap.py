"""difftex.mipmap: level sizes, values against references, the exact adjoint, bad input."""
from __future__ import annotations

from fractions import Fraction

import pytest
import torch
import torch.nn.functional as F

import difftex
from difftex.texture.pyramid.mipmap import Mipmap, level_count, level_size, mipmap


def _box_matrix(n: int, dtype=torch.float64) -> torch.Tensor:
    """Independent reference for one axis: output j averages [j n/m, (j+1) n/m) of the source, m = ceil(n/2)."""
    m = (n + 1) // 2
    A = torch.zeros(m, n, dtype=dtype)
    width = Fraction(n, m)
    for j in range(m):
        lo, hi = j * width, (j + 1) * width
        for i in range(n):
            overlap = min(hi, i + 1) - max(lo, i)
            if overlap > 0:
                A[j, i] = float(overlap / width)
    return A


def _reference_pyramid(x: torch.Tensor) -> list[torch.Tensor]:
    levels = [x]
    while max(levels[-1].shape[-2:]) > 1:
        y = levels[-1]
        H, W = y.shape[-2:]
        levels.append(torch.einsum("mh,bchw,nw->bcmn", _box_matrix(H, y.dtype), y, _box_matrix(W, y.dtype)))
    return levels


@pytest.mark.parametrize("shape", [(1, 3, 16, 16), (2, 1, 8, 32), (1, 2, 64, 4)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_even_levels_equal_avg_pool(shape, dtype):
    x = torch.rand(shape, dtype=dtype, generator=torch.Generator().manual_seed(0))
    m = mipmap(x)
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    for k in range(1, len(m)):
        prev = m[k - 1]
        if prev.shape[-2] % 2 == 0 and prev.shape[-1] % 2 == 0:
            torch.testing.assert_close(m[k], F.avg_pool2d(prev, 2), atol=tol, rtol=0)
        assert m[k].dtype == dtype


@pytest.mark.parametrize("hw", [(7, 5), (9, 16), (1, 13), (13, 1), (1, 1), (6, 10), (33, 17)])
def test_sizes_and_values_match_reference(hw):
    H, W = hw
    x = torch.rand(2, 2, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    m = mipmap(x)
    ref = _reference_pyramid(x)
    assert len(m) == level_count(H, W) == len(ref)
    for k, (a, b) in enumerate(zip(m, ref)):
        assert tuple(a.shape[-2:]) == level_size(H, W, k) == (-(-H // 2 ** k), -(-W // 2 ** k))
        torch.testing.assert_close(a, b, atol=1e-14, rtol=0)
    assert m[-1].shape[-2:] == (1, 1)
    # Level 0 is the texture (a view of it when an even chain follows).
    assert m[0].data_ptr() == x.data_ptr() and m[0].shape == x.shape


@pytest.mark.parametrize("hw", [(7, 5), (16, 16), (9, 4), (1, 11)])
def test_adjoint_is_exact(hw):
    """Gradient of a random functional of all levels == autograd through the dense reference construction."""
    H, W = hw
    g = torch.Generator().manual_seed(2)
    x = torch.rand(1, 3, H, W, dtype=torch.float64, generator=g, requires_grad=True)
    xr = x.detach().clone().requires_grad_(True)
    m = mipmap(x)
    weights = [torch.randn(lev.shape, dtype=torch.float64, generator=g) for lev in m]
    sum((lev * w).sum() for lev, w in zip(m, weights)).backward()
    sum((lev * w).sum() for lev, w in zip(_reference_pyramid(xr), weights)).backward()
    torch.testing.assert_close(x.grad, xr.grad, atol=1e-13, rtol=0)


@pytest.mark.parametrize("hw", [(7, 7), (5, 9), (1, 15), (15, 2), (1023, 3)])
def test_odd_level_keeps_mean_and_every_texel_its_share(hw):
    H, W = hw
    x = torch.rand(1, 1, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(3), requires_grad=True)
    m = mipmap(x)
    for lev in m:
        torch.testing.assert_close(lev.mean(), x.mean(), atol=1e-13, rtol=0)
    # d(sum of level 1)/d(texel) is the total weight each source texel gives
    # to level 1: equal for all texels, (h1 / H) * (w1 / W).
    m[1].sum().backward()
    h1, w1 = m[1].shape[-2:]
    torch.testing.assert_close(x.grad, torch.full_like(x, h1 * w1 / (H * W)), atol=1e-14, rtol=0)


def test_gradcheck_and_double_backward():
    x = torch.rand(1, 2, 7, 6, dtype=torch.float64, requires_grad=True)
    fn = lambda t: tuple(mipmap(t).levels[1:])
    assert torch.autograd.gradcheck(fn, (x,))
    assert torch.autograd.gradgradcheck(fn, (x,))
    y = torch.rand(1, 1, 8, 8, dtype=torch.float64, requires_grad=True)  # the hand-written even path
    assert torch.autograd.gradcheck(fn, (y,))
    assert torch.autograd.gradgradcheck(fn, (y,))
    # Every level used, level 0 too (its gradient joins the chain's adjoint),
    # and an even chain (12x8 -> 6x4 -> 3x2) followed by odd steps.
    every = lambda t: tuple(2 * lev for lev in mipmap(t).levels)
    z = torch.rand(2, 1, 12, 8, dtype=torch.float64, requires_grad=True)
    for t in (y, z):
        assert torch.autograd.gradcheck(every, (t,))
        assert torch.autograd.gradgradcheck(every, (t,))


def test_max_levels_and_batch():
    x = torch.rand(3, 2, 20, 12)
    assert len(mipmap(x)) == 6  # 20x12, 10x6, 5x3, 3x2, 2x1, 1x1
    m = mipmap(x, max_levels=3)
    assert [tuple(t.shape) for t in m] == [(3, 2, 20, 12), (3, 2, 10, 6), (3, 2, 5, 3)]
    for b in range(3):  # batch items are independent
        torch.testing.assert_close(mipmap(x[b:b + 1])[4], mipmap(x)[4][b:b + 1])
    assert len(mipmap(m)) == 3 and len(mipmap(m, max_levels=2)) == 2
    assert "5x3" in repr(m)


def test_supplied_levels_get_their_own_gradient():
    g = torch.Generator().manual_seed(4)
    levels = [torch.rand(1, 1, 4, 4, generator=g, dtype=torch.float64, requires_grad=True),
              torch.rand(1, 1, 2, 2, generator=g, dtype=torch.float64, requires_grad=True),
              torch.rand(1, 1, 1, 1, generator=g, dtype=torch.float64, requires_grad=True)]
    m = mipmap(levels)
    assert all(a is b for a, b in zip(m, levels))
    (m[1].sum() * 2).backward()
    assert levels[0].grad is None and levels[2].grad is None
    torch.testing.assert_close(levels[1].grad, torch.full((1, 1, 2, 2), 2.0, dtype=torch.float64))


def test_bad_input():
    with pytest.raises(TypeError, match="texture"):
        mipmap("not a tensor")
    with pytest.raises(TypeError, match="texture.*float"):
        mipmap(torch.zeros(1, 1, 4, 4, dtype=torch.int32))
    with pytest.raises(ValueError, match=r"texture.*\[B, C, H, W\]"):
        mipmap(torch.zeros(4, 4))
    with pytest.raises(ValueError, match="texture"):
        mipmap(torch.zeros(1, 1, 0, 4))
    with pytest.raises(ValueError, match="max_levels"):
        mipmap(torch.zeros(1, 1, 4, 4), max_levels=0)
    with pytest.raises(TypeError, match="max_levels"):
        mipmap(torch.zeros(1, 1, 4, 4), max_levels=1.5)
    with pytest.raises(ValueError, match=r"texture\[1\].*\(1, 1, 2, 2\)"):
        mipmap([torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 2, 3)])
    with pytest.raises(ValueError, match=r"texture\[1\]"):
        mipmap([torch.zeros(1, 1, 4, 4), torch.zeros(2, 1, 2, 2)])
    with pytest.raises(TypeError, match=r"texture\[1\].*dtype"):
        mipmap([torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 2, 2, dtype=torch.float64)])
    with pytest.raises(ValueError, match=r"texture\[1\].*device"):
        mipmap([torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 2, 2, device="meta")])
    with pytest.raises(ValueError, match="levels"):
        mipmap([torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 1, 1), torch.zeros(1, 1, 1, 1)])
    with pytest.raises(ValueError, match="at least one level"):
        mipmap([])


def test_single_level_filters_read_level_zero_of_a_mipmap():
    x = torch.rand(1, 3, 9, 7)
    uv = torch.rand(2, 5, 4, 2)
    for f in ("nearest", "bilinear", "bicubic"):
        torch.testing.assert_close(difftex.sample(mipmap(x), uv, filter=f), difftex.sample(x, uv, filter=f))
    assert isinstance(mipmap(x), Mipmap)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    x = torch.rand(1, 3, 37, 20, dtype=torch.float64)
    for a, b in zip(mipmap(x), mipmap(x.cuda())):
        torch.testing.assert_close(a, b.cpu(), atol=1e-12, rtol=0)

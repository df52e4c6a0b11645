"""Ripmaps (difftex/texture/pyramid/ripmap.py): level sizes, means, the diagonal, the adjoint, bad input."""
from __future__ import annotations

import pytest
import torch

import difftex
from difftex import Ripmap, mipmap, ripmap

f64 = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("hw", [(13, 20), (1, 7), (5, 1), (16, 16), (1, 1)])
def test_levels_have_ceil_sizes_and_keep_the_mean(hw):
    H, W = hw
    tex = torch.rand(2, 3, H, W, dtype=f64, generator=_gen(1))
    rip = ripmap(tex)
    n_u, n_v = rip.counts
    assert (n_u, n_v) == (1 + (W - 1).bit_length(), 1 + (H - 1).bit_length())
    for i in range(n_u):
        for j in range(n_v):
            lv = rip[i, j]
            assert lv.shape == (2, 3, -(-H // 2 ** j), -(-W // 2 ** i)), (i, j)
            # Odd sides use the area-weighted box: no texel is dropped, the mean is kept exactly.
            torch.testing.assert_close(lv.mean((-1, -2)), tex.mean((-1, -2)), atol=1e-13, rtol=0)
    assert rip[n_u - 1, n_v - 1].shape[-2:] == (1, 1)
    assert rip.base is tex and rip.shape == tex.shape and rip.dtype == f64
    assert repr(rip) == f"Ripmap(B=2, C=3, base={H}x{W}, levels={n_u}x{n_v} (u x v), dtype=torch.float64, device=cpu)"


def test_the_diagonal_is_the_mip_chain():
    tex = torch.rand(1, 2, 13, 40, dtype=f64, generator=_gen(2))
    diag = ripmap(tex).mipmap()
    mips = mipmap(tex)
    assert len(diag) == len(mips) == 7
    for a, b in zip(diag, mips):
        torch.testing.assert_close(a, b, atol=1e-14, rtol=0)


def test_a_texture_constant_along_v_has_the_one_row_mip_chain_in_every_row():
    row = torch.rand(1, 2, 1, 23, dtype=f64, generator=_gen(3))
    tex = row.expand(1, 2, 9, 23)
    rip = ripmap(tex)
    chain = mipmap(row)  # a one-row texture halves only its width
    for j in range(rip.counts[1]):
        for i in range(rip.counts[0]):
            lv = rip[i, j]
            torch.testing.assert_close(lv, chain[i].expand_as(lv), atol=1e-14, rtol=0)


def test_gradients_reach_the_base_through_the_exact_adjoint():
    tex = torch.rand(1, 1, 5, 6, dtype=f64, generator=_gen(4), requires_grad=True)

    def levels(t):
        rip = ripmap(t)
        return tuple(rip[i, j] for i in range(rip.counts[0]) for j in range(rip.counts[1]))

    assert torch.autograd.gradcheck(levels, (tex,))


def test_sample_reads_a_prebuilt_ripmap_like_a_texture():
    tex = torch.rand(2, 3, 12, 17, dtype=f64, generator=_gen(5))
    uv = torch.rand(2, 4, 5, 2, dtype=f64, generator=_gen(6)) * 2 - 0.5
    dx = torch.randn(2, 4, 5, 2, dtype=f64, generator=_gen(7)) * 0.2
    dy = torch.randn(2, 4, 5, 2, dtype=f64, generator=_gen(8)) * 0.05
    rip = ripmap(tex)
    assert ripmap(rip) is rip
    for f in ("bilinear", "ripmap", "sat", "trilinear", "anisotropic", "ewa"):
        kw = dict(uv_dx=dx, uv_dy=dy) if f != "bilinear" else {}
        a = difftex.sample(rip, uv, filter=f, wrap=("mirror", "clamp"), **kw)
        b = difftex.sample(tex, uv, filter=f, wrap=("mirror", "clamp"), **kw)
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0, msg=f)


def test_bad_input_names_the_argument():
    with pytest.raises(TypeError, match=r"texture: expected a floating-point tensor"):
        ripmap(torch.zeros(1, 1, 4, 4, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"texture: expected 4-D \[B, C, H, W\], got shape \(4, 4\)"):
        ripmap(torch.zeros(4, 4))
    with pytest.raises(ValueError, match=r"texture: expected B, C, H, W >= 1, got shape \(1, 1, 0, 4\)"):
        ripmap(torch.zeros(1, 1, 0, 4))
    with pytest.raises(TypeError, match=r"texture: expected a float tensor \[B, C, H, W\], got list"):
        ripmap([torch.zeros(1, 1, 2, 2)])
    assert isinstance(ripmap(torch.zeros(1, 1, 2, 2)), Ripmap)


def test_user_built_levels_are_checked():
    # sample() read a user-built Ripmap unchecked: wrong sizes silently, mixed dtypes as internal errors.
    tex = torch.rand(1, 2, 8, 8)
    uv = torch.rand(1, 4, 4, 2)
    d = dict(uv_dx=torch.full_like(uv, 0.3), uv_dy=torch.full_like(uv, 0.05))

    def grid_with(i, j, lv):
        g = [list(r) for r in ripmap(tex).grid]
        g[j][i] = lv
        return Ripmap(g)

    bad = [(grid_with(1, 1, torch.rand(1, 2, 3, 3)), ValueError, r"texture\[1, 1\]: expected shape \(1, 2, 4, 4\)"),
           (grid_with(1, 1, torch.rand(2, 2, 4, 4)), ValueError, r"texture\[1, 1\]: expected shape \(1, 2, 4, 4\)"),
           (grid_with(2, 1, torch.rand(1, 2, 4, 2, dtype=torch.float64)), TypeError,
            r"texture\[2, 1\]: expected dtype torch.float32"),
           (Ripmap([[tex], [torch.rand(1, 2, 4, 8)], []]), ValueError, r"rectangular grid"),
           (Ripmap([[tex] * 5]), ValueError, r"5 x 1 ripmap levels \(u x v\) given but a 8x8 base has only 4 x 4")]
    for rm, err, msg in bad:
        for f in ("ripmap", "trilinear", "bilinear"):
            with pytest.raises(err, match=msg):
                difftex.sample(rm, uv, filter=f, **d)
        with pytest.raises(err, match=msg):
            ripmap(rm)
    good = Ripmap([list(r) for r in ripmap(tex).grid])
    torch.testing.assert_close(difftex.sample(good, uv, filter="ripmap", **d),
                               difftex.sample(tex, uv, filter="ripmap", **d))

"""The native path of difftex.envmap.cubemap (csrc/cube.cpp) against the torch reference (backend "reference")."""
import pytest
import torch

from difftex.envmap import cube_mipmap, cube_to_direction, cubemap
from difftex.envmap.cube import _NativeFront, _native_kernel, _ring_tables, _gutter_table
from difftex import _native as native
from tests.conftest import use_backend
from tests.envmap.test_cube import random_dirs, tangent_derivs

F64 = torch.float64
NATIVE = ("bilinear", "trilinear", "nearest-mip")


@pytest.fixture(autouse=True)
def need_kernel():
    kernel = native.load()
    if kernel is None or not hasattr(kernel, "cube_read"):
        pytest.skip("native kernel not built here")


def edge_dirs(S: int, n: int = 64) -> torch.Tensor:
    """[1, 1, 4n, 3] directions on and next to every face edge and corner (within half a texel)."""
    g = torch.Generator().manual_seed(9)
    face = torch.randint(0, 6, (4 * n,), generator=g)
    t = torch.rand(4 * n, generator=g, dtype=F64)
    off = (torch.rand(4 * n, generator=g, dtype=F64) - 0.5) / S  # +- half a texel across the edge
    side = torch.arange(4 * n) % 4
    u = torch.where(side == 0, off.abs(), torch.where(side == 1, 1 - off.abs(), t))
    v = torch.where(side == 2, off.abs(), torch.where(side == 3, 1 - off.abs(), t))
    corner = torch.arange(4 * n) % 7 == 0
    u = torch.where(corner, (t > 0.5).to(F64), u)
    v = torch.where(corner, (off > 0).to(F64), v)
    d = cube_to_direction(face, torch.stack([u, v], -1))
    return (d / d.norm(dim=-1, keepdim=True)).view(1, 1, -1, 3)


def inputs(S: int, dtype=F64, seed: int = 3):
    g = torch.Generator().manual_seed(seed)
    cube = torch.randn(1, 6, 3, S, S, generator=g, dtype=F64).to(dtype)
    d = torch.cat([random_dirs(300, seed=seed), edge_dirs(S)], 2).to(dtype)
    d = d * torch.rand(d.shape[:-1] + (1,), generator=g, dtype=F64).to(dtype).add(0.5)  # lengths vary
    dx, dy = tangent_derivs(d / d.norm(dim=-1, keepdim=True), 2.5 / S)
    # Scale spread over the levels, and some anisotropy.
    scale = torch.logspace(-1.5, 1.5, d.shape[2], dtype=dtype).view(1, 1, -1, 1)
    aniso = torch.linspace(2.5, 0.3, d.shape[2], dtype=dtype).view(1, 1, -1, 1)  # either derivative the longer
    return cube, d, dx * scale, dy * scale * aniso


def both(fn):
    """fn() on the native path and on the reference."""
    with use_backend("native"):
        got = fn()
    with use_backend("reference"):
        want = fn()
    return got, want


def test_ring_tables_hold_every_gutter_texel():
    for n in (1, 2, 5):
        P = n + 2
        ri, rw = _ring_tables(n)
        pos, idx, w = _gutter_table(n, 1)
        assert ri.shape == (6 * (4 * P - 4), 3) and rw.shape == ri.shape
        # The same rows, permuted: the multiset of (indices, weights) agrees and every slot got one.
        key = lambda i, ww: sorted(zip(i.tolist(), ww.tolist()))
        assert key(ri, rw) == key(idx, w)
        torch.testing.assert_close(rw.sum(1), torch.ones(ri.shape[0], dtype=F64))


@pytest.mark.parametrize("filter", NATIVE)
def test_values_and_gradients_match_the_reference(filter):
    S = 8
    cube, d, dx, dy = inputs(S)
    bias = torch.linspace(-1, 1, d.shape[2], dtype=F64).view(1, 1, -1)

    def run():
        c, dd, x, y, b = (t.clone().requires_grad_() for t in (cube, d, dx, dy, bias))
        kw = dict(dirs_dx=x, dirs_dy=y, lod_bias=b) if filter != "bilinear" else {}
        out = cubemap(c, dd, filter=filter, **kw)
        w = torch.linspace(-1, 2, out.numel(), dtype=F64).view(out.shape)
        wrt = (c, dd) + ((x, y, b) if kw else ())
        grads = torch.autograd.grad((out * w).sum(), wrt, allow_unused=True)
        return out, [torch.zeros_like(t) if g is None else g for t, g in zip(wrt, grads)]

    assert _native_kernel(cube, d, filter) is not None
    (got, g_got), (want, g_want) = both(run)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    for name, a, b in zip(("cube", "dirs", "dirs_dx", "dirs_dy", "lod_bias"), g_got, g_want):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9, msg=f"{filter}: gradient of {name}")
        # nearest-mip: the level picks a level, it is not differentiated.
        assert (a.abs().sum() > 0) == (filter != "nearest-mip" or name in ("cube", "dirs")), name


def test_float32_batch_and_mipmap_input():
    S = 16
    cube, d, dx, dy = inputs(S, torch.float32)
    d, dx = d.expand(2, -1, -1, -1), torch.cat([dx, 0.5 * dx])  # dirs broadcast over a batch of derivatives
    dy = dy.expand(2, -1, -1, -1)
    for f in NATIVE:
        fn = lambda: cubemap(cube_mipmap(cube), d, filter=f, dirs_dx=dx, dirs_dy=dy)
        got, want = both(fn)
        assert got.shape == (2, 3, 1, d.shape[2]) and got.dtype == torch.float32
        torch.testing.assert_close(got, want, rtol=0, atol=2e-5)


def test_gradcheck_native():
    S = 4
    cube, d, dx, dy = inputs(S, seed=5)
    d, dx, dy = d[:, :, ::6], dx[:, :, ::6], dy[:, :, ::6]
    with use_backend("native"):
        for f in NATIVE:
            if f == "bilinear":
                fn = lambda c, dd: cubemap(c, dd)
                args = (cube.requires_grad_(), d.requires_grad_())
            else:
                fn = lambda c, dd, x, y: cubemap(c, dd, filter=f, dirs_dx=x, dirs_dy=y)
                args = tuple(t.detach().requires_grad_() for t in (cube, d, dx, dy))
            assert torch.autograd.gradcheck(fn, args, atol=1e-7, nondet_tol=1e-12), f


def test_double_backward_matches_the_reference():
    # create_graph=True: the native nodes hand their backward to the differentiable torch path.
    S = 4
    cube, d, dx, dy = inputs(S, seed=6)
    d, dx, dy = d[:, :, ::10], dx[:, :, ::10], dy[:, :, ::10]

    def run():
        c, dd = cube.clone().requires_grad_(), d.clone().requires_grad_()
        out = cubemap(c, dd, filter="trilinear", dirs_dx=dx, dirs_dy=dy)
        gc, gd = torch.autograd.grad((out * out).sum(), (c, dd), create_graph=True)
        return torch.autograd.grad(gc.square().sum() + gd.square().sum(), (c, dd))

    got, want = both(run)
    for a, b in zip(got, want):
        assert a.abs().sum() > 0
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)


def test_front_matches_the_direction_maths():
    # Face and uv are direction_to_cube's exactly (ties included); zero / non-finite directions are coded.
    d = torch.tensor([[1.0, 1.0, 0.2], [0.3, -1.0, 1.0], [-1.0, 1.0, -1.0], [0.0, 0.0, -2.0], [1e-12, 0, 0],
                      [0.0, 0.0, 0.0], [float("nan"), 1, 0], [0, float("-inf"), 0]], dtype=F64)
    from difftex.envmap import direction_to_cube
    face, uv, D = _NativeFront.apply(d, None, None, None, 0.0, 8, 1)
    f2, uv2 = direction_to_cube(d[:5])
    assert face.dtype == torch.int8 and D.numel() == 0
    assert torch.equal(face[:5].long(), f2) and face[5:].tolist() == [-1, -2, -2]
    torch.testing.assert_close(uv[:5], uv2, rtol=0, atol=1e-15)


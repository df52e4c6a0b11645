"""Tests for difftex.envmap.cube: seamless cube-map sampling (cubemap, cube_mipmap)."""
import math

import pytest
import torch

import difftex
from difftex.envmap import CubeMipmap, cube_mipmap, cube_to_direction, cubemap, direction_to_cube
from tests.conftest import use_backend

F64 = torch.float64
MIP = ("trilinear", "nearest-mip", "anisotropic", "auto", "ewa")


def texel_dirs(S: int, dtype=F64) -> torch.Tensor:
    """[6, S, S, 3] unit directions of the texel centres (face, row, col)."""
    c = (torch.arange(S, dtype=dtype) + 0.5) / S
    v, u = torch.meshgrid(c, c, indexing="ij")
    uv = torch.stack([u, v], -1).expand(6, S, S, 2)
    face = torch.arange(6).view(6, 1, 1).expand(6, S, S)
    d = cube_to_direction(face, uv)
    return d / d.norm(dim=-1, keepdim=True)


def smooth(d: torch.Tensor) -> torch.Tensor:
    """[..., 3] unit directions -> [..., 2] a smooth function on the sphere."""
    x, y, z = d.unbind(-1)
    return torch.stack([x + 0.5 * y * z, torch.sin(2 * y) + 0.3 * z], -1)


def smooth_cube(S: int, dtype=F64) -> torch.Tensor:
    return smooth(texel_dirs(S, dtype)).permute(0, 3, 1, 2).unsqueeze(0).contiguous()  # [1, 6, 2, S, S]


def random_dirs(n: int, seed: int = 0, dtype=F64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(1, 1, n, 3, generator=g, dtype=F64).to(dtype)
    return d / d.norm(dim=-1, keepdim=True)


def tangent_derivs(d: torch.Tensor, length: float, seed: int = 1):
    """Two random tangent vectors of the given length per direction (a footprint on the sphere)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(2):
        r = torch.randn(d.shape, generator=g, dtype=F64).to(d.dtype)
        r = r - (r * d).sum(-1, keepdim=True) * d
        out.append(r / r.norm(dim=-1, keepdim=True) * length)
    return out


# ---------------------------------------------------------------- values


@pytest.mark.parametrize("filter", ["bilinear", "trilinear"])
def test_values_converge_to_the_function(filter):
    """Lookups of a cube of f(texel-centre direction) agree with f.

    Measured max error: bilinear 0.18-0.22 / S overall (within a texel of an edge the folded gutter texel
    sits O(h) off its projected place), 1.8-1.9 / S^2 more than 2 texels from the edges; trilinear with a
    one-texel footprint 0.5-0.65 / S.
    """
    d = random_dirs(4000)
    want = smooth(d).permute(0, 3, 1, 2)
    _, uv = direction_to_cube(d)
    errs = []
    for S in (16, 32, 64):
        kw = {}
        if filter == "trilinear":
            dx, dy = tangent_derivs(d, 2.0 / S)  # about one texel: levels 0 .. 1
            kw = dict(dirs_dx=dx, dirs_dy=dy)
        err = (cubemap(smooth_cube(S), d, filter=filter, **kw) - want).abs().amax(1)[0]
        errs.append(err.max().item())
        assert errs[-1] < (0.3 if filter == "bilinear" else 0.9) / S, (S, errs[-1])
        if filter == "bilinear":
            inner = ((uv - 0.5).abs().amax(-1) < 0.5 - 2.0 / S)[0]
            assert err[inner].max() < 2.5 / S ** 2
    assert errs[2] < errs[0] / 3, errs


def test_edge_midpoint_and_corner_are_exact_averages():
    """At an edge the bilinear value is the mean of the two edge texels; at a corner the mean of the three."""
    S = 4
    cube = torch.randn(1, 6, 1, S, S, dtype=F64, generator=torch.Generator().manual_seed(3))
    # The +X / +Z edge (x = z = 1) at y between rows 1 and 2 of both faces' boundary columns:
    # +X's column 0 (s_c = -z = -1) meets +Z's column S - 1 (s_c = x = 1).
    y = -(2 * (1 + 0.5) / S - 1)  # t_c = -y at the centre of row 1 of both faces
    for eps in (1e-9, -1e-9):  # just on +X, just on +Z
        d = torch.tensor([[[[1.0 + eps, y, 1.0 - eps]]]], dtype=F64)
        got = cubemap(cube, d).item()
        want = 0.5 * (cube[0, 0, 0, 1, 0] + cube[0, 4, 0, 1, S - 1]).item()
        assert got == pytest.approx(want, abs=1e-7)
    # The corner (1, 1, 1): +X texel (row 0, col 0), +Y texel (row S-1, col S-1), +Z texel (row 0, col S-1).
    corner = (cube[0, 0, 0, 0, 0] + cube[0, 2, 0, S - 1, S - 1] + cube[0, 4, 0, 0, S - 1]).item() / 3
    for d in ([1.0, 1.0 - 1e-9, 1.0 - 2e-9], [1.0 - 1e-9, 1.0, 1.0 - 2e-9], [1.0 - 2e-9, 1.0 - 1e-9, 1.0]):
        got = cubemap(cube, torch.tensor(d, dtype=F64).view(1, 1, 1, 3)).item()
        assert got == pytest.approx(corner, abs=1e-7)


def test_backends_agree(backend):
    S = 8
    cube = torch.randn(2, 6, 3, S, S, dtype=F64, generator=torch.Generator().manual_seed(4))
    d = random_dirs(500, seed=5).expand(2, 1, 500, 3)
    dx, dy = tangent_derivs(d, 3.0 / S)
    with use_backend("reference"):
        refs = {f: cubemap(cube, d, filter=f, dirs_dx=dx, dirs_dy=dy)
                for f in ("nearest", "bilinear", "bicubic") + MIP}
    for f, ref in refs.items():
        got = cubemap(cube, d, filter=f, dirs_dx=dx, dirs_dy=dy)
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-10, msg=f)


def test_nearest_reads_the_containing_texel():
    S = 8
    cube = torch.randn(1, 6, 1, S, S, dtype=F64, generator=torch.Generator().manual_seed(6))
    d = random_dirs(1000, seed=7)
    face, uv = direction_to_cube(d)
    col = (uv[..., 0] * S).floor().long().clamp(0, S - 1)
    row = (uv[..., 1] * S).floor().long().clamp(0, S - 1)
    want = cube[0, face, 0, row, col]
    assert torch.equal(cubemap(cube, d, filter="nearest")[:, 0], want)


# ---------------------------------------------------------------- seams


def great_circles(n: int) -> torch.Tensor:
    """[K, n, 3] directions along great circles: the three equators (all 12 edges, at their midpoints),
    one through the corner (1, 1, 1) across the +X / +Y boundary there, and two tilted ones."""
    normals = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, -2.0], [1.0, 2.0, 3.0],
                            [0.3, -1.0, 0.7]], dtype=F64)
    out = []
    th = torch.arange(n, dtype=F64) * (2 * math.pi / n)
    for nrm in normals:
        nrm = nrm / nrm.norm()
        a = torch.linalg.cross(nrm, torch.tensor([0.577, 0.577, 0.577], dtype=F64))
        if nrm[0] == nrm[1] and nrm[2] == -2 * nrm[0]:
            a = torch.tensor([1.0, 1.0, 1.0], dtype=F64)  # start exactly at the corner
        a = a / a.norm()
        b = torch.linalg.cross(nrm, a)
        out.append(torch.cos(th)[:, None] * a + torch.sin(th)[:, None] * b)
    return torch.stack(out)


def naive_read(cube, dirs, filter, dx=None, dy=None):
    """Per-face clamp reads without gutters: what seamless filtering must beat."""
    if dx is not None:
        face, uv, uv_dx, uv_dy = direction_to_cube(dirs, dirs_dx=dx, dirs_dy=dy)
    else:
        face, uv = direction_to_cube(dirs)
        uv_dx = uv_dy = None
    out = 0
    for f in range(6):
        v = difftex.sample(cube[:, f], uv, filter=filter, wrap="clamp", uv_dx=uv_dx, uv_dy=uv_dy)
        out = out + v * (face == f).unsqueeze(1)
    return out


def seam_jumps(read, S):
    """(largest jump between neighbouring directions across a face change, largest within a face)."""
    d = great_circles(20000).unsqueeze(0)  # [1, K, n, 3]
    vals = read(d)  # [1, C, K, n]
    face, uv = direction_to_cube(d)
    jump = (vals - vals.roll(-1, -1)).abs().amax(1)[0]  # [K, n]
    cross = face[0] != face[0].roll(-1, -1)
    return jump[cross].max().item(), jump[~cross].max().item()


@pytest.mark.parametrize("filter", ["bilinear", "trilinear"])
def test_no_seams_along_great_circles(filter):
    S = 8
    cube = torch.rand(1, 6, 3, S, S, dtype=F64, generator=torch.Generator().manual_seed(8))
    def derivs(d):
        if filter != "trilinear":
            return {}
        # A footprint that varies smoothly along the circle (random ones would make jumps of their own):
        # along the circle and across it, 2.5 and 1.5 texels at face centres (levels 1 .. 2 near edges).
        t = d.roll(-1, -2) - d.roll(1, -2)
        t = t / t.norm(dim=-1, keepdim=True)
        return dict(dirs_dx=t * 5.0 / S, dirs_dy=torch.linalg.cross(d, t) * 3.0 / S)

    cross, inside = seam_jumps(lambda d: cubemap(cube, d, filter=filter, **derivs(d)), S)
    assert cross <= inside, (cross, inside)
    naive_cross, naive_inside = seam_jumps(
        lambda d: naive_read(cube, d, filter, *derivs(d).values()), S)
    assert naive_cross > 3 * naive_inside, (naive_cross, naive_inside)


def test_bicubic_seamless_away_from_corners():
    """Bicubic's 4 x 4 stencil is continuous across edges; within 2 texels of a cube corner, where three
    faces meet and no square stencil fits, the averaged gutter corners leave a jump (measured 0.028 on
    uniform [0, 1) texels at S = 8, against 0.0032 inside faces)."""
    S = 8
    cube = torch.rand(1, 6, 3, S, S, dtype=F64, generator=torch.Generator().manual_seed(8))
    d = great_circles(20000).unsqueeze(0)
    face, uv = direction_to_cube(d)
    vals = cubemap(cube, d, filter="bicubic")
    jump = (vals - vals.roll(-1, -1)).abs().amax(1)[0]
    cross = face[0] != face[0].roll(-1, -1)
    corner = (uv[0] - 0.5).abs().amin(-1) > 0.5 - 2.0 / S
    assert jump[cross & ~corner].max() <= jump[~cross].max()
    assert jump[cross & corner].max() < 0.05
    naive = naive_read(cube, d, "bicubic")
    naive_jump = (naive - naive.roll(-1, -1)).abs().amax(1)[0]
    assert naive_jump[cross & ~corner].max() > 3 * naive_jump[~cross].max()


def test_lod_bias():
    cube, d = grad_inputs(S=8)
    dx, dy = tangent_derivs(d.detach(), 0.3)
    a = cubemap(cube, d, filter="trilinear", dirs_dx=dx, dirs_dy=dy, lod_bias=0.7)
    b = cubemap(cube, d, filter="trilinear", dirs_dx=dx, dirs_dy=dy,
                lod_bias=torch.full(d.shape[:3], 0.7, dtype=F64))
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    # A large bias reads the 1 x 1 level, the mean of each face, at the face centres only (elsewhere the
    # 1 x 1 texel blends with the neighbouring faces' through the gutter, as any level does).
    centres = torch.cat([torch.eye(3, dtype=F64), -torch.eye(3, dtype=F64)])[[0, 3, 1, 4, 2, 5]].view(1, 1, 6, 3)
    top = cubemap(cube, centres, filter="trilinear", dirs_dx=dx[:, :, :6], dirs_dy=dy[:, :, :6], lod_bias=20.0)
    torch.testing.assert_close(top[0, :, 0], cube[0].mean((-1, -2)).T, rtol=0, atol=1e-12)
    bias = torch.full(d.shape[:3], 0.4, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda bb: cubemap(cube.detach(), d.detach(), filter="trilinear", dirs_dx=dx, dirs_dy=dy, lod_bias=bb),
        (bias,))


# ---------------------------------------------------------------- gradients


EDGE_DIRS = [[1.0, 0.31, 0.97], [0.96, -0.98, 0.2], [-0.97, 0.5, -0.99], [0.1, 0.98, -0.97],
             [1.0, 0.97, 0.96], [-0.96, -0.97, -1.0], [0.98, -1.0, 0.97]]  # edges, then corners


def grad_inputs(dtype=F64, S=4, C=2):
    g = torch.Generator().manual_seed(9)
    cube = torch.rand(1, 6, C, S, S, dtype=dtype, generator=g).requires_grad_()
    d = torch.tensor(EDGE_DIRS, dtype=dtype).view(1, 1, -1, 3).requires_grad_()
    return cube, d


@pytest.mark.parametrize("filter", ["bilinear", "bicubic"])
def test_gradcheck_single_level(filter):
    cube, d = grad_inputs()
    assert torch.autograd.gradcheck(lambda c, x: cubemap(c, x, filter=filter), (cube, d))


def test_nearest_gradient_reaches_the_cube_only():
    cube, d = grad_inputs()
    assert torch.autograd.gradcheck(lambda c: cubemap(c, d.detach(), filter="nearest"), (cube,))
    out = cubemap(cube, d, filter="nearest")
    gd, = torch.autograd.grad(out.sum(), d)
    assert torch.equal(gd, torch.zeros_like(gd))


@pytest.mark.parametrize("filter", ["trilinear", "anisotropic", "ewa"])
def test_gradcheck_mip(filter):
    cube, d = grad_inputs(S=8)
    # Fractional levels (no kink of the level blend) and, for anisotropic, a 3:1 footprint whose taps
    # cross the edges.
    g = torch.Generator().manual_seed(10)
    dx = (torch.randn(d.shape, generator=g, dtype=F64) * 0.13).requires_grad_()
    dy = (torch.randn(d.shape, generator=g, dtype=F64) * (0.05 if filter in ("anisotropic", "ewa") else 0.13))
    dy.requires_grad_()
    # fast_mode: random projections of the Jacobian (the full one costs a minute for anisotropic).
    assert torch.autograd.gradcheck(
        lambda c, x, a, b: cubemap(c, x, filter=filter, dirs_dx=a, dirs_dy=b), (cube, d, dx, dy), fast_mode=True)


def test_cube_mipmap_gradient_reaches_the_faces():
    cube, d = grad_inputs(S=8)
    dx, dy = tangent_derivs(d.detach(), 0.6)
    f = lambda c: cubemap(cube_mipmap(c), d.detach(), filter="trilinear", dirs_dx=dx, dirs_dy=dy)
    assert torch.autograd.gradcheck(f, (cube,), fast_mode=True)
    mm = cube_mipmap(cube)
    assert isinstance(mm, CubeMipmap) and [lv.shape[-1] for lv in mm] == [8, 4, 2, 1]
    torch.testing.assert_close(mm[1][0, 2, 1, 0, 0], cube[0, 2, 1, :2, :2].mean())
    torch.testing.assert_close(f(cube), cubemap(cube, d, filter="trilinear", dirs_dx=dx, dirs_dy=dy))


# ---------------------------------------------------------------- special directions


def test_zero_and_nonfinite_directions():
    cube, _ = grad_inputs()
    d = torch.tensor([[0.0, 0, 0], [float("nan"), 1, 0], [0.3, -0.2, 1.0], [float("inf"), 0, 0]],
                     dtype=F64).view(1, 1, 4, 3).requires_grad_()
    for f in ("bilinear", "trilinear", "ewa"):
        kw = dict(dirs_dx=torch.full_like(d, 0.1), dirs_dy=torch.full_like(d, -0.05)) if f != "bilinear" else {}
        out = cubemap(cube, d, filter=f, **kw)
        assert torch.equal(out[..., 0], torch.zeros_like(out[..., 0]))
        assert out[..., 1].isnan().all() and out[..., 3].isnan().all()
        assert out[..., 2].isfinite().all()
        gc, gd = torch.autograd.grad(out[..., :3].nan_to_num().sum() + out[..., 2].sum(), (cube, d))
        assert gc.isfinite().all() and gd.isfinite().all()
        assert torch.equal(gd[..., 0, :], torch.zeros(1, 1, 3, dtype=F64))
        assert torch.equal(gd[..., 1, :], torch.zeros(1, 1, 3, dtype=F64))
        assert gd[..., 2, :].abs().sum() > 0


def test_length_does_not_matter():
    cube, d = grad_inputs()
    d = d.detach()
    dx, dy = tangent_derivs(d / d.norm(dim=-1, keepdim=True), 0.3)
    a = cubemap(cube, d, filter="trilinear", dirs_dx=dx * d.norm(dim=-1, keepdim=True),
                dirs_dy=dy * d.norm(dim=-1, keepdim=True))
    # Scaling a direction by 5 scales its derivative by 5 too (d(5 r) = 5 dr).
    b = cubemap(cube, 5 * d, filter="trilinear", dirs_dx=5 * dx * d.norm(dim=-1, keepdim=True),
                dirs_dy=5 * dy * d.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype, scale", [(torch.float32, 1e-18), (torch.float64, 1e-100)])
@pytest.mark.parametrize("filter", ("nearest", "bilinear", "bicubic") + MIP)
def test_short_directions_read_as_unit_ones(backend, dtype, scale, filter):
    # m_a was floored at 1e-9, an absolute length: shorter directions read towards the face centre.
    g = torch.Generator().manual_seed(7)
    cube = torch.rand(1, 6, 3, 16, 16, generator=g, dtype=dtype)
    d, dx, dy = (torch.randn(1, 4, 8, 3, generator=g, dtype=dtype) * s for s in (1.0, 0.05, 0.05))
    # Both with a gradient: auto's tap counts may round differently on the kernel's no-gradient front end.
    ref = cubemap(cube, d.requires_grad_(), filter=filter, dirs_dx=dx, dirs_dy=dy)
    short = (d.detach() * scale).requires_grad_()
    got = cubemap(cube, short, filter=filter, dirs_dx=dx * scale, dirs_dy=dy * scale)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)
    got.sum().backward()
    assert short.grad.isfinite().all()


@pytest.mark.parametrize("dtype, scale", [(torch.float32, 1e-31), (torch.float32, 1e-40), (F64, 1e-200)])
def test_directions_below_the_floor_read_the_face_centre_on_every_backend(backend, dtype, scale):
    # Below dir_floor (1e-30 float32, 1e-150 float64) a direction is the zero vector's face centre, with no
    # gradient; the kernel clamped m_a instead and read other texels than the torch backends.
    g = torch.Generator().manual_seed(1)
    cube = torch.rand(1, 6, 3, 8, 8, generator=g, dtype=dtype)
    d = (torch.randn(1, 2, 3, 3, generator=g, dtype=dtype) * scale).requires_grad_()
    for f in ("bilinear", "trilinear"):
        kw = dict(dirs_dx=torch.full_like(d, 0.05 * scale), dirs_dy=torch.full_like(d, 0.02 * scale))
        got = cubemap(cube, d, filter=f, **kw)
        with use_backend("reference"):
            ref = cubemap(cube, d, filter=f, **kw)
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)
        got.sum().backward()
        assert torch.equal(d.grad, torch.zeros_like(d))
        d.grad = None


@pytest.mark.parametrize("filter", ["anisotropic", "auto"])
def test_values_do_not_depend_on_the_directions_needing_a_gradient(backend, filter):
    # The kernel's no-gradient front end gave one-tap points no axis; near an edge the count rises to the
    # neighbouring face's and the taps, spread along a zero axis, all fell on the point (2.3e-3 off for auto).
    g = torch.Generator().manual_seed(7)
    cube = torch.rand(1, 6, 3, 16, 16, generator=g, dtype=F64)
    d, dx, dy = (torch.randn(1, 4, 8, 3, generator=g, dtype=F64) * s for s in (1.0, 0.05, 0.05))
    a = cubemap(cube, d, filter=filter, dirs_dx=dx, dirs_dy=dy)
    b = cubemap(cube, d.clone().requires_grad_(), filter=filter, dirs_dx=dx, dirs_dy=dy)
    torch.testing.assert_close(a, b.detach(), rtol=0, atol=1e-12)


# ---------------------------------------------------------------- batch / dtype


@pytest.mark.parametrize("filter", ["bilinear", "trilinear", "auto", "ewa"])
def test_batch_dtype_and_broadcast(dtype, filter):
    S = 8
    g = torch.Generator().manual_seed(11)
    cube = torch.rand(3, 6, 2, S, S, dtype=F64, generator=g)
    d = torch.randn(3, 4, 5, 3, dtype=F64, generator=g)
    dx, dy = tangent_derivs(d / d.norm(dim=-1, keepdim=True), 0.4)
    kw = lambda i: dict(dirs_dx=dx[i:i + 1].to(dtype), dirs_dy=dy[i:i + 1].to(dtype)) if filter != "bilinear" \
        else {}
    kwb = dict(dirs_dx=dx.to(dtype), dirs_dy=dy.to(dtype)) if filter != "bilinear" else {}
    out = cubemap(cube.to(dtype), d.to(dtype), filter=filter, **kwb)
    assert out.shape == (3, 2, 4, 5) and out.dtype == dtype
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for i in range(3):
        one = cubemap(cube[i:i + 1].to(dtype), d[i:i + 1].to(dtype), filter=filter, **kw(i))
        torch.testing.assert_close(out[i:i + 1], one, rtol=0, atol=tol)
    # B = 1 cube over 3 direction batches, and 1 direction batch over 3 cubes
    shared = cubemap(cube[:1].to(dtype), d.to(dtype), filter=filter, **kwb)
    for i in range(3):
        one = cubemap(cube[:1].to(dtype), d[i:i + 1].to(dtype), filter=filter, **kw(i))
        torch.testing.assert_close(shared[i:i + 1], one, rtol=0, atol=tol)
    many = cubemap(cube.to(dtype), d[:1].to(dtype), filter=filter, **kw(0))
    for i in range(3):
        one = cubemap(cube[i:i + 1].to(dtype), d[:1].to(dtype), filter=filter, **kw(0))
        torch.testing.assert_close(many[i:i + 1], one, rtol=0, atol=tol)
    # float32 agrees with float64
    if dtype == torch.float32:
        ref = cubemap(cube, d, filter=filter, **({k: v.double() for k, v in kwb.items()}))
        torch.testing.assert_close(out.double(), ref, rtol=0, atol=1e-4)


def test_mipmap_input_equals_tensor_input():
    cube, d = grad_inputs(S=8)
    dx, dy = tangent_derivs(d.detach(), 0.5)
    for f in MIP + ("bilinear", "bicubic", "nearest"):
        a = cubemap(cube, d, filter=f, dirs_dx=dx, dirs_dy=dy)
        b = cubemap(cube_mipmap(cube), d, filter=f, dirs_dx=dx, dirs_dy=dy)
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_odd_face_size():
    S = 5
    d = random_dirs(2000, seed=12)
    want = smooth(d).permute(0, 3, 1, 2)
    got = cubemap(smooth_cube(S), d)
    assert (got - want).abs().max() < 6.0 / S
    dx, dy = tangent_derivs(d, 3.0 / S)
    got = cubemap(smooth_cube(S), d, filter="trilinear", dirs_dx=dx, dirs_dy=dy)
    assert (got - want).abs().max() < 12.0 / S


# ---------------------------------------------------------------- bad input


def test_bad_input():
    cube = torch.rand(1, 6, 3, 4, 4)
    d = torch.randn(1, 2, 2, 3)
    with pytest.raises(ValueError, match=r"cube: expected 5-D"):
        cubemap(cube[0], d)
    with pytest.raises(ValueError, match=r"cube: expected 6 faces"):
        cubemap(cube[:, :5], d)
    with pytest.raises(ValueError, match=r"cube: expected square faces.*4x3"):
        cubemap(cube[..., :3], d)
    with pytest.raises(TypeError, match=r"cube: expected a floating-point tensor"):
        cubemap(cube.long(), d)
    with pytest.raises(ValueError, match=r"dirs: expected last dimension 3"):
        cubemap(cube, d[..., :2])
    with pytest.raises(ValueError, match=r"dirs: expected 4-D"):
        cubemap(cube, d[0])
    with pytest.raises(TypeError, match=r"dirs: expected dtype torch.float32 like cube"):
        cubemap(cube, d.double())
    for f in MIP:
        with pytest.raises(ValueError, match=r"dirs_dx: required by filter"):
            cubemap(cube, d, filter=f)
    with pytest.raises(ValueError, match=r"dirs_dy: required by filter"):
        cubemap(cube, d, filter="trilinear", dirs_dx=d)
    with pytest.raises(ValueError, match=r"dirs_dx: expected last dimension 3"):
        cubemap(cube, d, filter="trilinear", dirs_dx=d[..., :2], dirs_dy=d)
    with pytest.raises(ValueError, match=r"dirs_dy: expected shape \[B, H, W, 3\]"):
        cubemap(cube, d, filter="trilinear", dirs_dx=d, dirs_dy=d[:, :1])
    for f in ("ripmap", "sat"):
        with pytest.raises(ValueError, match=rf"filter: '{f}' is not supported by cubemap .*face-aligned boxes"):
            cubemap(cube, d, filter=f, dirs_dx=d, dirs_dy=d)
    with pytest.raises(ValueError, match=r"filter: unknown filter"):
        cubemap(cube, d, filter="linear")
    with pytest.raises(ValueError, match=r"batch sizes do not match"):
        cubemap(cube.expand(2, -1, -1, -1, -1), d.expand(3, -1, -1, -1))
    with pytest.raises(ValueError, match=r"max_aniso"):
        cubemap(cube, d, filter="anisotropic", dirs_dx=d, dirs_dy=d, max_aniso=0.5)
    with pytest.raises(TypeError, match=r"lod_bias: expected a number"):
        cubemap(cube, d, filter="trilinear", dirs_dx=d, dirs_dy=d, lod_bias="1")
    with pytest.raises(ValueError, match=r"lod_bias: expected a scalar or \[B, H, W\]"):
        cubemap(cube, d, filter="trilinear", dirs_dx=d, dirs_dy=d, lod_bias=torch.zeros(1, 3, 2))
    bad = CubeMipmap([cube, cube[..., :1, :1]])
    with pytest.raises(ValueError, match=r"cube\[1\]: expected shape \(1, 6, 3, 2, 2\)"):
        cubemap(bad, d, filter="trilinear", dirs_dx=d, dirs_dy=d)
    with pytest.raises(ValueError, match=r"cube: expected 6 faces"):
        cube_mipmap(cube[:, :4])
    with pytest.raises(ValueError, match=r"cube: expected square faces"):
        cube_mipmap(cube[..., :2, :])


@pytest.mark.parametrize("filter", ["anisotropic", "auto"])
def test_anisotropic_taps_cross_edges_along_the_great_circle(filter):
    """A long footprint near an edge: the taps past the edge are reprojected onto the next face.

    The footprint is a vector of the face plane, so its taps lie on the plane line, i.e. on a great
    circle; the result must match the mean of f over those tap directions up to the filtering error of
    a smooth f (measured 0.064 / S); taps clamped into the face's gutter instead miss by 0.77 / S.
    """
    S, N = 16, 32
    g = torch.Generator().manual_seed(13)
    face = torch.arange(6).repeat(4)
    st = torch.rand(24, 2, generator=g, dtype=F64) * 1.6 - 0.8
    st[:, 0] = 0.75 * torch.where(torch.rand(24, generator=g) < 0.5, -1.0, 1.0)  # close to the left / right edge
    p = cube_to_direction(face, (st + 1) / 2)  # on the face plane, m_a = 1
    e_s = cube_to_direction(face, torch.tensor([1.0, 0.5], dtype=F64).expand(24, 2)) - \
        cube_to_direction(face, torch.tensor([0.0, 0.5], dtype=F64).expand(24, 2))  # the plane's s axis, length 2
    dxp = e_s * 0.5 * 2.0  # 2.0 face units ([-1, 1]), a texel per tap: up to 0.75 past the edge
    dyp = torch.linalg.cross(p, dxp)
    dyp = dyp / dyp.norm(dim=-1, keepdim=True) * (2.0 / N) * 0.9  # minor axis: N taps exactly
    offs = ((torch.arange(N, dtype=F64) + 0.5) / N - 0.5)
    taps = p[:, None, :] + offs[None, :, None] * dxp[:, None, :]
    want = smooth(taps / taps.norm(dim=-1, keepdim=True)).mean(1).T  # [2, 24]
    got = cubemap(smooth_cube(S), p.view(1, 1, 24, 3), filter=filter, max_aniso=N,
                  dirs_dx=dxp.view(1, 1, 24, 3), dirs_dy=dyp.view(1, 1, 24, 3))[0, :, 0]
    assert (got - want).abs().max() < 0.2 / S


def _equirect_dirs(H: int, W: int) -> torch.Tensor:
    """[H, W, 3] directions of an H x W equirect map's pixel centres."""
    v, u = torch.meshgrid((torch.arange(H, dtype=F64) + 0.5) / H, (torch.arange(W, dtype=F64) + 0.5) / W,
                          indexing="ij")
    return difftex.envmap.equirect_uv_to_direction(torch.stack((u, v), -1))


@pytest.mark.parametrize("filter", ["bilinear", "anisotropic"])
def test_cube_to_equirect_converges_to_the_function(filter):
    # A closed-form smooth function on the cube; the map's pixels take it at their directions. Measured: the
    # largest error is first order near the cube edges (0.07-0.42 / S, the gutters), the mean second order
    # (0.3-0.4 / S^2 bilinear, 0.94-1.0 / S^2 anisotropic), S = 8 .. 64.
    means = []
    for S in (8, 16, 32):
        out = difftex.envmap.cube_to_equirect(smooth_cube(S), (S, 2 * S), filter=filter)
        want = smooth(_equirect_dirs(S, 2 * S)).permute(2, 0, 1).unsqueeze(0)
        assert out.shape == (1, 2, S, 2 * S)
        err = (out - want).abs()
        assert err.max() < 0.5 / S and err.mean() < 1.2 / S ** 2, (S, err.max().item(), err.mean().item())
        means.append(err.mean().item())
    assert means[-1] < means[0] / 10, means


def test_cube_to_equirect_filters_a_minified_cube():
    # A 64^2 noise cube into a 16 x 32 map: each map pixel covers ~16 cube texels. Against a 4 x 4 supersampled
    # bilinear reference of the same map, anisotropic is far closer than point-sampling bilinear.
    g = torch.Generator().manual_seed(5)
    cube = torch.rand(1, 6, 1, 64, 64, generator=g, dtype=F64)
    H, W, ss = 16, 32, 4
    fine = difftex.envmap.cube_to_equirect(cube, (H * ss, W * ss), filter="bilinear")
    ref = torch.nn.functional.avg_pool2d(fine, ss)
    err = {f: (difftex.envmap.cube_to_equirect(cube, (H, W), filter=f) - ref).pow(2).mean().item()
           for f in ("bilinear", "trilinear", "anisotropic")}
    assert err["anisotropic"] < err["trilinear"] < err["bilinear"] / 2, err


def test_cube_to_equirect_gradient_and_bad_size():
    cube = torch.rand(1, 6, 1, 3, 3, dtype=F64, generator=torch.Generator().manual_seed(6), requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: difftex.envmap.cube_to_equirect(c, (3, 6), filter="trilinear"),
                                    (cube,), eps=1e-6, atol=1e-6)
    out = difftex.envmap.cube_to_equirect(cube_mipmap(cube.detach().float()), (2, 4))
    assert out.dtype == torch.float32 and out.shape == (1, 1, 2, 4)
    with pytest.raises(TypeError, match=r"size: expected \(H, W\) ints >= 1, got 8"):
        difftex.envmap.cube_to_equirect(cube, 8)
    with pytest.raises(ValueError, match=r"size: expected \(H, W\) ints >= 1, got \(0, 4\)"):
        difftex.envmap.cube_to_equirect(cube, (0, 4))


@pytest.fixture
def torch_path():
    """The torch path (the grid_sample backend), which reads the gutter atlases (the native read needs none)."""
    with use_backend("grid_sample"):
        yield


def test_cube_mipmap_keeps_its_atlases_without_grad(torch_path):
    cube, d = grad_inputs(S=8)
    dx, dy = tangent_derivs(d.detach(), 0.5)
    mm = cube_mipmap(cube.detach().clone())
    first = cubemap(mm, d.detach(), filter="trilinear", dirs_dx=dx, dirs_dy=dy)
    kept = dict(mm._atlases)
    assert kept and all(v[2] is mm._atlases[k][2] for k, v in kept.items())
    again = cubemap(mm, d.detach(), filter="trilinear", dirs_dx=dx, dirs_dy=dy)
    assert torch.equal(first, again) and all(v[2] is mm._atlases[k][2] for k, v in kept.items())
    # An in-place change of a level is seen (rebuilt), and values follow it.
    mm.levels[0].add_(1.0)
    assert torch.equal(cubemap(mm, d.detach()), cubemap(mm.levels[0], d.detach()))
    # Under grad mode a level that requires grad is read in the graph, every call.
    ref = cube_mipmap(cube)
    out = cubemap(ref, d.detach(), filter="trilinear", dirs_dx=dx, dirs_dy=dy)
    assert not ref._atlases and out.requires_grad


@pytest.mark.parametrize("filter", ["anisotropic", "auto"])
def test_anisotropic_level_blends_across_edges(filter):
    """The anisotropic / auto level is blended with the neighbouring face's near edges, as trilinear's.

    Along the great circles with a footprint of 1.5 x 4 texels: largest jump across a face change measured
    0.045 (0.079 with per-face levels), inside faces 0.086 (tap counts change there too)."""
    S = 8
    cube = torch.rand(1, 6, 3, S, S, dtype=F64, generator=torch.Generator().manual_seed(8))

    def read(d):
        t = d.roll(-1, -2) - d.roll(1, -2)
        t = t / t.norm(dim=-1, keepdim=True)
        return cubemap(cube, d, filter=filter, dirs_dx=t * 1.5 / S, dirs_dy=torch.linalg.cross(d, t) * 4.0 / S)

    cross, inside = seam_jumps(read, S)
    assert cross < 0.06 and cross <= inside, (cross, inside)


# ---------------------------------------------------------------- EWA


def _smooth_derivs(d, along, across, S):
    """Footprint along / across the great circle, in texels at face centres (smooth along the circle)."""
    t = d.roll(-1, -2) - d.roll(1, -2)
    t = t / t.norm(dim=-1, keepdim=True)
    return dict(dirs_dx=t * (2 * along / S), dirs_dy=torch.linalg.cross(d, t) * (2 * across / S))


@pytest.mark.parametrize("along, across", [(2.5, 1.5), (4.0, 1.0)])
def test_ewa_no_seams_along_great_circles(along, across):
    # EWA's taps are laid out in the direction's tangent plane (no face in it) and its level is blended
    # across edges; what jumps is the tap lattice's count, inside faces as much as at edges. Measured on
    # S = 8 noise, largest jump across a face change / inside a face: 0.0041 / 0.020 (footprint 2.5 x 1.5
    # texels) and 0.0057 / 0.019 (4 x 1); anisotropic's face-plane taps: 0.058 / 0.112 and 0.097 / 0.052.
    S = 8
    cube = torch.rand(1, 6, 3, S, S, dtype=F64, generator=torch.Generator().manual_seed(8))
    read = lambda f: seam_jumps(lambda d: cubemap(cube, d, filter=f, **_smooth_derivs(d, along, across, S)), S)
    cross, inside = read("ewa")
    assert cross <= inside / 2 and inside < 0.03, (cross, inside)
    assert cross < read("anisotropic")[0] / 5, cross


def test_ewa_matches_sample_inside_a_face():
    # Away from edges the cube's EWA (Gaussian-weighted bilinear taps) is close to difftex.sample's EWA on the
    # face (Gaussian-weighted texels): mean |difference| measured 0.021 (footprints ~0.6 texel) and 0.009
    # (~3 texels) on uniform noise, where anisotropic and sample's EWA differ by 0.014 and 0.029.
    S, n = 64, 300
    cube = torch.rand(1, 6, 3, S, S, dtype=F64, generator=torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(3)
    uv = torch.rand(n, 2, generator=g, dtype=F64) * 0.4 + 0.3
    face = torch.full((n,), 4)
    V = lambda t: t.view(1, 1, n, -1)
    for s, tol in ((0.01, 0.03), (0.05, 0.015)):
        du = torch.randn(n, 2, generator=g, dtype=F64) * s
        dv = torch.randn(n, 2, generator=g, dtype=F64) * s * 0.3
        # d(direction) / d(uv) by central differences of the exact map (the direction's length does not matter).
        e = 1e-6
        dd = [(cube_to_direction(face, uv + e * x) - cube_to_direction(face, uv - e * x)) / (2 * e) for x in (du, dv)]
        got = cubemap(cube, V(cube_to_direction(face, uv)), filter="ewa", dirs_dx=V(dd[0]), dirs_dy=V(dd[1]))
        want = difftex.sample(cube[:, 4], V(uv), filter="ewa", uv_dx=V(du), uv_dy=V(dv), wrap="clamp")
        assert (got - want).abs().mean() < tol, (s, (got - want).abs().mean())
    # A vanishing footprint is one bilinear tap.
    tiny = cubemap(cube, V(cube_to_direction(face, uv)), filter="ewa", dirs_dx=V(dd[0]) * 1e-9,
                   dirs_dy=V(dd[1]) * 1e-9)
    torch.testing.assert_close(tiny, difftex.sample(cube[:, 4], V(uv), wrap="clamp"), rtol=0, atol=1e-12)


def test_ewa_gradient_reaches_every_level():
    S = 8
    g = torch.Generator().manual_seed(12)
    levels = [lv.detach().requires_grad_() for lv in cube_mipmap(torch.rand(1, 6, 2, S, S, dtype=F64, generator=g))]
    d = torch.randn(1, 1, 64, 3, dtype=F64, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    dx, dy = tangent_derivs(d, 1.0)
    scale = torch.logspace(-2, 1, 64, dtype=F64).view(1, 1, 64, 1)  # footprints from 0.04 to 40 texels
    cubemap(CubeMipmap(levels), d, filter="ewa", dirs_dx=dx * scale, dirs_dy=dy * scale * 0.5).sum().backward()
    assert all(lv.grad.abs().sum() > 0 for lv in levels), [lv.grad.abs().sum().item() for lv in levels]


def test_ewa_nonfinite_and_degenerate_footprints():
    # A NaN / infinite / zero derivative: finite values and gradients (one tap, or the coarsest level).
    cube, d = grad_inputs()
    n = d.shape[2]
    dx = torch.full_like(d, 0.1).detach()
    dx[0, 0, 0, 0], dx[0, 0, 1, 1], dx[0, 0, 2] = float("nan"), float("inf"), 0.0
    dx.requires_grad_()
    dy = torch.zeros_like(dx, requires_grad=True)
    out = cubemap(cube, d, filter="ewa", dirs_dx=dx, dirs_dy=dy)
    assert out.shape == (1, 2, 1, n) and out.isfinite().all()
    gc, gd, gx, gy = torch.autograd.grad(out.sum(), (cube, d, dx, dy))
    assert gc.isfinite().all() and gx.isfinite().all() and gy.isfinite().all()
    # d's gradient where its derivative is NaN / infinite is NaN for every mip filter (direction_to_cube's
    # derivative maths); finite input keeps a finite gradient.
    assert gd[..., 2:, :].isfinite().all() and gd[..., 2, :].abs().sum() > 0  # a zero footprint: one tap


# ---------------------------------------------------------------- leftovers: odd faces, NaN footprints, tap counts


@pytest.mark.parametrize("S, sizes", [(5, [5, 3, 2, 1]), (7, [7, 4, 2, 1])])
def test_cube_mipmap_odd_faces_keep_every_texel(S, sizes):
    """Odd faces take mipmap's area-weighted box per face: no texel is dropped.

    Each level keeps every face's mean, and every base texel weighs the same in a level's sum ((n_k / S)^2
    each); level 1 of S = 5 averages texels 0, 1 of each axis with weights 3/5, 2/5."""
    cube = torch.rand(1, 6, 2, S, S, dtype=F64, generator=torch.Generator().manual_seed(11)).requires_grad_()
    mm = cube_mipmap(cube)
    assert [lv.shape[-1] for lv in mm] == sizes
    for lv in mm:
        n = lv.shape[-1]
        torch.testing.assert_close(lv.mean((-1, -2)), cube.mean((-1, -2)), rtol=0, atol=1e-14)
        (g,) = torch.autograd.grad(lv.sum(), cube, retain_graph=True)
        torch.testing.assert_close(g, torch.full_like(g, (n / S) ** 2), rtol=0, atol=1e-14)
    if S == 5:
        w = torch.tensor([0.6, 0.4], dtype=F64)
        want = (cube[0, 3, 1, :2, :2] * w[:, None] * w[None, :]).sum()
        torch.testing.assert_close(mm[1][0, 3, 1, 0, 0], want, rtol=0, atol=1e-15)


@pytest.mark.parametrize("filter", MIP)
def test_nan_derivative_stays_in_its_pixel(filter):
    """A NaN in one pixel's dirs_dx is a zero footprint there (lod's rule: level 0, one tap), on every
    backend: its value is the zero footprint's, every other pixel is unchanged, and the cube's gradient
    is exactly the one with that pixel's derivatives zero (finite; no NaN reaches the shared texels)."""
    S, p = 8, 7
    cube = torch.rand(1, 6, 2, S, S, dtype=F64, generator=torch.Generator().manual_seed(1)).requires_grad_()
    d = random_dirs(50, seed=3)
    dx, dy = tangent_derivs(d, 2.0 / S)
    nan_dx = dx.clone()
    nan_dx[0, 0, p, 1] = float("nan")
    zero_dx, zero_dy = dx.clone(), dy.clone()
    zero_dx[0, 0, p], zero_dy[0, 0, p] = 0.0, 0.0
    for backend in ("native", "reference"):
        with use_backend(backend):
            out = cubemap(cube, d, filter=filter, dirs_dx=nan_dx, dirs_dy=dy)
            (g,) = torch.autograd.grad(out.sum(), cube)
            want = cubemap(cube, d, filter=filter, dirs_dx=zero_dx, dirs_dy=zero_dy)
            (g0,) = torch.autograd.grad(want.sum(), cube)
            clean = cubemap(cube, d, filter=filter, dirs_dx=dx, dirs_dy=dy)
        assert out.isfinite().all() and g.isfinite().all(), backend
        torch.testing.assert_close(out, want, rtol=0, atol=1e-14)
        torch.testing.assert_close(g, g0, rtol=0, atol=1e-14)
        others = torch.arange(50) != p
        assert torch.equal(out[..., others], clean[..., others]), backend


@pytest.mark.parametrize("filter", ["anisotropic", "auto"])
def test_anisotropic_tap_count_does_not_jump_at_edges(filter, monkeypatch):
    """Within the edge band the tap count is the largest of the faces' measures, the same on both sides of
    an edge: pairs of directions 1e-9 apart across each of the 12 edges, with the same footprint, take as
    many taps (on per-face counts they differed at 13 (anisotropic) and 14 (auto) of the 24 pairs)."""
    import difftex.envmap.cube as cube_module
    seen = []
    spread = cube_module.spread_taps
    monkeypatch.setattr(cube_module, "spread_taps", lambda uv, axis, count: seen.append(count) or spread(uv, axis, count))
    S = 8
    cube = torch.rand(1, 6, 1, S, S, dtype=F64, generator=torch.Generator().manual_seed(2))
    g = torch.Generator().manual_seed(4)
    pairs = []
    for a in range(3):  # the 12 edges: two axes at +-1, the third free
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                for t in (-0.6, 0.35):
                    p = torch.zeros(3, dtype=F64)
                    p[a], p[(a + 1) % 3], p[(a + 2) % 3] = t, s1, s2
                    eps = torch.zeros(3, dtype=F64)
                    eps[(a + 1) % 3] = 1e-9 * s1
                    pairs += [p + eps, p - eps]  # either face of the edge
    d = torch.stack(pairs).view(1, 1, -1, 3)
    d = d / d.norm(dim=-1, keepdim=True)
    half = (1, 1, d.shape[2] // 2, 3)  # one footprint per pair
    dx = (torch.randn(half, generator=g, dtype=F64) * (3.0 / S)).repeat_interleave(2, 2)
    dy = (torch.randn(half, generator=g, dtype=F64) * (0.5 / S)).repeat_interleave(2, 2)
    cubemap(cube, d, filter=filter, dirs_dx=dx, dirs_dy=dy)
    count = seen[-1]
    faces = direction_to_cube(d)[0].view(-1)
    assert (faces[0::2] != faces[1::2]).all()  # each pair straddles an edge
    assert torch.equal(count[0::2], count[1::2]), (count[0::2], count[1::2])
    assert count.max() > 1

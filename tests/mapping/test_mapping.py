"""Tests for difftex.mapping: values, analytic screen-space derivatives, seams, poles, gradcheck."""

import math

import pytest
import torch

from difftex import envmap as E
from difftex import mapping as M

F64 = torch.float64
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
AXES = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=F64)

# Central differences with h = 1e-6 in float64: truncation O(h^2) and rounding
# O(1e-16 / h) keep the error far below this tolerance.
FD_H = 1e-6
FD_TOL = 1e-7


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _fd(fn, p, dp, h=FD_H):
    """Central difference of fn along dp (uv per unit of dp)."""
    return (fn(p + h * dp) - fn(p - h * dp)) / (2 * h)


# mapping name -> (uv-only function, function taking derivatives) on [..., 3] inputs
MAPPINGS = {
    "planar": lambda p, **k: M.planar_uv(p, (0.1, -0.2, 0.3), (0.5, 0.1, 0.0), (0.0, -0.4, 0.2), **k),
    "cylindrical": lambda p, **k: M.cylindrical_uv(p, (0.1, 0.2, -0.1), (0.0, 0.0, 2.0), **k),
    "cylindrical_tilted": lambda p, **k: M.cylindrical_uv(p, (0.0, 0.0, 0.0), (0.3, 1.0, 0.2), **k),
    "spherical": lambda p, **k: M.spherical_uv(p, (0.1, 0.2, -0.1), **k),
    "normal": lambda p, **k: M.normal_uv(p, **({"normals_dx": k["points_dx"], "normals_dy": k["points_dy"]} if k else {})),
    "equirect": lambda p, **k: E.direction_to_equirect_uv(p, **({"dirs_dx": k["points_dx"], "dirs_dy": k["points_dy"]} if k else {})),
    "cube": lambda p, **k: (lambda r: r[1] if not k else r[1:])(E.direction_to_cube(p, **({"dirs_dx": k["points_dx"], "dirs_dy": k["points_dy"]} if k else {}))),
    "box": lambda p, **k: M.box_uv(p, torch.tensor([0.2, -1.0, 0.3], dtype=p.dtype, device=p.device), center=(0.1, 0.0, 0.0), size=2.5, **k),
}


def _safe_points(n, seed):
    """Points away from every seam / pole / face edge of the mappings above."""
    g = _gen(seed)
    pts = []
    while len(pts) < n:
        p = torch.randn(3, generator=g, dtype=F64)
        q = p - torch.tensor([0.1, 0.2, -0.1], dtype=F64)
        # spherical / cylindrical (z axis): |phi| < pi - 0.3, r_xy > 0.3
        if q[:2].norm() < 0.3 or abs(math.atan2(q[1], q[0])) > math.pi - 0.3:
            continue
        if p[:2].norm() < 0.3 or abs(math.atan2(p[1], p[0])) > math.pi - 0.3:  # normal
            continue
        if math.hypot(p[0], p[2]) < 0.3 or abs(math.atan2(p[0], -p[2])) > math.pi - 0.3:  # equirect
            continue
        a = p.abs().sort().values  # cube: clear major axis
        if a[2] - a[1] < 0.2:
            continue
        pts.append(p)
    return torch.stack(pts)


# ----------------------------------------------------------------- values


def test_spherical_known_points():
    c = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    pts = torch.cat([AXES * 2.5, torch.zeros(1, 3, dtype=F64)]) + c
    uv = M.spherical_uv(pts, c)
    # +x: phi 0; -x: phi = pi (atan2(+0, -1)); +y: pi/2; -y: -pi/2; poles u = 0.5 by definition
    expected = [[0.5, 0.5], [1.0, 0.5], [0.75, 0.5], [0.25, 0.5], [0.5, 0.0], [0.5, 1.0], [0.5, 0.5]]
    assert torch.allclose(uv, torch.tensor(expected, dtype=F64), atol=1e-15)
    # a point at 45 degrees latitude: v = theta / pi = 0.25
    p = torch.tensor([[math.sqrt(0.5), 0.0, math.sqrt(0.5)]], dtype=F64)
    assert M.spherical_uv(p).flatten().tolist() == pytest.approx([0.5, 0.25], abs=1e-15)
    # the seed formula v = arccos(z / r) / pi on random points
    q = torch.randn(50, 3, generator=_gen(1), dtype=F64)
    ref_v = torch.arccos(q[:, 2] / q.norm(dim=1)) / math.pi
    ref_u = (torch.atan2(q[:, 1], q[:, 0]) + math.pi) / (2 * math.pi)
    assert torch.allclose(M.spherical_uv(q), torch.stack([ref_u, ref_v], 1), atol=1e-14)


def test_cylindrical_known_points():
    c = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    axis = torch.tensor([0.0, 0.0, 2.0], dtype=F64)  # height 4: z from -1 to 3
    pts = torch.tensor([[1, 0, 3], [0, 1, 1], [-1, 0, -1], [0, -1, 2], [0, 0, 1]], dtype=F64)
    uv = M.cylindrical_uv(pts, c, axis)
    expected = [[0.5, 0.0], [0.75, 0.5], [1.0, 1.0], [0.25, 0.25], [0.5, 0.5]]
    assert torch.allclose(uv, torch.tensor(expected, dtype=F64), atol=1e-15)
    # any axis: with axis +y and ref +z, phi is measured from z towards y x z = x
    uv = M.cylindrical_uv(torch.tensor([[0.0, 0.5, 1.0], [1.0, -0.5, 0.0]], dtype=F64), (0, 0, 0),
                          (0.0, 0.5, 0.0), ref=(0.0, 0.0, 1.0))
    assert uv.flatten().tolist() == pytest.approx([0.5, 0.0, 0.75, 1.0], abs=1e-15)
    # u of a z-axis cylinder equals the spherical u (documented default frame)
    q = torch.randn(20, 3, generator=_gen(2), dtype=F64)
    assert torch.allclose(M.cylindrical_uv(q, (0, 0, 0), (0, 0, 1.0))[:, 0], M.spherical_uv(q)[:, 0], atol=1e-14)


def test_planar_on_axes():
    pts = torch.tensor([[1.0, 1.0, 0.0], [3.0, 1.0, 0.0], [1.0, -1.0, 0.0], [3.0, -1.0, 5.0]], dtype=F64)
    # square [1, 3] x [-1, 1] in the z = 0 plane, image upright for y up
    uv = M.planar_uv(pts, (1.0, 1.0, 0.0), (0.5, 0.0, 0.0), (0.0, -0.5, 0.0))
    assert uv.tolist() == [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]


def test_normal_uv_is_spherical_of_normal():
    n = torch.randn(30, 3, generator=_gen(3), dtype=F64)
    assert torch.allclose(M.normal_uv(n), M.spherical_uv(n), atol=0)
    assert torch.allclose(M.normal_uv(n * 7.0), M.normal_uv(n), atol=1e-15)


def test_equirect_convention_and_inverse():
    uv = E.direction_to_equirect_uv(AXES)
    #            +x           -x            +y (up)      -y           +z (seam)    -z (front)
    expected = [[0.75, 0.5], [0.25, 0.5], [0.5, 0.0], [0.5, 1.0], [1.0, 0.5], [0.5, 0.5]]
    assert torch.allclose(uv, torch.tensor(expected, dtype=F64), atol=1e-15)
    d = torch.nn.functional.normalize(torch.randn(100, 3, generator=_gen(4), dtype=F64), dim=-1)
    assert torch.allclose(E.equirect_uv_to_direction(E.direction_to_equirect_uv(d)), d, atol=1e-13)
    uv = torch.rand(100, 2, generator=_gen(5), dtype=F64) * 0.98 + 0.01
    assert torch.allclose(E.direction_to_equirect_uv(E.equirect_uv_to_direction(uv)), uv, atol=1e-13)


def test_cube_faces_centres_and_orientation():
    face, uv = E.direction_to_cube(AXES * 3.0)
    assert face.tolist() == [0, 1, 2, 3, 4, 5]
    assert torch.equal(uv, torch.full((6, 2), 0.5, dtype=F64))
    assert M.CUBE_FACES == ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
    # OpenGL table 8.19, one direction per face with (s_c, t_c) = (+0.5, +0.5) |m_a| -> uv (0.75, 0.75)
    dirs = torch.tensor([[1, -1, -1], [-1, -1, 1], [1, 1, 1], [1, -1, -1], [1, -1, 1], [-1, -1, -1]], dtype=F64)
    # add a bias on the major axis so the face is unambiguous
    dirs = dirs * 0.5 + AXES * 0.5
    face, uv = E.direction_to_cube(dirs)
    assert face.tolist() == [0, 1, 2, 3, 4, 5]
    assert torch.allclose(uv, torch.full((6, 2), 0.75, dtype=F64), atol=1e-15)
    # round trip through cube_to_direction
    d = torch.randn(200, 3, generator=_gen(6), dtype=F64)
    face, uv = E.direction_to_cube(d)
    back = E.cube_to_direction(face, uv)
    assert torch.allclose(back, d / d.abs().amax(dim=-1, keepdim=True), atol=1e-14)


def test_box_uv_faces_and_layouts():
    # on the surface of the box, box_uv equals the cube map of (p - center)
    c = torch.tensor([0.5, -1.0, 2.0], dtype=F64)
    g = _gen(7)
    d = torch.randn(200, 3, generator=g, dtype=F64)
    d = d / d.abs().amax(dim=-1, keepdim=True)  # on [-1, 1]^3's surface
    face_n = torch.argmax(d.abs(), dim=-1)
    normals = torch.zeros_like(d).scatter(-1, face_n[:, None], torch.gather(d, -1, face_n[:, None]).sign())
    uv = M.box_uv(c + 1.5 * d, normals, center=c, size=3.0)
    face, uv_cube = E.direction_to_cube(d)
    assert torch.allclose(uv, uv_cube, atol=1e-14)
    # the face comes from the normal, not the position: a point on the +X side
    # with a +Y normal is projected along y
    p = torch.tensor([[0.5, 0.1, 0.25]], dtype=F64)
    # +Y face: (s_c, t_c) = (x, z) / half size -> uv ((1 + 1) / 2, (0.5 + 1) / 2)
    assert M.box_uv(p, torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)).flatten().tolist() == pytest.approx([1.0, 0.75], abs=1e-15)
    # atlas: face f goes to column f % 3, row f // 3
    uv_atlas = M.box_uv(c + 1.5 * d, normals, center=c, size=3.0, layout="atlas")
    cell = torch.stack([face % 3, face // 3], -1).to(F64)
    assert torch.allclose(uv_atlas, (uv_cube + cell) / torch.tensor([3.0, 2.0], dtype=F64), atol=1e-14)


def test_batched_shapes_broadcast_and_dtype():
    p = torch.randn(2, 4, 5, 3, generator=_gen(8))
    centers = torch.randn(2, 1, 1, 3, generator=_gen(9))
    uv = M.spherical_uv(p, centers)
    assert uv.shape == (2, 4, 5, 2) and uv.dtype == torch.float32
    assert torch.allclose(uv[1], M.spherical_uv(p[1], centers[1, 0, 0]))
    uv64 = M.spherical_uv(p.double(), centers.double())
    assert uv64.dtype == F64
    # float32 agrees with float64 away from the seam to float32 precision
    away = (uv64[..., 0] - 0.5).abs() < 0.45
    assert (uv.double() - uv64)[away].abs().max().item() < 1e-5
    out = M.cylindrical_uv(p, centers, torch.tensor([0.0, 1.0, 0.0]),
                           points_dx=torch.ones_like(p), points_dy=torch.ones(3))
    assert [t.shape for t in out] == [(2, 4, 5, 2)] * 3


@pytest.mark.parametrize("device", DEVICES)
def test_devices(device):
    p = torch.randn(10, 3, device=device, dtype=F64)
    for name, fn in MAPPINGS.items():
        out = fn(p, points_dx=torch.ones_like(p), points_dy=torch.ones_like(p))
        assert all(t.device == p.device and t.dtype == F64 for t in out), name
    uv = M.box_uv(p, p, layout="atlas")
    assert uv.device == p.device
    face, _ = E.direction_to_cube(p)
    assert E.cube_to_direction(face, torch.full((10, 2), 0.5, device=device)).device == p.device
    m = M.uv_transform(angle=torch.tensor(0.5, device=device))
    assert M.texture_matrix(torch.rand(10, 2, device=device), m).device == p.device


# ----------------------------------------------------------------- derivatives


@pytest.mark.parametrize("name", list(MAPPINGS))
def test_analytic_derivatives_match_finite_differences(name):
    fn = MAPPINGS[name]
    p = _safe_points(40, 10)
    g = _gen(11)
    dx = torch.randn(p.shape, generator=g, dtype=F64) * 0.01
    dy = torch.randn(p.shape, generator=g, dtype=F64) * 0.01
    uv, uv_dx, uv_dy = fn(p, points_dx=dx, points_dy=dy)
    assert torch.equal(uv, fn(p))
    # the derivative is linear in dp: compare per unit dp
    assert (uv_dx - _fd(fn, p, dx / 0.01) * 0.01).abs().max().item() < FD_TOL
    assert (uv_dy - _fd(fn, p, dy / 0.01) * 0.01).abs().max().item() < FD_TOL


@pytest.mark.parametrize("name", ["spherical", "cylindrical", "normal", "equirect"])
def test_seam_derivatives_do_not_jump(name):
    fn = MAPPINGS[name]
    c = torch.tensor([0.1, 0.2, -0.1], dtype=F64) if name in ("spherical", "cylindrical") else torch.zeros(3, dtype=F64)
    # a row of 64 "pixels" walking around the axis, through the seam
    t = torch.linspace(math.pi - 0.2, math.pi + 0.2, 64, dtype=F64)
    if name == "equirect":  # phi = atan2(x, -z), seam at +z
        p = torch.stack([torch.sin(t), 0.3 * torch.ones_like(t), -torch.cos(t)], -1)
        dp = torch.stack([torch.cos(t), torch.zeros_like(t), torch.sin(t)], -1) * (t[1] - t[0])
    else:  # phi = atan2(y, x), seam at -x
        p = c + torch.stack([torch.cos(t), torch.sin(t), 0.3 * torch.ones_like(t)], -1)
        dp = torch.stack([-torch.sin(t), torch.cos(t), torch.zeros_like(t)], -1) * (t[1] - t[0])
    uv, uv_dx, _ = fn(p, points_dx=dp, points_dy=dp)
    step = (t[1] - t[0]).item() / (2 * math.pi)  # the true du per pixel
    fd = uv[1:, 0] - uv[:-1, 0]
    assert fd.abs().max().item() > 0.9  # finite differences jump by a whole texture width
    assert torch.allclose(uv_dx[:, 0], torch.full_like(t, step), rtol=1e-12)  # analytic: constant
    assert (uv_dx[1:] - uv_dx[:-1]).abs().max().item() < 1e-12


def test_texture_matrix_derivatives_and_round_trip():
    uv = torch.rand(50, 2, generator=_gen(12), dtype=F64)
    m = M.uv_transform(torch.tensor([0.1, -0.3], dtype=F64), 0.7, torch.tensor([2.0, 0.5], dtype=F64))
    back = M.texture_matrix(M.texture_matrix(uv, m), torch.linalg.inv(m))
    assert (back - uv).abs().max().item() < 1e-14
    proj = m.clone()
    proj[2] = torch.tensor([0.2, -0.1, 1.0], dtype=F64)  # projective: w in [0.9, 1.2]
    back = M.texture_matrix(M.texture_matrix(uv, proj), torch.linalg.inv(proj))
    assert (back - uv).abs().max().item() < 1e-14
    du = torch.randn(50, 2, generator=_gen(13), dtype=F64)
    for mat in (m, proj):
        _, d1, d2 = M.texture_matrix(uv, mat, uv_dx=du, uv_dy=-du)
        fd = (M.texture_matrix(uv + FD_H * du, mat) - M.texture_matrix(uv - FD_H * du, mat)) / (2 * FD_H)
        assert (d1 - fd).abs().max().item() < FD_TOL and (d2 + fd).abs().max().item() < FD_TOL
    # affine: derivatives are the linear part
    assert torch.allclose(M.texture_matrix(uv, m, uv_dx=du, uv_dy=du)[1], du @ m[:2, :2].T, atol=1e-15)


def test_uv_transform_semantics():
    pts = torch.tensor([[0.5, 0.5], [1.0, 0.5], [1.0, 1.0]], dtype=F64)
    # rotation by pi/2 about the centre turns the u axis to +v (clockwise as displayed)
    r = M.texture_matrix(pts, M.uv_transform(angle=math.pi / 2, dtype=F64))
    assert torch.allclose(r, torch.tensor([[0.5, 0.5], [0.5, 1.0], [0.0, 1.0]], dtype=F64), atol=1e-15)
    s = M.texture_matrix(pts, M.uv_transform(scale=2.0, shift=(0.1, 0.0), dtype=F64))
    assert torch.allclose(s, torch.tensor([[0.6, 0.5], [1.6, 0.5], [1.6, 1.5]], dtype=F64), atol=1e-15)
    assert torch.equal(M.uv_transform(dtype=F64), torch.eye(3, dtype=F64))
    batch = M.uv_transform(angle=torch.tensor([0.0, 1.0, 2.0]), scale=torch.ones(3, 2))
    assert batch.shape == (3, 3, 3) and batch.dtype == torch.float32


# ----------------------------------------------------------------- gradcheck


@pytest.mark.parametrize("name", list(MAPPINGS))
def test_gradcheck(name):
    fn = MAPPINGS[name]
    p = _safe_points(4, 14).requires_grad_()
    g = _gen(15)
    dx = (torch.randn(p.shape, generator=g, dtype=F64) * 0.1).requires_grad_()
    dy = (torch.randn(p.shape, generator=g, dtype=F64) * 0.1).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c: fn(a, points_dx=b, points_dy=c), (p, dx, dy))


def test_gradcheck_parameters():
    p = _safe_points(4, 16)
    c = torch.tensor([0.1, 0.2, -0.1], dtype=F64, requires_grad=True)
    axis = torch.tensor([0.1, -0.2, 1.5], dtype=F64, requires_grad=True)
    dp = torch.randn(p.shape, generator=_gen(17), dtype=F64)
    assert torch.autograd.gradcheck(lambda c_, a_: M.cylindrical_uv(p, c_, a_, points_dx=dp, points_dy=dp), (c, axis))
    assert torch.autograd.gradcheck(lambda c_: M.spherical_uv(p, c_, points_dx=dp, points_dy=dp), (c,))
    o = torch.zeros(3, dtype=F64, requires_grad=True)
    au = torch.tensor([1.0, 0.2, 0.0], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda o_, a_: M.planar_uv(p, o_, a_, (0, 1.0, 0)), (o, au))
    size = torch.tensor(2.0, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c_, s_: M.box_uv(p, p, center=c_, size=s_), (c, size))
    uv = torch.rand(5, 2, generator=_gen(18), dtype=F64, requires_grad=True)
    ang = torch.tensor(0.3, dtype=F64, requires_grad=True)
    sh = torch.tensor([0.1, 0.2], dtype=F64, requires_grad=True)
    sc = torch.tensor([1.5, 0.7], dtype=F64, requires_grad=True)
    duv = torch.randn(5, 2, generator=_gen(19), dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda u, a, s1, s2, d: M.texture_matrix(u, M.uv_transform(s1, a, s2), uv_dx=d, uv_dy=2 * d),
        (uv, ang, sh, sc, duv))
    proj = torch.tensor([[1.0, 0.1, 0.0], [0.2, 0.9, 0.1], [0.1, -0.2, 1.0]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda u, m, d: M.texture_matrix(u, m, uv_dx=d, uv_dy=d), (uv, proj, duv))


# ----------------------------------------------------------------- singular points


SINGULAR = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -2.0], [0.0, 0.0, 0.0], [1e-12, 0.0, 0.5],
                         [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=F64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", ["spherical", "cylindrical", "normal", "equirect", "cube", "box"])
def test_poles_and_zero_vectors_are_finite(name, dtype):
    fn = MAPPINGS[name]
    c = torch.tensor([0.1, 0.2, -0.1], dtype=dtype) if name in ("spherical", "cylindrical") else 0.0
    p = (SINGULAR.to(dtype) + c).requires_grad_()
    dx = torch.full_like(p, 0.01).requires_grad_()
    dy = torch.tensor([0.01, -0.02, 0.03], dtype=dtype).expand_as(p).clone().requires_grad_()
    outs = fn(p, points_dx=dx, points_dy=dy)
    for o in outs:
        assert torch.isfinite(o).all(), name
    sum(o.sum() for o in outs).backward()
    for t in (p, dx, dy):
        assert t.grad is not None and torch.isfinite(t.grad).all(), name


def test_pole_values():
    # documented: within EPS of the axis u = 0.5 and the derivatives of phi and rho are 0
    # (the cone point has no linear derivative); at the centre v = 0.5 too
    ones = torch.ones(3, 3, dtype=F64)
    uv, dx, _ = M.spherical_uv(SINGULAR[:3], points_dx=ones, points_dy=ones)
    assert uv.tolist() == [[0.5, 0.0], [0.5, 1.0], [0.5, 0.5]]
    assert dx.tolist() == [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]
    _, cube_uv = E.direction_to_cube(torch.zeros(1, 3, dtype=F64))
    assert cube_uv.tolist() == [[0.5, 0.5]]
    assert E.direction_to_equirect_uv(torch.zeros(1, 3, dtype=F64)).tolist() == [[0.5, 0.5]]


def test_near_pole_derivatives_are_exact_outside_eps():
    # at rho = 1e-3 (>> EPS) the analytic derivative still matches finite differences
    p = torch.tensor([[1e-3, 2e-3, 1.0]], dtype=F64)
    d = torch.tensor([[0.3, -0.2, 0.1]], dtype=F64)
    _, uv_dx, _ = M.spherical_uv(p, points_dx=d, points_dy=d)
    fd = _fd(lambda q: M.spherical_uv(q), p, d, h=1e-8)
    assert (uv_dx - fd).abs().max().item() < 1e-5 * fd.abs().max().item()


# ----------------------------------------------------------------- bad input


def test_bad_inputs():
    p = torch.zeros(4, 3)
    with pytest.raises(ValueError, match=r"points must have shape \[\.\.\., 3\], got \(4, 2\)"):
        M.spherical_uv(torch.zeros(4, 2))
    with pytest.raises(TypeError, match="points must be a floating tensor.*int64"):
        M.spherical_uv(torch.zeros(4, 3, dtype=torch.int64))
    with pytest.raises(TypeError, match="points must be a torch.Tensor"):
        M.spherical_uv([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match=r"center must have shape \[\.\.\., 3\], got \(2,\)"):
        M.spherical_uv(p, (0.0, 0.0))
    with pytest.raises(ValueError, match=r"axis must have shape \[\.\.\., 3\], got \(4,\)"):
        M.cylindrical_uv(p, (0, 0, 0), (0.0, 0.0, 1.0, 0.0))
    with pytest.raises(ValueError, match=r"axis_v must have shape"):
        M.planar_uv(p, (0, 0, 0), (1.0, 0, 0), (0.0, 1.0))
    with pytest.raises(ValueError, match="points_dx and points_dy must be given together, got only points_dx"):
        M.spherical_uv(p, points_dx=p)
    with pytest.raises(ValueError, match=r"points_dy must have shape \[\.\.\., 3\], got \(4, 2\)"):
        M.spherical_uv(p, points_dx=p, points_dy=torch.zeros(4, 2))
    with pytest.raises(ValueError, match=r"points_dx must broadcast with points \(4, 3\), got \(5, 3\)"):
        M.spherical_uv(p, points_dx=torch.zeros(5, 3), points_dy=p)
    with pytest.raises(ValueError, match=r"normals must have shape"):
        M.normal_uv(torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"dirs must have shape"):
        E.direction_to_cube(torch.zeros(2, 4))
    with pytest.raises(ValueError, match=r"dirs must have shape"):
        E.direction_to_equirect_uv(torch.zeros(2, 2))
    with pytest.raises(ValueError, match="layout must be 'shared' or 'atlas'"):
        M.box_uv(p, p, layout="cross")
    with pytest.raises(ValueError, match=r"normals must have shape"):
        M.box_uv(p, torch.zeros(4, 2))
    with pytest.raises(ValueError, match=r"matrix must have shape \[\.\.\., 3, 3\], got \(2, 3\)"):
        M.texture_matrix(torch.zeros(4, 2), torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"uv must have shape \[\.\.\., 2\], got \(4, 3\)"):
        M.texture_matrix(torch.zeros(4, 3), torch.eye(3))
    with pytest.raises(ValueError, match=r"scale must be a number or have shape \[\.\.\., 2\], got \(3,\)"):
        M.uv_transform(scale=torch.ones(3))
    with pytest.raises(ValueError, match=r"shift must have shape"):
        M.uv_transform(shift=1.0)
    with pytest.raises(ValueError, match=r"face must have shape"):
        E.cube_to_direction(torch.zeros(3, dtype=torch.long), torch.zeros(4, 2))
    # Parameters and batches that do not broadcast: ValueError naming the argument.
    with pytest.raises(ValueError, match=r"origin must broadcast with points \(4, 3\), got \(5, 3\)"):
        M.planar_uv(p, torch.zeros(5, 3), (1.0, 0, 0), (0, 1.0, 0))
    with pytest.raises(ValueError, match=r"center must broadcast with points \(4, 3\), got \(5, 3\)"):
        M.spherical_uv(p, torch.zeros(5, 3))
    with pytest.raises(ValueError, match=r"axis must broadcast"):
        M.cylindrical_uv(p, (0, 0, 0), torch.ones(5, 3))
    with pytest.raises(ValueError, match=r"size must broadcast with points' batch shape \(4,\), got \(5,\)"):
        M.box_uv(p, p, size=torch.ones(5))
    with pytest.raises(ValueError, match=r"matrix's batch shape must broadcast with uv's \(4,\), got \(5,\)"):
        M.texture_matrix(torch.zeros(4, 2), torch.eye(3).expand(5, 3, 3))
    uv2 = torch.full((3, 2), 0.5)
    for face in ([-1, 0, 1], [0, 6, 2]):
        with pytest.raises(ValueError, match=r"face must hold values 0\.\.5, got values in"):
            E.cube_to_direction(torch.tensor(face), uv2)
    with pytest.raises(TypeError, match="face must be an integer tensor.*bool"):
        E.cube_to_direction(torch.ones(3, dtype=torch.bool), uv2)
    with pytest.raises(TypeError, match="dtype must be a floating dtype, got torch.int64"):
        M.uv_transform(dtype=torch.int64)


def test_integer_tensor_arguments_do_not_truncate_uv_transform():
    # An int scale / angle used to make the matrix int64, dropping shift and centre.
    ref = M.uv_transform(shift=(0.1, 0.0), scale=2.0)
    torch.testing.assert_close(ref[:2, 2], torch.tensor([-0.4, -0.5]))
    got = M.uv_transform(shift=(0.1, 0.0), scale=torch.tensor(2))
    assert got.dtype == torch.get_default_dtype()
    torch.testing.assert_close(got, ref)
    got = M.uv_transform(shift=(0.25, 0.25), angle=torch.tensor(0), scale=torch.tensor([2.0, 2.0], dtype=torch.float64))
    assert got.dtype == torch.float64
    torch.testing.assert_close(got[:2, 2], torch.tensor([-0.25, -0.25], dtype=torch.float64))


def test_derivatives_get_the_parameters_batch_shape():
    g = torch.Generator().manual_seed(3)
    p, dp = torch.randn(4, 3, generator=g), torch.randn(4, 3, generator=g)
    origin = torch.randn(2, 1, 3, generator=g)
    uv, dx, dy = M.planar_uv(p, origin, (1.0, 0, 0), (0, 1.0, 0), points_dx=dp, points_dy=-dp)
    assert uv.shape == dx.shape == dy.shape == (2, 4, 2)
    torch.testing.assert_close(dx[1], dp[:, :2])
    torch.testing.assert_close(dy[0], -dp[:, :2])


# ----------------------------------------------------------------- non-finite input and extremes


def nonfinite_stays_in_its_element(fn, params, dtype=F64):
    """Check ``fn(points, params, points_dx, points_dy) -> (uv, uv_dx, uv_dy)`` on 6 points where point 0
    holds a NaN, point 1 an inf and point 3's dx a NaN: those elements (and only those) are NaN, and a loss
    over the other elements gives the shared parameters the gradients of the same loss on the good points alone.

    Shared by the envmap tests (tests/envmap/test_directions.py).
    """
    g = _gen(40)
    p = torch.randn(6, 3, generator=g, dtype=dtype)
    dx, dy = torch.randn(6, 3, generator=g, dtype=dtype), torch.randn(6, 3, generator=g, dtype=dtype)
    p[0, 0], p[1, 2], dx[3, 1] = float("nan"), float("inf"), float("nan")
    good, good_d = [2, 3, 4, 5], [2, 4, 5]

    def loss(idx, idx_d):
        for t in params:
            t.grad = None
        uv, uv_dx, uv_dy = fn(p[idx], params, dx[idx], dy[idx])
        pos_d = [idx.index(i) for i in idx_d]
        (uv.sum() + uv_dx[pos_d].sum() + uv_dy.sum()).backward()
        return uv, uv_dx, [t.grad.clone() for t in params]

    uv, uv_dx, uv_dy = fn(p, params, dx, dy)
    assert torch.isnan(uv[:2]).all() and torch.isfinite(uv[2:]).all()
    assert torch.isnan(uv_dx[[0, 1, 3]]).all() and torch.isfinite(uv_dx[good_d]).all()
    assert torch.isnan(uv_dy[:2]).all() and torch.isfinite(uv_dy[2:]).all()
    want_uv, want_dx, want_grads = loss(good, good_d)
    got_uv, got_dx, got_grads = loss(list(range(6)), good_d)
    torch.testing.assert_close(got_uv[good], want_uv, rtol=0, atol=0)
    torch.testing.assert_close(got_dx[good_d], want_dx[[0, 2, 3]], rtol=0, atol=0)
    for got, want in zip(got_grads, want_grads):
        assert torch.isfinite(want).all()
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_nonfinite_point_stays_in_its_element_spherical():
    c = torch.tensor([0.1, 0.2, -0.3], dtype=F64, requires_grad=True)
    nonfinite_stays_in_its_element(lambda p, ps, dx, dy: M.spherical_uv(p, ps[0], points_dx=dx, points_dy=dy), [c])


def test_nonfinite_point_stays_in_its_element_cylindrical():
    c = torch.tensor([0.1, 0.2, -0.3], dtype=F64, requires_grad=True)
    axis = torch.tensor([0.2, 0.1, 1.5], dtype=F64, requires_grad=True)
    ref = torch.tensor([1.0, 0.3, 0.1], dtype=F64, requires_grad=True)
    nonfinite_stays_in_its_element(
        lambda p, ps, dx, dy: M.cylindrical_uv(p, ps[0], ps[1], ref=ps[2], points_dx=dx, points_dy=dy),
        [c, axis, ref])


def test_nonfinite_point_stays_in_its_element_normal():
    # A shared offset of the normals stands in for any parameter the normals come from.
    t = torch.tensor([0.1, 0.2, -0.3], dtype=F64, requires_grad=True)
    nonfinite_stays_in_its_element(lambda n, ps, dx, dy: M.normal_uv(n + ps[0], normals_dx=dx, normals_dy=dy), [t])


def test_spherical_does_not_overflow_the_squared_radius():
    # float32 squares overflow past ~1.8e19: r_xy^2 = inf made v = 0.5 (theta = pi / 2) at 45 degrees latitude.
    p = torch.tensor([[1e20, 0.0, 1e20], [-3e30, 4e30, 5e30], [3.0, 4.0, 5.0]])
    dp = torch.tensor([[0.0, 1e20, 0.0], [1e30, 2e30, -1e30], [1.0, 2.0, -1.0]])
    uv, uv_dx, _ = M.spherical_uv(p, points_dx=dp, points_dy=dp)
    ref, ref_dx, _ = M.spherical_uv(p.double(), points_dx=dp.double(), points_dy=dp.double())
    torch.testing.assert_close(uv[0], torch.tensor([0.5, 0.25]), rtol=0, atol=1e-7)
    torch.testing.assert_close(uv.double(), ref, rtol=0, atol=1e-6)
    torch.testing.assert_close(uv_dx.double(), ref_dx, rtol=1e-5, atol=0)
    # and the scale-free derivative: d(u)/dy at (1, 0) is 1 / (2 pi r)
    assert uv_dx[0, 0].item() == pytest.approx(1 / (2 * math.pi), rel=1e-6)


def test_texture_matrix_at_infinity():
    # w = 0 (a point at infinity): +-inf in both coordinates, +inf for x = 0 (was 0 / 0 = NaN),
    # +inf derivatives, and no NaN in the gradients.
    m = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=F64, requires_grad=True)
    uv = torch.tensor([[0.0, 0.5], [0.0, -0.5], [2.0, 1.0]], dtype=F64, requires_grad=True)
    ones = torch.ones(3, 2, dtype=F64)
    out, dx, _ = M.texture_matrix(uv, m, uv_dx=ones, uv_dy=ones)
    assert out[:2].tolist() == [[math.inf, math.inf], [math.inf, -math.inf]]
    assert out[2].tolist() == [1.0, 0.5]
    assert dx[:2].tolist() == [[math.inf] * 2] * 2
    out[2].sum().backward()
    # d(x / w)/d(m) and d/d(uv) at the finite point only: u = 2, v = 1, w = 2
    want_m = torch.tensor([[1.0, 0.5, 0.5], [1.0, 0.5, 0.5], [-1.5, -0.75, -0.75]], dtype=F64)
    torch.testing.assert_close(m.grad, want_m, rtol=0, atol=1e-15)
    torch.testing.assert_close(uv.grad, torch.tensor([[0.0, 0.0], [0.0, 0.0], [-0.25, 0.5]], dtype=F64),
                               rtol=0, atol=1e-15)


def test_cylindrical_ref_parallel_to_axis_raises():
    p = torch.randn(4, 3, generator=_gen(41), dtype=F64)
    for ref in ((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), (0.0, 0.0, 0.0), (1e-10, 0.0, 1.0)):
        with pytest.raises(ValueError, match=r"ref: must not be parallel to axis .*got ref \[.*\] with axis "
                                             r"\[0\.0, 0\.0, 1\.0\]"):
            M.cylindrical_uv(p, (0, 0, 0), (0.0, 0.0, 1.0), ref=ref)
    # one bad ref in a batch is enough, and the message shows that one
    refs = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 3.0]], dtype=F64)
    with pytest.raises(ValueError, match=r"got ref \[0\.0, 0\.0, 3\.0\]"):
        M.cylindrical_uv(p[:2], (0, 0, 0), (0.0, 0.0, 1.0), ref=refs)
    # float32 rounds the projection of a 1e-6 rad tilt to noise: refused there, not in float64
    with pytest.raises(ValueError, match="ref: must not be parallel"):
        M.cylindrical_uv(p.float(), (0, 0, 0), (0.0, 0.0, 1.0), ref=(1e-6, 0.0, 1.0))
    # a small but clear angle still works
    uv = M.cylindrical_uv(torch.tensor([[1.0, 0.0, 0.0]], dtype=F64), (0, 0, 0), (0.0, 0.0, 1.0), ref=(1e-2, 0, 1))
    assert uv[0, 0].item() == pytest.approx(0.5, abs=1e-12)


def test_non_numeric_parameters_name_the_argument():
    # torch.as_tensor's own message was "new(): invalid data type 'str'", naming nothing.
    p = torch.zeros(4, 3)
    cases = [
        (lambda: M.planar_uv(p, (0, 0, 0), "abc", (0, 1.0, 0)), r"axis_u must be a tensor or numbers of shape "
                                                                  r"\[\.\.\., 3\], got str 'abc'"),
        (lambda: M.spherical_uv(p, "origin"), r"center must be a tensor or numbers of shape \[\.\.\., 3\], got str"),
        (lambda: M.cylindrical_uv(p, (0, 0, 0), (0, 0, 1.0), ref=[1.0, "x", 0]), r"ref must be a tensor or numbers"),
        (lambda: M.box_uv(p, p, size="2"), r"size must be a tensor or numbers of shape \[\.\.\.\].*got str '2'"),
        (lambda: M.uv_transform(angle="1"), r"angle must be a tensor or numbers of shape \[\.\.\.\], got str '1'"),
        (lambda: M.uv_transform(shift="ab"), r"shift must be a tensor or numbers of shape \[\.\.\., 2\], got str"),
        (lambda: M.uv_transform(scale=None), r"scale must be a tensor or numbers .*got NoneType None"),
        (lambda: M.uv_transform(center={"u": 0.5}), r"center must be a tensor or numbers of shape \[\.\.\., 2\]"),
    ]
    for fn, match in cases:
        with pytest.raises(TypeError, match=match):
            fn()


def test_box_uv_size_must_be_positive():
    # 2 / size: size 0 gave inf / NaN uv, a negative size a mirrored box.
    p = torch.rand(3, 3, generator=_gen(42), dtype=F64)
    for size in (0.0, -1.0, float("nan"), torch.tensor([1.0, 0.0, 2.0], dtype=F64)):
        with pytest.raises(ValueError, match=r"size must be positive \(the box's edge length\), got (0\.0|-1\.0|nan)"):
            M.box_uv(p, p, size=size)
    # an int tensor size is a float size
    torch.testing.assert_close(M.box_uv(p, p, size=torch.tensor(2)), M.box_uv(p, p, size=2.0), rtol=0, atol=0)

"""blinn_phong against a hand computation, the texture modes, gradients and bad input."""
import math

import pytest
import torch

from difftex.shading import blinn_phong, combine


def _unit(v):
    n = math.sqrt(sum(x * x for x in v))
    return [x / n for x in v]


def _dot(a, b):
    return sum(x * y for x, y in zip(a, b))


def _hand(n, v, lights, colors, kd, ks, s, ambient):
    """The formula written out with scalars, channel by channel."""
    n, v = _unit(n), _unit(v)
    out = []
    for c in range(len(kd)):
        total = ambient[c] * kd[c]
        for l, col in zip(lights, colors):
            l = _unit(l)
            h = _unit([a + b for a, b in zip(l, v)])
            total += col[c] * (kd[c] * max(_dot(n, l), 0.0) + ks[c] * max(_dot(n, h), 0.0) ** s)
        out.append(total)
    return out


NORMALS = [[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.3, -0.2, 0.9]]
VIEWS = [[0.0, 0.0, 1.0], [0.2, 0.5, 1.0], [-0.4, 0.1, 0.8]]
LIGHTS = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [-1.0, 0.3, -0.2]]  # the last is below the first point's horizon
COLORS = [[1.0, 1.0, 1.0], [0.5, 0.2, 0.1], [2.0, 1.0, 0.5]]
KD = [[0.8, 0.5, 0.2], [0.1, 0.9, 0.4], [0.3, 0.3, 0.3]]
KS = [0.4, 0.25, 0.1]


def test_blinn_phong_matches_the_hand_computation_with_three_lights(dtype, device):
    t = lambda x: torch.tensor(x, dtype=dtype, device=device)
    out = blinn_phong(t(NORMALS), t(VIEWS), t(LIGHTS), t(KD), t(KS)[:, None], 7.5,
                      ambient=t([0.1, 0.2, 0.05]), light_colors=t(COLORS))
    assert out.shape == (3, 3) and out.dtype == dtype
    want = [_hand(NORMALS[i], VIEWS[i], LIGHTS, COLORS, KD[i], [KS[i]] * 3, 7.5, [0.1, 0.2, 0.05]) for i in range(3)]
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(out, t(want), atol=tol, rtol=tol)
    # The first point under the light along n = v alone: exactly kd + ks (n.l = n.h = 1).
    one = blinn_phong(t([0.0, 0.0, 2.0]), t([0.0, 0.0, 1.0]), t([0.0, 0.0, 5.0]), t(KD[0]), 0.4, 7.5)
    torch.testing.assert_close(one, t(KD[0]) + 0.4, atol=tol, rtol=0)


def test_one_light_per_point_and_broadcasting():
    # Per-point light directions [P, 1, 3] against a shared normal [3]; kd a number gives C = 1.
    lights = torch.tensor([[[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]], [[0.6, 0.0, 0.8]]])
    out = blinn_phong(torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, 1.0]), lights, 0.5, 0.0)
    torch.testing.assert_close(out, torch.tensor([[0.5], [0.0], [0.4]]))


def test_specular_zero_and_gradients_finite_where_n_dot_h_is_zero():
    # v = l perpendicular to n: h is perpendicular too, so n.h = 0 exactly; fractional exponent.
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64, requires_grad=True)
    v = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    s = torch.tensor([0.5], dtype=torch.float64, requires_grad=True)
    out = blinn_phong(n, v, v.detach().unsqueeze(-2), 0.0, 1.0, s)
    assert float(out.detach()) == 0.0
    out.sum().backward()
    for g in (n.grad, v.grad, s.grad):
        assert torch.isfinite(g).all()
    # Opposite light and view: zero half vector, still finite.
    out = blinn_phong(n, -v, v.detach().unsqueeze(-2), 0.5, 1.0, 0.5)
    assert torch.isfinite(out).all()


def test_energy_normalised_form_and_ambient_occlusion():
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    out = blinn_phong(z, z, z, 0.6, 0.3, 16.0, normalized=True)
    torch.testing.assert_close(out, torch.tensor([0.6 / math.pi + 0.3 * 24 / (8 * math.pi)], dtype=torch.float64))
    # Occlusion multiplies the ambient term only: 0.2 * 0.6 * 0.25 + 0.6 * cos 60deg.
    l = torch.tensor([math.sin(math.pi / 3), 0.0, 0.5], dtype=torch.float64)
    occ = blinn_phong(z, z, l, 0.6, ambient=0.2, occlusion=torch.tensor([0.25], dtype=torch.float64))
    torch.testing.assert_close(occ, torch.tensor([0.2 * 0.6 * 0.25 + 0.6 * 0.5], dtype=torch.float64))


def test_blinn_phong_gradcheck():
    g = torch.Generator().manual_seed(3)
    r = lambda *s: torch.randn(*s, dtype=torch.float64, generator=g)
    n, v = r(4, 3) + torch.tensor([0, 0, 2.0], dtype=torch.float64), r(4, 3) + torch.tensor([0, 0, 2.0], dtype=torch.float64)
    lights = r(4, 2, 3) + torch.tensor([0, 0, 1.5], dtype=torch.float64)
    kd, ks = torch.rand(4, 3, dtype=torch.float64, generator=g), torch.rand(4, 1, dtype=torch.float64, generator=g)
    s = 2.5 + torch.rand(4, 1, dtype=torch.float64, generator=g)
    cols = torch.rand(2, 3, dtype=torch.float64, generator=g)
    occ = torch.rand(4, 1, dtype=torch.float64, generator=g)
    args = [t.requires_grad_() for t in (n, v, lights, kd, ks, s, cols, occ)]
    for normalized in (False, True):
        f = lambda n, v, l, kd, ks, s, c, o: blinn_phong(n, v, l, kd, ks, s, ambient=0.1, light_colors=c,
                                                          occlusion=o, normalized=normalized)
        assert torch.autograd.gradcheck(f, args)


def test_replace_and_modulate_differ_exactly_as_defined():
    tex = torch.rand(2, 5, 5, 3)
    shading = torch.rand(2, 5, 5, 1) * 2
    rep, mod = combine(tex, shading, "replace"), combine(tex, shading, "modulate")
    assert torch.equal(rep, tex.expand(2, 5, 5, 3))
    assert torch.equal(mod, rep * shading)
    assert not torch.equal(rep, mod)


def test_decal_mixes_by_the_texture_alpha():
    rgba = torch.tensor([[0.2, 0.4, 0.6, 0.0], [0.2, 0.4, 0.6, 1.0], [0.2, 0.4, 0.6, 0.25]])
    shading = torch.tensor([[1.0, 0.5, 0.0]])
    out = combine(rgba, shading, "decal")
    torch.testing.assert_close(out, torch.tensor([[1.0, 0.5, 0.0], [0.2, 0.4, 0.6],
                                                  [0.25 * 0.2 + 0.75, 0.25 * 0.4 + 0.375, 0.25 * 0.6]]))
    t = torch.rand(3, 4, dtype=torch.float64, requires_grad=True)
    s = torch.rand(3, 3, dtype=torch.float64, requires_grad=True)
    for mode, tt in (("decal", t), ("modulate", t[:, :3]), ("replace", t[:, :3])):
        assert torch.autograd.gradcheck(lambda a, b: combine(a, b, mode), (tt.detach().requires_grad_(), s))


def test_bad_input():
    z = torch.tensor([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match=r"normals: expected last dimension 3"):
        blinn_phong(torch.zeros(4, 2), z, z, 0.5)
    with pytest.raises(TypeError, match=r"view_dirs: expected dtype torch.float32 like normals"):
        blinn_phong(z, z.double(), z, 0.5)
    with pytest.raises(TypeError, match=r"kd: expected a floating-point tensor"):
        blinn_phong(z, z, z, torch.ones(3, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"ks: expected a number or a float tensor"):
        blinn_phong(z, z, z, 0.5, "shiny")
    with pytest.raises(ValueError, match=r"shininess: expected values > 0"):
        blinn_phong(z, z, z, 0.5, 0.5, 0.0)
    with pytest.raises(ValueError, match=r"light_colors: expected 2 lights on dimension -2"):
        blinn_phong(z, z, torch.ones(2, 3), 0.5, light_colors=torch.ones(3, 3))
    with pytest.raises(ValueError, match=r"shapes do not broadcast \(normals \(4,\), view_dirs \(5,\)"):
        blinn_phong(torch.ones(4, 3), torch.ones(5, 3), z, 0.5)
    with pytest.raises(ValueError, match=r"mode: unknown mode 'add'"):
        combine(torch.ones(2, 3), 0.5, "add")
    with pytest.raises(ValueError, match=r"texture: 'decal' needs colour and alpha"):
        combine(torch.ones(2, 1), 0.5, "decal")
    with pytest.raises(TypeError, match=r"shading: expected dtype torch.float32 like texture"):
        combine(torch.ones(2, 3), torch.ones(2, 3, dtype=torch.float64))


def test_unit_is_exact_within_its_documented_range_and_finite_beyond():
    # unit() takes |x| from the squares in one pass (a rescaling pass cost 1.5-3x on shading's per-pixel calls):
    # exact for lengths within [1e-18, 1e18] (float32), finite beyond.
    from difftex.geometry.mesh import unit
    for dtype, inside, beyond in ((torch.float32, [1e-18, 1.0, 1e18], [1e-22, 1e-23, 1e-40, 1e25, 3e38]),
                                  (torch.float64, [1e-153, 1e153], [1e-160, 1e-300, 1e200])):
        for t in inside + beyond:
            x = torch.tensor([[t, t, 0.0], [0.0, 0.0, -t]], dtype=dtype)
            n = unit(x).norm(dim=-1)
            assert torch.isfinite(unit(x)).all(), (dtype, t)
            if t in inside:
                torch.testing.assert_close(n, torch.ones(2, dtype=dtype), atol=1e-6, rtol=0)
    assert torch.equal(unit(torch.zeros(1, 3)), torch.zeros(1, 3))

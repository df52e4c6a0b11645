"""Tests for difftex.envmap.directions beyond the shared mapping tests (tests/mapping/test_mapping.py)."""
import torch

from difftex.envmap import directions as D
from tests.mapping.test_mapping import F64, nonfinite_stays_in_its_element


def test_nonfinite_direction_stays_in_its_element_equirect():
    # A shared offset of the directions stands in for any parameter they come from (a reflection's normal).
    t = torch.tensor([0.1, 0.2, -0.3], dtype=F64, requires_grad=True)
    nonfinite_stays_in_its_element(
        lambda d, ps, dx, dy: D.direction_to_equirect_uv(d + ps[0], dirs_dx=dx, dirs_dy=dy), [t])


def test_short_directions_map_as_unit_ones():
    # A floor of 1e-9 on the cube's m_a, and the equirect axis test (an absolute length), once sent directions
    # shorter than 1e-9 to the face centre / the pole.
    g = torch.Generator().manual_seed(3)
    for dtype, scale in ((torch.float32, 1e-18), (F64, 1e-100)):
        d, dx, dy = (torch.randn(64, 3, generator=g, dtype=dtype) * s for s in (1.0, 0.1, 0.1))
        tol = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
        face, *uvs = D.direction_to_cube(d, dirs_dx=dx, dirs_dy=dy)
        face_s, *uvs_s = D.direction_to_cube(d * scale, dirs_dx=dx * scale, dirs_dy=dy * scale)
        assert torch.equal(face, face_s)
        for a, b in zip(uvs, uvs_s):
            torch.testing.assert_close(b, a, **tol)
        for a, b in zip(D.direction_to_equirect_uv(d, dirs_dx=dx, dirs_dy=dy),
                        D.direction_to_equirect_uv(d * scale, dirs_dx=dx * scale, dirs_dy=dy * scale)):
            torch.testing.assert_close(b, a, **tol)

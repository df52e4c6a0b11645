"""Tests for difftex.envmap.directions beyond the shared mapping tests (tests/mapping/test_mapping.py)."""
import torch

from difftex.envmap import directions as D
from tests.mapping.test_mapping import F64, nonfinite_stays_in_its_element


def test_nonfinite_direction_stays_in_its_element_equirect():
    # A shared offset of the directions stands in for any parameter they come from (a reflection's normal).
    t = torch.tensor([0.1, 0.2, -0.3], dtype=F64, requires_grad=True)
    nonfinite_stays_in_its_element(
        lambda d, ps, dx, dy: D.direction_to_equirect_uv(d + ps[0], dirs_dx=dx, dirs_dy=dy), [t])

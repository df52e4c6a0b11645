"""The filter-after-shading study's normal readers (experiments/studies/filter_after_shading.py)."""
import math

import torch

import difftex
from experiments.studies import filter_after_shading as fas


def test_bump_normals_tilt_a_ramp_downhill_and_match_difftex_bump():
    s = 0.3  # height rises by 0.3 per uv unit along u
    u = (torch.arange(16, dtype=torch.float64) + 0.5) / 16
    height = (s * u).expand(1, 1, 16, 16).contiguous()
    g = torch.linspace(0.3, 0.7, 5, dtype=torch.float64)  # away from the repeat seam
    v, uu = torch.meshgrid(g, g, indexing="ij")
    uv = torch.stack([uu, v], -1)[None]
    n = fas.bump_normals(height, uv, filter="bilinear")
    want = torch.tensor([-s, 0.0, 1.0], dtype=torch.float64) / math.sqrt(1 + s * s)
    torch.testing.assert_close(n, want.expand_as(n), atol=1e-12, rtol=0)
    frames = torch.eye(3, dtype=torch.float64).expand(1, 5, 5, 3, 3)
    bumpy = fas.bump_height_map(64).double()
    torch.testing.assert_close(fas.bump_normals(bumpy, uv, filter="bilinear"),
                               difftex.bump(bumpy, uv, frames, filter="bilinear"), atol=1e-12, rtol=0)


def test_the_normal_map_and_the_height_map_hold_the_same_bumps():
    # At texel centres the bilinear slope of the height map is a one-sided difference, the normal map's a
    # central one: the same field, normals within a few degrees, and flat where the field is.
    size = 512  # the study's: the bumps are 24-96 cycles across
    nm = fas.bump_normal_map(size).double()
    hm = fas.bump_height_map(size).double()
    c = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    v, u = torch.meshgrid(c, c, indexing="ij")
    uv = torch.stack([u, v], -1)[None] + 0.25 / size  # off the centres: the bilinear slope is defined
    a = fas.normal_map_normals(nm, uv, filter="nearest")
    b = fas.bump_normals(hm, uv, filter="bilinear")
    cos = (a * b).sum(-1)
    assert float(cos.mean()) > 0.985 and float(cos.min()) > 0.8  # measured 0.989, 0.843
    for n in (a, b):  # slopes of about 0.35 (20 deg) by construction: mean tilts 0.30 and 0.32 rad
        assert 0.27 < float(torch.acos(n[..., 2].clamp(max=1)).mean()) < 0.36

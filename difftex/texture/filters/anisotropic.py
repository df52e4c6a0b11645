"""Anisotropic filtering: several trilinear taps along the footprint's major axis.

The D3D 11.3 / Feline scheme. The footprint ellipse has the singular values
``major >= minor`` of the texel Jacobian as its axes (its true axes, not the
screen axes). A point takes ``N = min(ceil(major / minor), max_aniso)``
trilinear taps spread evenly over the major axis, at offsets
``((i + 1/2) / N - 1/2) * major`` for ``i = 0 .. N-1``, each at level
``log2(major / N) + lod_bias`` and weight ``1 / N``.

Taps are variable per point: a point that needs one tap costs one trilinear
tap. All go through one ``trilinear_points`` call (one pass of the native
kernel on the CPU; flattened into one (point, tap) list on the torch path).
Where no derivative needs a gradient, the native kernel's front end
computes the counts, levels and axes on the CPU (``difftex.sample``); the
functions here are its reference and serve everywhere else.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ..lod import Ellipse, Footprint, level

# N = ceil(major / minor) would jump to 2 on rounding noise at an exactly
# isotropic footprint; a ratio within this of an integer rounds down.
RATIO_TOL = 1e-4


def tap_count(ell: Ellipse, fp: Footprint, max_aniso: float) -> Tensor:
    """Trilinear taps per point: ``min(ceil(major / minor), floor(max_aniso))``, at least 1; int64."""
    cap = max(int(math.floor(max_aniso)), 1)
    major, minor = ell.major.detach(), ell.minor.detach()
    # Masks as products (8x faster than torch.where on CPU); all finite.
    pos = (minor > 0).to(minor.dtype)
    ratio = major / (minor + (1 - pos)) * pos + cap * (1 - pos)
    n = torch.nan_to_num(torch.ceil(ratio - RATIO_TOL), nan=1.0).clamp_(1, cap)
    bad = (fp.zero | fp.inf).to(n.dtype)
    return (n * (1 - bad) + bad).long()


def anisotropic_taps(fp: Footprint, ell: Ellipse, n: Tensor, lod_bias: Tensor | float, levels: int, height: int,
                     width: int) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Level, axis and count of the taps of ``n`` (``tap_count`` or auto's) per point, for ``trilinear_points``.

    Args:
        fp, ell: footprint and its ellipse per point, [M] (``difftex.lod``).
        n: [M] int64 tap count per point (>= 1).
        lod_bias: scalar or [M].
        levels: number of pyramid levels (D is clamped to ``levels - 1``).
        height, width: level 0's size.

    Returns:
        (D [M], axis [M, 2] uv, n), or (D, None, None) where every point
        takes one tap. ``D = log2(major / n) + lod_bias``, clamped; ``axis``
        is the major axis (its full length) as a uv vector. Differentiable in
        the footprint (through D and the axis; n is piecewise constant) and
        lod_bias.
    """
    D = level(ell.log2_major - torch.log2(n.to(ell.major.dtype)), lod_bias, levels)
    if bool((n == 1).all()):
        return D, None, None
    # Major axis as a uv vector: direction * length in texels / texture size.
    scale = torch.exp2(fp.log2_scale).unsqueeze(-1)
    axis = ell.direction * (ell.major.unsqueeze(-1) * scale) / ell.major.new_tensor([float(width), float(height)])
    return D, axis, n

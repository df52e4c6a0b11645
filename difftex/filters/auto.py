"""The "auto" filter: per point, the anisotropic filter with the fewest taps that are accurate enough.

The anisotropic filter (``anisotropic.py``) takes ``N = min(ceil(major /
minor), max_aniso)`` trilinear taps, spaced ``s = major / N`` texels apart
along the major axis, each read at level ``log2 s + lod_bias`` (its
prefilter is about ``s`` texels wide). "auto" runs the same code with a
smaller per-point count,

    N_a = min(ceil(major' / max(minor', 1)), floor(max_aniso))
    N   = ceil(N_a / (1 + tolerance)),

where ``x' = x * 2^lod_bias`` (level-0 texels after the bias). Two things
make it smaller:

* the floor of one texel: where the minor axis is under a texel of level 0
  the taps read level 0 anyway (the level clamps), so taps closer than a
  texel only re-read the bilinear interpolant; the spacing stays one texel;
* ``tolerance``: each tap's prefilter (2^level) may be up to ``1 +
  tolerance`` times wider than the anisotropic filter's, i.e. its level up
  to ``log2(1 + tolerance)`` coarser (more blur across the footprint).

The special cases fall out of the formula: a magnified point (``major' <=
1``) gets one tap at level 0, i.e. bilinear on level 0; a round footprint
(``N_a <= 1 + tolerance``) gets one tap, i.e. trilinear at ``log2 major``;
a long one gets just enough taps. With the default tolerance 0.25 a count
of 2-4 is kept and 5-16 drop to 4-13, except where the footprint is
longer than ``max_aniso`` allows, which keeps all ``max_aniso`` taps (measured: within 0.5 dB of
anisotropic 16 on the grazing-plane, sphere and spot scenes; a ratio just
over 1 is *not* cheapened to one tap, because the anisotropic filter's two
taps one level finer are markedly sharper and 3-5 dB more accurate on
spot's texture; docs/auto_filter.md).

Points are not grouped by method: one ``anisotropic_points`` call serves
them all (a one-tap point costs one trilinear tap, a magnified one a single
bilinear read), so values, gradients and degenerate-input handling are the
anisotropic filter's.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from ..lod import Ellipse, Footprint
from .anisotropic import _RATIO_TOL, anisotropic_points, tap_count

# exp2 of a larger exponent would overflow float32; any count past 2^64 is
# capped at max_aniso anyway.
_MAX_LOG2 = 64.0


def auto_tap_count(ell: Ellipse, fp: Footprint, lod_bias: Tensor | float, max_aniso: float,
                   tolerance: float) -> Tensor:
    """Trilinear taps per point of the "auto" filter (module docstring): [M] int64 in ``[1, floor(max_aniso)]``."""
    cap = tap_count(ell, fp, max_aniso)  # also 1 at zero / NaN / infinite footprints
    bias = lod_bias.detach() if isinstance(lod_bias, Tensor) else lod_bias
    with torch.no_grad():
        # In log2 so that huge biases or lengths cannot overflow; degenerate
        # lengths are +-_FAR there (finite), a NaN bias gives NaN -> 1 tap.
        minor_floor = torch.clamp(ell.log2_minor + bias, min=0.0)
        x = ell.log2_major + bias - minor_floor
        top = float(max(math.floor(max_aniso), 1))
        # The count the anisotropic filter would take (with the one-texel
        # floor), capped first, so the level differs from its by at most
        # log2(1 + tolerance); clamped before the cast (no int overflow).
        ratio = torch.exp2(x.clamp(max=_MAX_LOG2))
        full = torch.ceil(ratio - _RATIO_TOL).clamp_(max=top)
        n = torch.ceil(full / (1.0 + tolerance) - _RATIO_TOL)
        # Past max_aniso the anisotropic taps are already wider than the
        # footprint's minor axis; fewer would blur a grazing view twice over
        # (2-3 dB at 5 degrees), so there auto keeps all of them.
        n = torch.where(ratio > top, full, n)
        n = torch.nan_to_num(n, nan=1.0).clamp_(1.0, top).long()
    return torch.minimum(n, cap)


def auto_points(levels: Sequence[Tensor], uv: Tensor, fp: Footprint, ell: Ellipse, lod_bias: Tensor | float,
                max_aniso: float, tolerance: float, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """The "auto" filter on one texture.

    Args:
        levels: the pyramid of one texture, ``[1, C, H_k, W_k]`` each.
        uv: [M, 2] sample points.
        fp, ell: footprint and its ellipse per point (``difftex.lod``).
        lod_bias: scalar or [M].
        max_aniso: most taps per point (>= 1).
        tolerance: allowed excess width of a tap's prefilter over the
            footprint's minor axis, as a fraction (>= 0).
        wrap_u, wrap_v, border: as in ``separable_sample``.

    Returns:
        [C, M]; NaN where uv is not finite. Differentiable like the
        anisotropic filter: in the levels, uv, the footprint (level and tap
        positions; the count is piecewise constant) and lod_bias.
    """
    n = auto_tap_count(ell, fp, lod_bias, max_aniso, tolerance)
    return anisotropic_points(levels, uv, fp, ell, lod_bias, max_aniso, wrap_u, wrap_v, border, taps=n)

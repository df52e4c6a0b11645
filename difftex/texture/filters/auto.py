"""The "auto" filter: per point, the anisotropic filter with the fewest taps that are accurate enough.

The anisotropic filter (``anisotropic.py``) takes ``N = min(ceil(major /
minor), max_aniso)`` trilinear taps, spaced ``s = major / N`` texels apart
along the major axis, each read at level ``log2 s + lod_bias`` (its
prefilter is about ``s`` texels wide). "auto" runs the same code with a
smaller per-point count,

    N_a = min(ceil(major' / max(minor', 1/2)), floor(max_aniso))
    N   = ceil(N_a / (1 + tolerance)),

where ``x' = x * 2^lod_bias`` (level-0 texels after the bias). Two things
make it smaller:

* a floor of half a texel on the spacing: where the minor axis is under a
  texel all taps read level 0 (the level clamps), so extra taps only
  supersample the bilinear interpolant inside the pixel. That still pays
  down to about half a texel: on a sphere magnified 1.4-2x, anisotropic's
  two level-0 taps are 5-6 dB closer to the pixel's box average than one
  bilinear read (53 vs 48 dB), which a one-texel floor gave away. Below
  half a texel the gap stays 5-8 dB, but both errors are under one 8-bit
  level (RMSE 0.0025, 52 dB, at 3x magnification), so one read is taken;
* ``tolerance``: each tap's prefilter (2^level) may be up to ``1 +
  tolerance`` times wider than the anisotropic filter's, i.e. its level up
  to ``log2(1 + tolerance)`` coarser (more blur across the footprint).

The special cases fall out of the formula: a point whose major axis is
under half a texel gets one tap at level 0, i.e. bilinear; a round
footprint (``N_a <= 1 + tolerance``) gets one tap, i.e. trilinear at
``log2 major``; a long one gets just enough taps, except where the
footprint is longer than ``max_aniso`` allows, which keeps all
``max_aniso`` taps. The default tolerance 0.1 keeps counts up to 10 and
drops 11-16 by one (measured on the 17 scenes of
experiments/studies/speed_vs_accuracy.py: within 0.33 dB of anisotropic 16 on
every one; 0.25 saved 10 % of the taps on grazing planes but lost up to 2.1
dB there). So on those scenes auto is anisotropic 16 less 0-3 % of its
taps; it saves more where footprints are magnified (one read instead of
anisotropic's two where the major axis is under half a texel) or round. A
ratio just over 1 is *not* cheapened to one tap: the anisotropic filter's
two taps one level finer are markedly sharper and 3-5 dB more accurate on
spot's texture (docs/auto_filter.md).

Points are not grouped by method: one ``trilinear_points`` call with the
anisotropic filter's taps (``anisotropic_taps``) serves them all (a one-tap
point costs one trilinear tap, a magnified one a single bilinear read), so
values, gradients and degenerate-input handling are the anisotropic
filter's. Where no derivative needs a gradient the native kernel computes
these counts on the CPU (``difftex.sample``); this function is its
reference.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ..lod import Ellipse, Footprint
from .anisotropic import RATIO_TOL, tap_count

# exp2 of a larger exponent would overflow float32; any count past 2^64 is
# capped at max_aniso anyway.
MAX_LOG2 = 64.0
# Taps closer than half a level-0 texel are not worth their cost (module
# docstring); log2 of that spacing floor.
LOG2_FLOOR = -1.0


def auto_tap_count(ell: Ellipse, fp: Footprint, lod_bias: Tensor | float, max_aniso: float,
                   tolerance: float) -> Tensor:
    """Trilinear taps per point of the "auto" filter (module docstring): [M] int64 in ``[1, floor(max_aniso)]``."""
    cap = tap_count(ell, fp, max_aniso)  # also 1 at zero / NaN / infinite footprints
    bias = lod_bias.detach() if isinstance(lod_bias, Tensor) else lod_bias
    with torch.no_grad():
        # In log2 so that huge biases or lengths cannot overflow; degenerate
        # lengths are +-FAR there (finite), a NaN bias gives NaN -> 1 tap.
        minor_floor = torch.clamp(ell.log2_minor + bias, min=LOG2_FLOOR)
        x = ell.log2_major + bias - minor_floor
        top = float(max(math.floor(max_aniso), 1))
        # The count the anisotropic filter would take (with the half-texel
        # floor), capped first, so the level differs from its by at most
        # log2(1 + tolerance); clamped before the cast (no int overflow).
        ratio = torch.exp2(x.clamp(max=MAX_LOG2))
        full = torch.ceil(ratio - RATIO_TOL).clamp_(max=top)
        n = torch.ceil(full / (1.0 + tolerance) - RATIO_TOL)
        # Past max_aniso the anisotropic taps are already wider than the
        # footprint's minor axis; fewer would blur a grazing view twice over
        # (2-3 dB at 5 degrees), so there auto keeps all of them.
        n = torch.where(ratio > top, full, n)
        n = torch.nan_to_num(n, nan=1.0).clamp_(1.0, top).long()
    return torch.minimum(n, cap)

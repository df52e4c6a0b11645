"""The options of ``sample``: the filter names, the caps and defaults, and their checks (one wording)."""
from __future__ import annotations

import math
import numbers

# Filters that read one texture level; the value is the per-axis kernel.
SEPARABLE = {"nearest": "nearest", "bilinear": "linear", "bicubic": "cubic"}
# Filters that read a mip pyramid and need uv_dx / uv_dy.
MIP_FILTERS = ("trilinear", "nearest-mip", "anisotropic", "ewa", "auto")
# Default of ``tolerance`` ("auto"): within 0.5 dB of anisotropic 16 on every
# scene of experiments/studies/speed_vs_accuracy.py (filters/auto.py).
DEFAULT_TOLERANCE = 0.1
# Largest max_aniso. A rank-1 or grazing footprint takes max_aniso taps (EWA:
# an ellipse max_aniso times longer than wide), so this bounds the work per
# point: 1024 trilinear taps, about 20k texels for EWA. (GPUs stop at 16.)
MAX_ANISO = 1024
FILTERS = tuple(SEPARABLE) + MIP_FILTERS


def check_filter(filter: object) -> str:
    """``filter`` if it names a filter of ``FILTERS``; ValueError naming the argument otherwise."""
    if not isinstance(filter, str) or filter not in FILTERS:
        raise ValueError(f"filter: unknown filter {filter!r}; expected one of {FILTERS}")
    return filter


def check_number(name: str, value: object, minimum: float, maximum: float = math.inf) -> float:
    """A finite real in [minimum, maximum], as float; TypeError / ValueError naming ``name`` otherwise."""
    want = ("" if minimum == -math.inf and maximum == math.inf else f" >= {minimum:g}" if maximum == math.inf
            else f" in [{minimum:g}, {maximum:g}]")
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name}: expected a number{want}, got {type(value).__name__}")
    if not (math.isfinite(value) and minimum <= value <= maximum):
        raise ValueError(f"{name}: expected a finite number{want}, got {value!r}")
    return float(value)

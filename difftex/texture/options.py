"""The options of ``sample``: the filter names, the caps and defaults, and their checks (one wording)."""
from __future__ import annotations

import math
import numbers
from typing import Union

import torch
from torch import Tensor

from .._checks import check_float, check_same, describe

# Filters that read one texture level; the value is the per-axis kernel.
SEPARABLE = {"nearest": "nearest", "bilinear": "linear", "bicubic": "cubic"}
# Filters that read a prefiltered texture (mip pyramid, ripmap, summed-area table) and need uv_dx / uv_dy.
MIP_FILTERS = ("trilinear", "nearest-mip", "anisotropic", "ewa", "auto", "ripmap", "sat")
# Of those, the ones filtering the footprint's axis-aligned box (filters/ripmap.py, filters/sat.py).
BOX_FILTERS = ("ripmap", "sat")
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


# The filters with a stochastic mode (``sample(..., stochastic=k)``, filters/stochastic.py).
STOCHASTIC_FILTERS = ("bilinear", "bicubic", "trilinear", "anisotropic", "ewa")


def check_stochastic(stochastic: object, filter: str | None = None) -> int:
    """The number of draws a pixel (0: the deterministic filter) of ``stochastic`` (True is 1).

    The one check of ``sample``'s and ``TexturedMesh``'s ``stochastic``:
    TypeError where it is not an int, ValueError where it is negative or,
    ``filter`` given, where k >= 1 and that filter has no stochastic mode.
    """
    if isinstance(stochastic, bool):
        stochastic = int(stochastic)
    if not isinstance(stochastic, numbers.Integral):
        raise TypeError(f"stochastic: expected an int >= 0 (draws a pixel), got {type(stochastic).__name__}")
    if stochastic < 0:
        raise ValueError(f"stochastic: expected an int >= 0 (draws a pixel), got {stochastic}")
    if stochastic and filter is not None and filter not in STOCHASTIC_FILTERS:
        raise ValueError(f"stochastic: filter {filter!r} has no stochastic mode; expected one of "
                         f"{STOCHASTIC_FILTERS}")
    return int(stochastic)


def check_generator(generator: object, like: Tensor) -> None:
    """``generator`` must be None or a ``torch.Generator`` on ``like``'s device type (TypeError / ValueError)."""
    if generator is None:
        return
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")
    if generator.device.type != like.device.type:
        raise ValueError(f"generator: on {generator.device}, expected uv's device type {like.device.type}")


def check_number(name: str, value: object, minimum: float, maximum: float = math.inf) -> float:
    """A finite real in [minimum, maximum], as float; TypeError / ValueError naming ``name`` otherwise."""
    # Plain floats and ints skip the numbers.Real ABC check and the message: every sample() call makes
    # three of these, and both showed in its per-call overhead.
    if type(value) is not float and type(value) is not int and (isinstance(value, bool)
                                                                 or not isinstance(value, numbers.Real)):
        raise TypeError(f"{name}: expected a number{_range_text(minimum, maximum)}, got {type(value).__name__}")
    if not (math.isfinite(value) and minimum <= value <= maximum):
        raise ValueError(f"{name}: expected a finite number{_range_text(minimum, maximum)}, got {value!r}")
    return float(value)


def _range_text(minimum: float, maximum: float) -> str:
    return ("" if minimum == -math.inf and maximum == math.inf else f" >= {minimum:g}" if maximum == math.inf
            else f" in [{minimum:g}, {maximum:g}]")


def check_bias(lod_bias: object, points: Tensor, points_name: str, ref: Tensor, ref_name: str,
               dims: str = "Ho, Wo") -> Union[float, Tensor]:
    """``lod_bias`` as a float, or a float tensor: a scalar or [B, ...] with the pixel shape of ``points``.

    ``points`` is [B, H, W, K] (uv, directions), named ``points_name`` in
    the messages; the tensor must share ``ref``'s dtype and device. ``dims``
    names the pixel axes in the messages. TypeError / ValueError naming
    lod_bias otherwise.
    """
    if type(lod_bias) is float or type(lod_bias) is int:
        return float(lod_bias)
    B, H, W = points.shape[:3]
    shape = f"[B, {dims}] = [{B}, {H}, {W}]"
    if isinstance(lod_bias, Tensor):
        check_float("lod_bias", lod_bias, (0, 3), shape_doc=f"scalar or {shape}")
        check_same("lod_bias", lod_bias, ref_name, ref)
        if lod_bias.dim() == 3 and tuple(lod_bias.shape[1:]) != (H, W):
            raise ValueError(f"lod_bias: expected a scalar or {shape} like {points_name}, got {describe(lod_bias)}")
        return lod_bias
    if isinstance(lod_bias, bool) or not isinstance(lod_bias, numbers.Real):
        raise TypeError(f"lod_bias: expected a number or a float tensor [B, {dims}], got {type(lod_bias).__name__}")
    return float(lod_bias)

"""Image metrics in difftex's conventions ([B, C, H, W] images in [0, 1])."""
from __future__ import annotations

import math

import torch
from torch import Tensor


def psnr(x: Tensor, ref: Tensor, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over the finite pixels of ``ref``; NaN if ``x`` is not finite there."""
    ok = torch.isfinite(ref)  # not x's: a filter that emits NaN must not score a perfect inf
    mse = ((x - ref)[ok].double() ** 2).mean().item()
    if not math.isfinite(mse):  # an inf in x would make log10(0) raise
        return float("nan")
    return float("inf") if mse == 0 else 10 * math.log10(peak * peak / mse)

"""Image metrics in difftex's conventions ([B, C, H, W] images in [0, 1])."""
from __future__ import annotations

import math
from typing import Optional

import torch
from torch import Tensor


def psnr(x: Tensor, ref: Tensor, peak: float = 1.0, *, mask: Optional[Tensor] = None) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(peak^2 / MSE)``, over the finite pixels of ``ref``.

    The one PSNR of the project (tests, benchmarks and experiments). The MSE is
    pooled over every selected value, batch and channels included: the
    difference is taken in the inputs' dtype, squared and averaged in float64
    (the formula is :func:`kornia.metrics.psnr`'s).

    Args:
        x: the image scored, any shape, e.g. [B, C, H, W].
        ref: the reference; broadcast to ``x``'s shape (e.g. [1, 1, H, W]
            against [B, C, H, W]). Its non-finite values are left out: a
            reference marks unscored pixels with NaN.
        peak: the data range (1 for images in [0, 1]), > 0.
        mask: optional bool tensor broadcast to ``x``'s shape; only the
            values where it is True are scored (e.g. the covered pixels,
            [B, 1, H, W]).

    Returns:
        PSNR in dB as a Python float: ``inf`` for an exact match, NaN where
        ``x`` is not finite at a scored value (a filter that emits NaN or inf
        must not score well) or where nothing is scored. Not differentiable.

    Raises:
        TypeError: ``x``, ``ref`` or ``mask`` not a tensor, or ``mask`` not bool.
        ValueError: ``ref`` or ``mask`` does not broadcast to ``x``'s shape,
            or ``peak`` is not a positive finite number.
    """
    for name, t in (("x", x), ("ref", ref)):
        if not isinstance(t, Tensor):
            raise TypeError(f"psnr: {name} must be a torch.Tensor, got {type(t).__name__}")
    if isinstance(peak, bool) or not isinstance(peak, (int, float)) or not (math.isfinite(peak) and peak > 0):
        raise ValueError(f"psnr: peak must be a positive finite number, got {peak!r}")
    ok = torch.isfinite(_broadcast("ref", ref, x.shape))  # not x's: a filter that emits NaN must not score inf
    if mask is not None:
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
            raise TypeError(f"psnr: mask must be a bool tensor, got "
                            f"{mask.dtype if isinstance(mask, Tensor) else type(mask).__name__}")
        ok = ok & _broadcast("mask", mask, x.shape)
    # One difference, selected once and widened once: the fit scripts score 3M-texel textures often.
    d = x.detach() - ref.detach()
    d = d.reshape(-1) if bool(ok.all()) else d[ok]
    d = d.double()
    if d.numel() == 0 or not bool(torch.isfinite(d).all()):
        return float("nan")  # an inf in x would give -inf (log10 of 0), a NaN NaN: both mean "broken"
    # Imported here: kornia costs `import difftex` about 0.4 s and only this metric uses it.
    from kornia.metrics import psnr as kornia_psnr

    # kornia's formula on (x - ref, 0); it gives inf for an MSE of 0, the convention kept here.
    return float(kornia_psnr(d, d.new_zeros(()).expand_as(d), float(peak)))


def _broadcast(name: str, t: Tensor, shape: torch.Size) -> Tensor:
    try:
        return t.expand(shape)
    except RuntimeError:
        raise ValueError(f"psnr: {name} of shape {tuple(t.shape)} does not broadcast to x's shape "
                         f"{tuple(shape)}") from None

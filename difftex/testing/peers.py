"""Other libraries' texture lookups read with difftex's conventions, to compare against (benchmarks, tests).

``F.grid_sample`` and kornia's ``remap`` have no repeat mode. A one-texel
circular pad along a repeating axis and uv folded into [0, 1) make them
exact there; a clamping axis is grid_sample's ``padding_mode="border"`` as
it is. The pad and the fold are part of the peer's work (timed with it).
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

_PEER_WRAPS = ("repeat", "clamp")


def _wrap_pair(wrap: str | Sequence[str]) -> tuple[str, str]:
    pair = (wrap, wrap) if isinstance(wrap, str) else tuple(wrap)
    if len(pair) != 2 or any(w not in _PEER_WRAPS for w in pair):
        raise ValueError(f"peers: wrap must be one of {_PEER_WRAPS} or a (u, v) pair of them, got {wrap!r}")
    return pair  # type: ignore[return-value]


def pad_and_grid(texture: Tensor, uv: Tensor, wrap: str | Sequence[str] = "repeat") -> tuple[Tensor, Tensor]:
    """The texture and the grid_sample grid (align_corners=False, padding "border") that read it like difftex.

    Args:
        texture: [B or 1, C, H, W].
        uv: [B, Ho, Wo, 2] in difftex's uv (texel centres at (i + 0.5) / W).
        wrap: "repeat" or "clamp", or a (u, v) pair.

    Returns:
        ``(padded texture, grid [B, Ho, Wo, 2])``; the grid is in the padded
        texture's normalized coordinates. Differentiable in both inputs.
    """
    H, W = texture.shape[-2:]
    wu, wv = _wrap_pair(wrap)
    pu, pv = int(wu == "repeat"), int(wv == "repeat")
    if not (pu or pv):
        return texture, uv * 2 - 1
    padded = F.pad(texture, (pu, pu, pv, pv), mode="circular")
    fold = torch.stack([uv[..., 0] - torch.floor(uv[..., 0]) if pu else uv[..., 0],
                        uv[..., 1] - torch.floor(uv[..., 1]) if pv else uv[..., 1]], -1)
    grid = (fold * uv.new_tensor([W, H]) + uv.new_tensor([pu, pv])) / uv.new_tensor([W + 2 * pu, H + 2 * pv]) * 2 - 1
    return padded, grid


def grid_sample_lookup(texture: Tensor, uv: Tensor, wrap: str | Sequence[str] = "repeat",
                       mode: str = "bilinear") -> Tensor:
    """``F.grid_sample`` with difftex's uv and wrap: [B, C, Ho, Wo] (the texture is expanded to uv's batch).

    ``mode``: grid_sample's "nearest", "bilinear" or "bicubic" (bicubic
    reads up to two texels past an edge, so a one-texel pad is exact for
    nearest and bilinear only). Differentiable in texture and uv.
    """
    padded, grid = pad_and_grid(texture, uv, wrap)
    if padded.shape[0] != grid.shape[0]:
        padded = padded.expand(grid.shape[0], -1, -1, -1)
    return F.grid_sample(padded, grid, mode=mode, padding_mode="border", align_corners=False)


def kornia_lookup(texture: Tensor, uv: Tensor, wrap: str | Sequence[str] = "repeat") -> Tensor:
    """kornia's ``remap`` (bilinear, normalized coordinates, align_corners=False) with difftex's uv and wrap."""
    from kornia.geometry.transform import remap

    padded, grid = pad_and_grid(texture, uv, wrap)
    return remap(padded, grid[..., 0], grid[..., 1], mode="bilinear", padding_mode="border",
                 align_corners=False, normalized_coordinates=True)

"""3D textures: ``sample3d`` reads a volume [B, C, D, H, W] at uvw coordinates, nearest or trilinear.

Conventions extend the 2D ones of DESIGN.md by one axis: ``uvw`` in
``[0, 1]^3`` covers the volume once, ``u`` runs along W, ``v`` along H and
``w`` along D; texel ``(d, i, j)`` has its centre at
``((j + 0.5) / W, (i + 0.5) / H, (d + 0.5) / D)``, so
``F.grid_sample(volume, 2 * uvw - 1, align_corners=False)`` on 5-D input
samples the same point. Wrap modes are the 2D ones (``texture.wrap``), one per
axis.

The op is written with differentiable torch ops (gather, weights from the
fractional texel coordinate), so autograd gives the volume gradient (a
scatter of the weights), the uvw gradient and higher derivatives.
"""
from __future__ import annotations

from typing import Sequence, Union

import torch
from torch import Tensor

from .._checks import broadcast_batch, check_float, check_same, describe
from .filters.gather import reduce_coordinate
from .wrap import WRAP_MODES, floor_index, parse_wrap, wrap_index

__all__ = ["sample3d", "VOLUME_FILTERS"]

VOLUME_FILTERS = ("nearest", "linear")

Wrap3 = Union[str, Sequence[str]]


def parse_wrap3(wrap: Wrap3) -> tuple[str, str, str]:
    """One mode for all axes or a (wrap_u, wrap_v, wrap_w) triple; ValueError / TypeError naming ``wrap``."""
    if isinstance(wrap, str):
        parse_wrap(wrap)
        return wrap, wrap, wrap
    if not isinstance(wrap, (tuple, list)):
        raise TypeError(f"wrap: expected a str or a (wrap_u, wrap_v, wrap_w) triple, got {type(wrap).__name__}")
    if len(wrap) != 3:
        raise ValueError(f"wrap: expected one mode or a triple (wrap_u, wrap_v, wrap_w), got {len(wrap)} items "
                         f"{wrap!r}")
    for mode in wrap:
        parse_wrap(mode) if isinstance(mode, str) else parse_wrap([mode, mode])
    return tuple(wrap)  # type: ignore[return-value]


def sample3d(volume: Tensor, uvw: Tensor, *, filter: str = "linear", wrap: Wrap3 = "repeat",
             border_value: float = 0.0) -> Tensor:
    """Sample a 3D texture (volume) at uvw coordinates.

    Args:
        volume: [B, C, D, H, W] float32 / float64; B = 1 broadcasts over
            uvw's batch.
        uvw: [B, ..., 3] coordinates (any number of point dimensions), same
            dtype and device as ``volume``; ``u`` along W, ``v`` along H, ``w``
            along D, ``(0, 0, 0)`` the outer corner of texel (0, 0, 0) and
            texel centres at ``(index + 0.5) / size`` (``grid = 2 * uvw - 1``
            with ``align_corners=False`` for ``F.grid_sample``). B = 1
            broadcasts over the volume batch.
        filter: "nearest" (round half to even, like grid_sample) or "linear"
            (trilinear over the 8 nearest texel centres).
        wrap: "repeat" | "clamp" | "mirror" | "border", one for every axis or
            a triple (wrap_u, wrap_v, wrap_w). clamp is grid_sample's
            padding "border", mirror its "reflection", border its "zeros"
            (with ``border_value``).
        border_value: the constant that "border" reads outside the volume.

    Returns:
        [B, C, ...] with uvw's point dimensions.

    Gradients flow to ``volume`` and (for "linear") to ``uvw``; both to any
    order. NaN / inf coordinates give NaN in their own outputs only, and no
    gradient to the volume or to themselves. Raises
    TypeError on non-float tensors or mismatched dtypes, ValueError naming
    the argument on bad shapes, devices, batch sizes, filters or wraps.
    """
    volume = check_float("volume", volume, ndim=5, shape_doc="[B, C, D, H, W]")
    uvw = check_float("uvw", uvw, last=3, shape_doc="[B, ..., 3]")
    if uvw.dim() < 2:
        raise ValueError(f"uvw: expected at least 2-D [B, ..., 3], got {describe(uvw)}")
    check_same("uvw", uvw, "volume", volume)
    if filter not in VOLUME_FILTERS:
        raise ValueError(f"filter: expected one of {VOLUME_FILTERS} for sample3d, got {filter!r}")
    modes = parse_wrap3(wrap)
    if isinstance(border_value, bool) or not isinstance(border_value, (int, float)):
        raise TypeError(f"border_value: expected a number, got {type(border_value).__name__}")
    if min(volume.shape[2:]) == 0:
        raise ValueError(f"volume: expected a non-empty volume [B, C, D, H, W], got {describe(volume)}")
    Bv, C, D, H, W = volume.shape
    Bu = uvw.shape[0]
    B = broadcast_batch(("volume", "uvw"), (Bv, Bu))
    points = uvw.shape[1:-1]
    pts = uvw.reshape(Bu, -1, 3)
    if Bv == 1 and Bu > 1:  # one volume for every row of points: gather from it as one long row
        pts = pts.reshape(1, -1, 3)
    elif Bu == 1 and Bv > 1:
        pts = pts.expand(Bv, -1, -1)
    flat = volume.reshape(Bv, C, D * H * W)
    # A NaN / inf point reads from zero coordinates and shows NaN afterwards, so that it spreads no NaN
    # into the volume's gradient through the texel it would index.
    bad = ~torch.isfinite(pts.detach()).all(-1)  # [Bv or 1, M]
    if bool(bad.any()):
        pts = torch.where(bad.unsqueeze(-1), torch.zeros_like(pts), pts)
    else:
        bad = None
    sizes = (W, H, D)
    taps = []  # per axis: list of (index, valid, weight)
    for axis in range(3):
        n = sizes[axis]
        x = reduce_coordinate(pts[..., axis], modes[axis]) * n - 0.5
        if filter == "nearest":
            base = torch.round(x.detach())
            # 1 where x is finite, NaN where not: a bad coordinate shows in its own output.
            ws = [1 + 0 * x]
            offs = [0]
        else:
            base = torch.floor(x.detach())
            t = x - base
            ws = [1 - t, t]
            offs = [0, 1]
        b = floor_index(base)
        axis_taps = []
        for o, w in zip(offs, ws):
            idx, valid = wrap_index(b + o, n, modes[axis])
            axis_taps.append((idx, valid, w))
        taps.append(axis_taps)
    out = None
    for iz, vz, wz in taps[2]:
        for iy, vy, wy in taps[1]:
            for ix, vx, wx in taps[0]:
                idx = (iz * H + iy) * W + ix  # [Bv, M]
                vals = torch.gather(flat, 2, idx.unsqueeze(1).expand(-1, C, -1))
                valid = [v for v in (vx, vy, vz) if v is not None]
                if valid:
                    ok = valid[0]
                    for v in valid[1:]:
                        ok = ok & v
                    vals = torch.where(ok.unsqueeze(1), vals, vals.new_tensor(border_value))
                term = vals * (wz * wy * wx).unsqueeze(1)
                out = term if out is None else out + term
    if bad is not None:
        out = torch.where(bad.unsqueeze(1), out.new_tensor(float("nan")), out)
    if out.shape[0] != B:  # the long row of a shared volume back into uvw's batch
        out = out.view(C, B, -1).transpose(0, 1)
    return out.reshape(B, C, *points)

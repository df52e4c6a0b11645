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
from .lod import level
from .pyramid.mipmap import _down_axis
from .wrap import floor_index, parse_wrap, wrap_index

__all__ = ["sample3d", "volume_mipmap", "VOLUME_FILTERS"]

VOLUME_FILTERS = ("nearest", "linear")

Wrap3 = Union[str, Sequence[str]]


def volume_mipmap(volume: Tensor, *, max_levels: int | None = None) -> list[Tensor]:
    """The mip pyramid of a volume: level ``k`` is ``ceil(D / 2^k) x ceil(H / 2^k) x ceil(W / 2^k)``.

    Each axis halves with the 2D pyramid's filters (``texture.pyramid``: the
    2-texel box on an even axis, the area-weighted box on an odd one, which
    keeps the mean exactly), down to 1 x 1 x 1.

    Args:
        volume: [B, C, D, H, W] float.
        max_levels: keep at most this many levels (>= 1); default all.

    Returns:
        list of [B, C, D_k, H_k, W_k] tensors, level 0 first (``volume``
        itself). Differentiable: gradients reach ``volume`` from every level.
        Raises TypeError / ValueError naming the argument on bad input.
    """
    volume = check_float("volume", volume, ndim=5, shape_doc="[B, C, D, H, W]")
    if min(volume.shape[2:]) == 0:
        raise ValueError(f"volume: expected a non-empty volume [B, C, D, H, W], got {describe(volume)}")
    if max_levels is not None and (isinstance(max_levels, bool) or not isinstance(max_levels, int)
                                   or max_levels < 1):
        raise ValueError(f"max_levels: expected None or an int >= 1, got {max_levels!r}")
    n = 1 + max(int(s - 1).bit_length() for s in volume.shape[2:])  # ceil(log2 of the largest side) + 1
    n = n if max_levels is None else min(n, max_levels)
    levels = [volume]
    while len(levels) < n:
        x = _down_axis(_down_axis(levels[-1], -1), -2)
        levels.append(_down_axis(x.transpose(-3, -2), -2).transpose(-3, -2))
    return levels


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


def sample3d(volume: Tensor | Sequence[Tensor], uvw: Tensor, *, filter: str = "linear", wrap: Wrap3 = "repeat",
             border_value: float = 0.0, lod: Tensor | float | None = None) -> Tensor:
    """Sample a 3D texture (volume) at uvw coordinates.

    Args:
        volume: [B, C, D, H, W] float32 / float64; B = 1 broadcasts over
            uvw's batch. With ``lod``, also a list of levels from
            :func:`volume_mipmap` (else the pyramid is built on the fly).
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
        lod: optional level of detail ``D`` (a number or a [B, ...] tensor
            with uvw's point shape): blends ``filter`` reads of levels
            ``floor(D)`` and ``floor(D) + 1`` of the volume's pyramid by the
            fraction of ``D``, after ``D = clamp(D, 0, top level)`` (the 2D
            level formula and its gradient convention
            of DESIGN.md, ``texture.lod.level``; the caller computes D,
            e.g. ``log2`` of the footprint in level-0 texels). None reads
            level 0 only.

    Returns:
        [B, C, ...] with uvw's point dimensions.

    Gradients flow to ``volume`` (through every level) and (for "linear")
    to ``uvw`` and ``lod``; to any order. NaN / inf coordinates give NaN in their own outputs only, and no
    gradient to the volume or to themselves. Raises
    TypeError on non-float tensors or mismatched dtypes, ValueError naming
    the argument on bad shapes, devices, batch sizes, filters or wraps.
    """
    levels = None
    if isinstance(volume, (list, tuple)):
        if lod is None or len(volume) == 0:
            raise TypeError("volume: a list of levels needs lod (and at least one level); pass a tensor otherwise")
        levels = [check_float(f"volume[{k}]", v, ndim=5, shape_doc="[B, C, D, H, W]") for k, v in enumerate(volume)]
        volume = levels[0]
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
    B = broadcast_batch(("volume", "uvw"), (volume.shape[0], uvw.shape[0]))
    if lod is None:
        return _read(volume, uvw, filter, modes, float(border_value))
    if levels is None:
        levels = volume_mipmap(volume)
    for k, v in enumerate(levels[1:], 1):
        check_same(f"volume[{k}]", v, "volume[0]", volume)
        if v.shape[:2] != volume.shape[:2]:
            raise ValueError(f"volume[{k}]: expected batch and channels {tuple(volume.shape[:2])} like volume[0], "
                             f"got {describe(v)}")
    if isinstance(lod, Tensor):
        check_float("lod", lod)
        check_same("lod", lod, "uvw", uvw)
        if lod.dim() > 0 and (lod.shape[1:] != uvw.shape[1:-1] or lod.shape[0] not in (1, B)):
            raise ValueError(f"lod: expected a number or [B, ...] = {(B, *uvw.shape[1:-1])} like uvw's points, "
                             f"got {describe(lod)}")
    elif isinstance(lod, bool) or not isinstance(lod, (int, float)):
        raise TypeError(f"lod: expected None, a number or a tensor, got {type(lod).__name__}")
    else:
        lod = uvw.new_tensor(float(lod))
    if lod.dim() == 0:
        lod = lod.expand(1, *uvw.shape[1:-1])
    d = level(lod, 0.0, len(levels))
    # Blend levels lo and lo + 1 with lo = ceil(D) - 1: at an integer D = k > 0 that is levels k - 1 and k with
    # weight 1 on k, so the gradient in D is the derivative from below, v_k - v_(k-1), as DESIGN.md states.
    lo = (torch.ceil(d.detach()) - 1).clamp(min=0)
    frac = d - lo
    out = None
    for k in range(len(levels)):
        near = (lo == k) | (lo == k - 1)
        if not bool(near.any()):
            continue
        w = torch.where(lo == k, 1 - frac, torch.where(lo == k - 1, frac, torch.zeros_like(frac)))
        term = _read(levels[k], uvw, filter, modes, float(border_value)) * w.unsqueeze(1)
        out = term if out is None else out + term
    return out


def _read(volume: Tensor, uvw: Tensor, filter: str, modes: tuple[str, str, str], border_value: float) -> Tensor:
    """One level, checked inputs: [B, C, ...]."""
    Bv, C, D, H, W = volume.shape
    Bu = uvw.shape[0]
    B = max(Bv, Bu)
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

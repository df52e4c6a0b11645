"""Ripmaps: pyramids whose width and height shrink independently, for axis-aligned anisotropic footprints.

Level ``(i, j)`` of an ``H x W`` texture is ``ceil(H / 2^j) x ceil(W / 2^i)``
(i halvings of the width, j of the height), for ``i < level_count(1, W)``
and ``j < level_count(H, 1)``: a grid of levels whose diagonal ``(k, k)`` is
the mip chain (clamped to the last level along the shorter side). Each
halving is the mipmap's one-axis step (``mipmap._down_axis``: the 2-texel
box on an even side, the area-weighted box on an odd one, no texel
dropped), so a ripmap level is the mipmap level of the same size up to
rounding, and every level keeps the texture's mean.

The levels are built in autograd-tracked ops: the gradient of anything
read from any level reaches the base texture through the exact adjoint of
the halvings. Memory is about 4x the base (a mipmap's is 4/3).
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from ..._checks import check_float, check_same, describe
from .mipmap import Mipmap, _down_axis, level_count, level_size


def ripmap_counts(height: int, width: int) -> tuple[int, int]:
    """``(n_u, n_v)``: levels along u (width halvings + 1) and along v of a full ripmap, down to 1 texel."""
    return level_count(1, width), level_count(height, 1)


def build_ripmap(texture: Tensor, n_u: int, n_v: int) -> list[list[Tensor]]:
    """Levels ``[j][i]`` (j: height halvings, i: width halvings) for ``i < n_u``, ``j < n_v``."""
    column = [texture]
    for _ in range(1, n_v):
        column.append(_down_axis(column[-1], -2))
    grid = []
    for first in column:
        row = [first]
        for _ in range(1, n_u):
            row.append(_down_axis(row[-1], -1))
        grid.append(row)
    return grid


class Ripmap:
    """A ripmap: levels ``(i, j)`` of ``[B, C, ceil(H / 2^j), ceil(W / 2^i)]``, ``(0, 0)`` the base.

    Build one with ``difftex.ripmap``. ``ripmap[i, j]`` is a level (i width
    halvings, j height halvings); the levels are ordinary tensors in the
    autograd graph. ``difftex.sample`` accepts a Ripmap wherever it takes a
    texture: ``filter="ripmap"`` reads its levels, the single-level filters
    and "sat" its base, the mip filters its diagonal (``mipmap()``).
    """

    __slots__ = ("grid",)

    def __init__(self, grid: Sequence[Sequence[Tensor]]):
        self.grid = [list(row) for row in grid]

    def __getitem__(self, ij: tuple[int, int]) -> Tensor:
        i, j = ij
        return self.grid[j][i]

    @property
    def counts(self) -> tuple[int, int]:
        """``(n_u, n_v)``: levels along u (width) and along v (height)."""
        return len(self.grid[0]), len(self.grid)

    @property
    def base(self) -> Tensor:
        return self.grid[0][0]

    @property
    def shape(self) -> torch.Size:
        """Shape of the base level."""
        return self.base.shape

    @property
    def dtype(self) -> torch.dtype:
        return self.base.dtype

    @property
    def device(self) -> torch.device:
        return self.base.device

    def select(self, b: int) -> "Ripmap":
        """The ripmap of texture ``b`` of the batch (levels ``[1, C, ...]``, views)."""
        return Ripmap([[lv[b:b + 1] for lv in row] for row in self.grid])

    def mipmap(self) -> Mipmap:
        """The diagonal ``(k, k)`` as a Mipmap (k clamped to each axis' last level): the mip chain."""
        n_u, n_v = self.counts
        return Mipmap([self[min(k, n_u - 1), min(k, n_v - 1)] for k in range(max(n_u, n_v))])

    def __repr__(self) -> str:
        B, C, H, W = self.shape
        n_u, n_v = self.counts
        return (f"Ripmap(B={B}, C={C}, base={H}x{W}, levels={n_u}x{n_v} (u x v), dtype={self.dtype}, "
                f"device={self.device})")


def check_ripmap(rm: Ripmap) -> Ripmap:
    """``rm`` itself after checking a (possibly user-built) grid: rectangular, at most a full ripmap's levels,
    level ``(i, j)`` of shape ``[B, C, ceil(H / 2^j), ceil(W / 2^i)]``, every level of the base's dtype and
    device. Raises ValueError / TypeError naming the level ``texture[i, j]``."""
    grid = rm.grid
    if not grid or not grid[0] or any(len(row) != len(grid[0]) for row in grid):
        raise ValueError(f"texture: expected a non-empty rectangular grid of ripmap levels, got rows of "
                         f"{[len(row) for row in grid]} levels")
    base = check_float("texture[0, 0]", grid[0][0], 4, shape_doc="[B, C, H, W]")
    B, C, H, W = base.shape
    if min(B, C, H, W) < 1:
        raise ValueError(f"texture[0, 0]: expected B, C, H, W >= 1, got {describe(base)}")
    n_u, n_v = rm.counts
    full = ripmap_counts(H, W)
    if n_u > full[0] or n_v > full[1]:
        raise ValueError(f"texture: {n_u} x {n_v} ripmap levels (u x v) given but a {H}x{W} base has only "
                         f"{full[0]} x {full[1]}")
    for j, row in enumerate(grid):
        for i, lev in enumerate(row):
            if i == j == 0:
                continue
            name = f"texture[{i}, {j}]"
            check_float(name, lev, 4, shape_doc="[B, C, H_j, W_i]")
            check_same(name, lev, "texture[0, 0]", base)
            want = (B, C, level_size(H, 1, j)[0], level_size(1, W, i)[1])
            if tuple(lev.shape) != want:
                raise ValueError(f"{name}: expected shape {want} (ceil(H / 2^j) x ceil(W / 2^i)), got {describe(lev)}")
    return rm


def ripmap(texture: Tensor | Ripmap) -> Ripmap:
    """Build the ripmap of a texture: every combination of width and height halvings.

    Args:
        texture: [B, C, H, W] float tensor (any H, W >= 1, odd included: the
            mipmap's area-weighted box, no texel dropped), or a Ripmap
            (checked as :func:`check_ripmap` does, and returned as is).

    Returns:
        Ripmap with ``level_count(1, W) x level_count(H, 1)`` levels; level
        ``(0, 0)`` is ``texture`` itself.

    Differentiable: gradients of any level reach the base texture through
    the exact adjoint of the halvings. Raises TypeError on a non-float
    texture, ValueError naming ``texture`` on a bad shape.
    """
    if isinstance(texture, Ripmap):
        return check_ripmap(texture)
    check_float("texture", texture, 4, shape_doc="[B, C, H, W]")
    B, C, H, W = texture.shape
    if min(B, C, H, W) < 1:
        raise ValueError(f"texture: expected B, C, H, W >= 1, got {describe(texture)}")
    return Ripmap(build_ripmap(texture, *ripmap_counts(H, W)))

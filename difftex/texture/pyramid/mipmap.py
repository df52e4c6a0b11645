"""Mipmap pyramids: construction, its exact adjoint, and the ``Mipmap`` container.

Level ``k`` of an ``H x W`` texture is ``ceil(H / 2^k) x ceil(W / 2^k)``
(DESIGN.md section 2), down to 1 x 1. Each level is made from the previous
one axis by axis:

* an even axis of n texels halves with the 2-texel box ``[1/2, 1/2]``;
* an odd axis of n > 1 texels becomes ``m = (n + 1) / 2`` texels with the
  *area-weighted box* (polyphase box, the filter OpenGL's NPOT mipmap notes
  recommend): output texel ``j`` covers the source interval
  ``[j n / m, (j + 1) n / m)`` of width ``n / m < 2`` and averages the source
  texels it overlaps, weighted by the overlap. Every source texel thus gives
  the same total weight ``m / n`` to the next level (its share), at most
  three source texels meet in one output, and the mean is kept exactly.
* an axis of 1 texel stays 1.

The pyramid is built in autograd-tracked ops, so the gradient of anything
read from any level reaches the base texture through the exact adjoint
(transpose) of these filters. A run of even x even steps, the common case,
is one autograd node with a hand-written adjoint (spread each gradient 1/4
to its 2 x 2 block, folded coarse to fine), itself differentiable.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Iterator, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from ... import _native as native
from ..._checks import check_float, check_same, describe


def level_count(height: int, width: int) -> int:
    """Levels of the full chain for an ``height x width`` base, down to 1 x 1 (both included)."""
    return 1 + (max(height, width) - 1).bit_length()


def level_size(height: int, width: int, k: int) -> tuple[int, int]:
    """``(ceil(H / 2^k), ceil(W / 2^k))``, the size of level ``k``."""
    return -(-height // (1 << k)), -(-width // (1 << k))


def _box2(x: Tensor) -> Tensor:
    """2 x 2 box average of an even x even level."""
    kernel = native.kernel(x)
    if kernel is not None:
        # The same sums in one pass over the level (bit-identical; 0.5 vs
        # 0.85 ms measured at 1024^2 x 3 on CPU).
        return kernel.box2(x)
    # Two strided passes beat F.avg_pool2d by ~5x on CPU (measured, 1024^2).
    y = x[..., 0::2] + x[..., 1::2]
    return torch.add(y[..., 0::2, :], y[..., 1::2, :]).mul_(0.25)


class _EvenChain(torch.autograd.Function):
    """``n`` successive 2 x 2 box steps of an even chain, as one node.

    Outputs ``(x, box(x), box(box(x)), ...)`` (``x`` as a view), so that the
    backward receives every level's gradient at once and folds them
    coarse to fine with one broadcast add per level (``pyramid_adjoint``): no
    upsampled copy of a level's gradient, and no separate add for level 0's
    own gradient.
    """

    @staticmethod
    def forward(ctx, x: Tensor, n: int) -> tuple[Tensor, ...]:
        ctx.set_materialize_grads(False)
        ctx.hw = tuple(x.shape[-2:])
        out = [x.view_as(x)]
        for _ in range(n):
            out.append(_box2(out[-1]))
        return tuple(out)

    @staticmethod
    def backward(ctx, *grads: Tensor | None):
        return pyramid_adjoint(list(grads), ctx.hw, inplace=False), None


def pyramid_adjoint(grads: list[Tensor | None], base_hw: tuple[int, int], *, inplace: bool) -> Tensor | None:
    """Gradient of the base from gradients of levels ``0 .. n-1`` (None: no gradient), the transpose of the pyramid.

    Folds coarse to fine: level k gets its own gradient plus the transpose of
    the step k -> k+1 applied to level k+1's total. ``base_hw``: level 0's
    size. ``inplace``: add into (and scale) the given gradient buffers (the
    caller owns them; first order only), else out of place and differentiably.
    """
    acc = None
    for k in range(len(grads) - 1, -1, -1):
        acc = grads[k] if acc is None else step_adjoint(grads[k], acc, level_size(*base_hw, k), inplace)
    return acc


def step_adjoint(fine: Tensor | None, coarse: Tensor, fine_hw: tuple[int, int], inplace: bool) -> Tensor:
    """``fine`` plus the transpose of the step that made ``coarse`` from a level of size ``fine_hw``."""
    B, C, h, w = coarse.shape
    H, W = fine_hw
    if (H, W) != (2 * h, 2 * w):
        # Odd side: the exact transpose of _down_axis by autograd (the step
        # is linear, so any point of evaluation gives the same transpose).
        with torch.enable_grad():
            x = coarse.new_zeros((B, C, H, W), requires_grad=True)
            y = _down_axis(_down_axis(x, -1), -2)
            adj, = torch.autograd.grad(y, x, coarse, create_graph=torch.is_grad_enabled() and not inplace)
        return adj if fine is None else (fine.add_(adj) if inplace else fine + adj)
    kernel = native.kernel(coarse)
    # One pass that writes the fine gradient once (bit-identical; measured 2.2-2.5x faster than the nearest
    # upsampling below at 512^2 -> 1024^2 x 3). Not under create_graph (the kernel is not differentiable), nor
    # to add into a given buffer in place, which the broadcast add below already does in one pass.
    if kernel is not None and (fine is None if inplace else not torch.is_grad_enabled()):
        return kernel.box2_adjoint(coarse, fine)
    if fine is None:
        # Nearest 2x upsampling: 1.7x faster on CPU than a broadcast copy
        # (measured, 512^2 -> 1024^2); in place, the 1/4 needs no new buffer.
        return F.interpolate(coarse.mul_(0.25) if inplace else coarse * 0.25, size=(H, W), mode="nearest")
    # One broadcast add over the fine gradient: faster on CPU than nearest
    # upsampling followed by an add, and no upsampled copy (measured).
    f6 = fine.unflatten(-1, (w, 2)).unflatten(-3, (h, 2))
    c6 = coarse.view(B, C, h, 1, w, 1)
    if inplace:
        f6.add_(c6, alpha=0.25)
        return fine
    return torch.add(f6, c6, alpha=0.25).view(B, C, H, W)


@lru_cache(maxsize=256)
def _odd_taps(n: int) -> tuple[list[list[int]], list[list[float]]]:
    """Source indices and weights (3 per output) of the area-weighted box n -> (n + 1) // 2, n odd."""
    m = (n + 1) // 2
    idx, wts = [], []
    for j in range(m):
        # Work in units of 1/m so that every boundary is an integer: output j
        # covers [j n, (j + 1) n), source texel i covers [i m, (i + 1) m).
        lo, hi = j * n, (j + 1) * n
        row_i, row_w = [], []
        for i in range(lo // m, min(-(-hi // m), n)):
            overlap = min(hi, (i + 1) * m) - max(lo, i * m)
            if overlap > 0:
                row_i.append(i)
                row_w.append(overlap / n)
        while len(row_i) < 3:
            row_i.append(row_i[-1])
            row_w.append(0.0)
        idx.append(row_i)
        wts.append(row_w)
    return idx, wts


def _down_axis(x: Tensor, dim: int) -> Tensor:
    """Halve one axis (``dim`` = -1 for width, -2 for height) with the filters of the module docstring."""
    n = x.shape[dim]
    if n == 1:
        return x
    if n % 2 == 0:
        if dim == -1:
            return (x[..., 0::2] + x[..., 1::2]) * 0.5
        return (x[..., 0::2, :] + x[..., 1::2, :]) * 0.5
    idx_l, w_l = _odd_taps(n)
    m = len(idx_l)
    idx = torch.tensor(idx_l, device=x.device).flatten()
    w = torch.tensor(w_l, dtype=x.dtype, device=x.device)
    picked = x.index_select(dim, idx)
    if dim == -1:
        return (picked.unflatten(-1, (m, 3)) * w).sum(-1)
    return (picked.unflatten(-2, (m, 3)) * w.unsqueeze(-1)).sum(-2)


def build_levels(texture: Tensor, n: int) -> list[Tensor]:
    """Levels 0 .. n-1 of ``texture``: runs of even x even steps as one ``_EvenChain``, other steps axis by axis."""
    # A strided base (an NHWC texture's NCHW view) is copied once here; the
    # box steps and the kernels' reads would each copy it otherwise.
    levels = [texture.contiguous()]
    while len(levels) < n:
        x = levels[-1]
        H, W = x.shape[-2:]
        steps = 0
        while len(levels) + steps < n and H % (2 << steps) == 0 and W % (2 << steps) == 0:
            steps += 1
        if steps:
            levels[-1:] = _EvenChain.apply(x, steps)
        else:
            levels.append(_down_axis(_down_axis(x, -1), -2))
    return levels


class Pyramid:
    """A list of levels, level 0 the base: what every pyramid type (Mipmap, the cube's) shares."""

    __slots__ = ("levels",)

    def __init__(self, levels: Sequence[Tensor]):
        self.levels = list(levels)

    def __len__(self) -> int:
        return len(self.levels)

    def __getitem__(self, k: int) -> Tensor:
        return self.levels[k]

    def __iter__(self) -> Iterator[Tensor]:
        return iter(self.levels)

    @property
    def base(self) -> Tensor:
        return self.levels[0]


class Mipmap(Pyramid):
    """A mip pyramid: a list of levels ``[B, C, H_k, W_k]``, level 0 the base.

    Build one with ``difftex.mipmap``. The levels are ordinary tensors in the
    autograd graph; ``difftex.sample`` accepts a Mipmap wherever it accepts a
    texture (the single-level filters read level 0).
    """

    __slots__ = ()

    @property
    def shape(self) -> torch.Size:
        """Shape of level 0."""
        return self.levels[0].shape

    @property
    def dtype(self) -> torch.dtype:
        return self.levels[0].dtype

    @property
    def device(self) -> torch.device:
        return self.levels[0].device

    def __repr__(self) -> str:
        sizes = ", ".join(f"{t.shape[-2]}x{t.shape[-1]}" for t in self.levels)
        B, C = self.levels[0].shape[:2]
        return f"Mipmap(B={B}, C={C}, levels=[{sizes}], dtype={self.dtype}, device={self.device})"


def mipmap(texture: Tensor | Sequence[Tensor] | Mipmap, *, max_levels: int | None = None) -> Mipmap:
    """Build the mip pyramid of a texture, or wrap user-supplied levels.

    Args:
        texture: [B, C, H, W] float tensor (any H, W >= 1, odd included; see
            the module docstring for the odd-side filter), or a sequence of
            levels ``[B, C, ceil(H / 2^k), ceil(W / 2^k)]`` for k = 0, 1, ...
            (a prefix of the chain is fine), or a Mipmap (returned as is,
            truncated to ``max_levels``).
        max_levels: keep at most this many levels (>= 1); default: the full
            chain down to 1 x 1, ``1 + ceil(log2(max(H, W)))`` levels.

    Returns:
        Mipmap whose level 0 holds ``texture``'s values (a view of it when
        the next step is an even x even box, so that its gradient joins the
        pyramid's adjoint in one pass).

    Built levels are differentiable: gradients reach the base texture through
    the exact adjoint of the downsampling. Supplied levels each receive their
    own gradient. Raises TypeError on non-float tensors or mixed dtypes,
    ValueError naming the argument on bad shapes, mismatched levels, mixed
    devices or ``max_levels < 1``.
    """
    if max_levels is not None:
        if isinstance(max_levels, bool) or not isinstance(max_levels, int):
            raise TypeError(f"max_levels: expected an int >= 1 or None, got {type(max_levels).__name__}")
        if max_levels < 1:
            raise ValueError(f"max_levels: expected an int >= 1 or None, got {max_levels}")
    if isinstance(texture, Mipmap):
        levels = texture.levels
        return Mipmap(levels[:max_levels] if max_levels else levels)
    if isinstance(texture, (list, tuple)):
        return _from_levels(list(texture), max_levels)
    check_float("texture", texture, 4, shape_doc="[B, C, H, W]")
    B, C, H, W = texture.shape
    if min(B, C, H, W) < 1:
        raise ValueError(f"texture: expected B, C, H, W >= 1, got {describe(texture)}")
    n = level_count(H, W)
    if max_levels is not None:
        n = min(n, max_levels)
    return Mipmap(build_levels(texture, n))


def _from_levels(levels: list[Tensor], max_levels: int | None) -> Mipmap:
    if not levels:
        raise ValueError("texture: expected at least one level, got an empty sequence")
    base = check_float("texture[0]", levels[0], 4, shape_doc="[B, C, H, W]")
    B, C, H, W = base.shape
    if min(B, C, H, W) < 1:
        raise ValueError(f"texture[0]: expected B, C, H, W >= 1, got {describe(base)}")
    if len(levels) > level_count(H, W):
        raise ValueError(f"texture: {len(levels)} levels given but a {H}x{W} base has only "
                         f"{level_count(H, W)} (down to 1x1)")
    for k, lev in enumerate(levels[1:], 1):
        check_float(f"texture[{k}]", lev, 4, shape_doc="[B, C, H_k, W_k]")
        check_same(f"texture[{k}]", lev, "texture[0]", base)
        want = (B, C) + level_size(H, W, k)
        if tuple(lev.shape) != want:
            raise ValueError(f"texture[{k}]: expected shape {want} (ceil(H / 2^k) x ceil(W / 2^k)), "
                             f"got {describe(lev)}")
    return Mipmap(levels[:max_levels] if max_levels else levels)

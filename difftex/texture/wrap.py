"""Wrap modes: how integer texel indices outside the texture map back into it.

Every filter asks this one module which texel an out-of-range tap reads, so
repeat / clamp / mirror / border behave the same for nearest, bilinear,
bicubic and the mip-mapped filters built on them.

The modes and their `torch.nn.functional.grid_sample` counterparts
(``align_corners=False``):

=========  ==========================================  ======================
mode       texel read for index ``i`` of an axis of n  grid_sample padding
=========  ==========================================  ======================
repeat     ``i mod n``                                 (none: tile 3x3)
clamp      ``min(max(i, 0), n - 1)``                   ``"border"``
mirror     ``i mod 2n``, reflected into ``[0, n)``      ``"reflection"``
border     ``i`` if inside, else the border constant   ``"zeros"``
=========  ==========================================  ======================
"""
from __future__ import annotations

from functools import lru_cache
from typing import Sequence, Union

import torch
from torch import Tensor

WRAP_MODES = ("repeat", "clamp", "mirror", "border")
# The native kernel's code of each mode: its position in WRAP_MODES.
WRAP_CODES = {mode: code for code, mode in enumerate(WRAP_MODES)}
# From 2^52 on a float has no fractional part left: the cap of texel indices.
INDEX_CAP = 2.0 ** 52

Wrap = Union[str, Sequence[str]]


def parse_wrap(wrap: Wrap) -> tuple[str, str]:
    """Normalise ``wrap`` to a ``(wrap_u, wrap_v)`` pair of known modes.

    Args:
        wrap: one mode for both axes, or a pair ``(wrap_u, wrap_v)``;
            u runs along the texture width, v along its height.

    Raises ValueError naming ``wrap`` for unknown modes or a wrong length,
    TypeError for anything that is not a string or a pair of strings.
    """
    if isinstance(wrap, str):
        pair = (wrap, wrap)
    elif isinstance(wrap, (tuple, list)):
        if len(wrap) != 2:
            raise ValueError(f"wrap: expected one mode or a pair (wrap_u, wrap_v), got {len(wrap)} items {wrap!r}")
        pair = tuple(wrap)
    else:
        raise TypeError(f"wrap: expected a str or a (wrap_u, wrap_v) pair, got {type(wrap).__name__}")
    for mode in pair:
        if not isinstance(mode, str):
            raise TypeError(f"wrap: modes must be strings, got {type(mode).__name__}")
        if mode not in WRAP_MODES:
            raise ValueError(f"wrap: unknown mode {mode!r}; expected one of {WRAP_MODES}")
    return pair  # type: ignore[return-value]


def floor_index(x: Tensor) -> Tensor:
    """``floor(x)`` as int64, with NaN / inf mapped to 0 and magnitudes capped at 2**52.

    A bad coordinate thus lands on some in-range texel after wrapping and
    never reads outside the texture; its weights carry the NaN instead. Past
    2**52 a float has no fractional part left, so capping loses nothing.
    """
    i = torch.nan_to_num(torch.floor(x), nan=0.0, posinf=0.0, neginf=0.0)
    # float16 / bfloat16 cannot hold 2**52; their finite values are all below it.
    cap = min(INDEX_CAP, torch.finfo(x.dtype).max)
    return i.clamp_(-cap, cap).long()


def wrap_index(i: Tensor, n: int, mode: str) -> tuple[Tensor, Tensor | None]:
    """Map integer texel indices of one axis into ``[0, n)``.

    Args:
        i: int64 texel indices (e.g. from ``floor_index``); a float tensor is
            converted by ``floor_index`` first.
        n: texels along this axis (>= 1).
        mode: one of ``WRAP_MODES``.

    Returns:
        ``(index, valid)``: int64 indices in ``[0, n)``, and for ``"border"``
        a bool mask of taps that fall inside the texture (the others must
        read the border constant); ``None`` for the other modes.
    """
    if i.is_floating_point():
        i = floor_index(i)
    if mode == "repeat":
        return torch.remainder(i, n), None
    if mode == "mirror":
        r = torch.remainder(i, 2 * n)
        return torch.where(r >= n, 2 * n - 1 - r, r), None
    if mode == "clamp":
        return i.clamp(0, n - 1), None
    if mode == "border":
        valid = (i >= 0) & (i < n)
        return i.clamp(0, n - 1), valid
    raise ValueError(f"wrap: unknown mode {mode!r}; expected one of {WRAP_MODES}")


# The same rule on continuous coordinates (the grid_sample path and EWA fold uv; the native kernel restates
# these in C++, held equal by the tests of texture/native).


@lru_cache(maxsize=256)
def pad_index(mode: str, p: int, n: int, device: torch.device) -> Tensor:
    """Source texel of each of the ``n + 2p`` positions of an axis padded by ``p`` (repeat / mirror)."""
    i = torch.arange(-p, n + p, device=device)
    if mode == "repeat":
        return i % n
    return wrap_index(i, n, "mirror")[0]


def fold(u: Tensor, mode: str) -> Tensor:
    """Fold a uv coordinate into one period of the mode: [0, 1) for repeat, [0, 1] for mirror, else as is."""
    if mode == "repeat":
        return u - torch.floor(u)
    if mode == "mirror":
        # Triangle wave: 0 -> 0, 1 -> 1, 2 -> 0; slope +-1 like the mirror.
        h = u * 0.5
        return 1 - torch.abs(2 * (h - torch.floor(h)) - 1)
    return u


def fold_slope(u: Tensor, mode: str) -> Tensor | None:
    """d fold(u) / du: +-1 for mirror, None (1) for the other modes."""
    if mode != "mirror":
        return None
    h = u * 0.5
    return torch.where(h - torch.floor(h) < 0.5, 1.0, -1.0).to(u.dtype)


def drop_periods(u: Tensor, mode: str) -> Tensor:
    """u minus a whole number of the mode's periods (1 for repeat, 2 for mirror, none else); gradient 1."""
    if mode == "repeat":
        return u - torch.floor(u.detach())
    if mode == "mirror":
        return u - 2 * torch.floor(u.detach() * 0.5)
    return u

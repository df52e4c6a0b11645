"""Input checks shared by the public ops: one wording for every error."""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor


def describe(t: Tensor) -> str:
    return f"shape {tuple(t.shape)}, dtype {t.dtype}, device {t.device}"


def check_float(name: str, t: object, ndim: int | Sequence[int] | None = None, last: int | None = None,
                shape_doc: str = "") -> Tensor:
    """Raise TypeError / ValueError naming ``name`` unless ``t`` is a float tensor of the given rank.

    Args:
        name: argument name used in the message.
        t: the value to check.
        ndim: required number of dimensions (one or several allowed).
        last: required size of the last dimension.
        shape_doc: the expected shape as the docs write it, e.g. "[B, Ho, Wo, 2]".
    """
    expect = f" {shape_doc}" if shape_doc else ""
    if not isinstance(t, Tensor):
        raise TypeError(f"{name}: expected a float tensor{expect}, got {type(t).__name__}")
    if not t.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor (float32 or float64){expect}, got {describe(t)}")
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if t.dim() not in allowed:
            raise ValueError(f"{name}: expected {' or '.join(f'{d}-D' for d in allowed)}{expect}, got {describe(t)}")
    if last is not None and (t.dim() == 0 or t.shape[-1] != last):
        raise ValueError(f"{name}: expected last dimension {last}{expect}, got {describe(t)}")
    return t


def check_same(name: str, t: Tensor, ref_name: str, ref: Tensor) -> None:
    """Raise ValueError / TypeError unless ``t`` shares ``ref``'s device and dtype."""
    if t.device != ref.device:
        raise ValueError(f"{name}: expected device {ref.device} like {ref_name}, got {describe(t)}")
    if t.dtype != ref.dtype:
        raise TypeError(f"{name}: expected dtype {ref.dtype} like {ref_name}, got {describe(t)}")


def broadcast_batch(names: Sequence[str], sizes: Sequence[int]) -> int:
    """The common batch size of several tensors where 1 broadcasts; ValueError otherwise."""
    big = {s for s in sizes if s != 1}
    if len(big) > 1:
        listed = ", ".join(f"{n} {s}" for n, s in zip(names, sizes))
        raise ValueError(f"batch sizes do not match ({listed}): expected equal sizes or 1")
    return big.pop() if big else 1


def check_index(name: str, idx: object, num_rows: int, rows_doc: str, device: torch.device, *,
                check_range: bool = True) -> Tensor:
    """An [F, 3] integer index array into ``num_rows`` rows, as int64 on ``device``.

    Raises TypeError unless ``idx`` is an integer tensor, ValueError naming
    ``name`` on another shape or indices outside ``[0, num_rows)``;
    ``rows_doc`` says what the rows are (e.g. "number of vertices").
    ``check_range=False`` leaves the range (a pass over all indices) to a
    caller whose kernel tests every index anyway and calls this again with
    the check where one is out of range.
    """
    if not isinstance(idx, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(idx).__name__}")
    if idx.dtype.is_floating_point or idx.dtype.is_complex or idx.dtype == torch.bool:
        raise TypeError(f"{name} must be an integer tensor, got dtype {idx.dtype}")
    if idx.dim() != 2 or idx.shape[1] != 3:
        raise ValueError(f"{name} must have shape [F, 3], got {tuple(idx.shape)}")
    idx = idx.to(device=device, dtype=torch.int64)
    if check_range and idx.numel() > 0:
        lo, hi = (int(v) for v in torch.aminmax(idx))  # one pass, not two
        if lo < 0 or hi >= num_rows:
            raise ValueError(f"{name} indices must lie in [0, {num_rows - 1}] ({rows_doc}), got values in [{lo}, {hi}]")
    return idx

"""What the shading ops share: the safe normalisation and the checks of broadcast operands."""
from __future__ import annotations

import numbers
from typing import Union

import torch
from torch import Tensor

from .._checks import check_float, check_same
from ..geometry.mesh import unit  # noqa: F401  (re-exported for the shading modules)

Operand = Union[Tensor, float]


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the last axis, keeping it (size 1)."""
    return (a * b).sum(-1, keepdim=True)


def check_vectors(name: str, x: object, like: Tensor | None = None, like_name: str = "normals") -> Tensor:
    """A float tensor [..., 3] (on ``like``'s device and dtype when given); TypeError / ValueError naming ``name``."""
    check_float(name, x, last=3, shape_doc="[..., 3]")
    if like is not None:
        check_same(name, x, like_name, like)  # type: ignore[arg-type]
    return x  # type: ignore[return-value]


def operand(name: str, x: object, like: Tensor, shape_doc: str, like_name: str = "normals") -> Tensor:
    """A number or a float tensor as a tensor on ``like``'s device and dtype.

    Raises TypeError naming ``name`` for anything else (a bool, a string, an
    integer tensor, another dtype), ValueError for a device mismatch or a
    non-finite number.
    """
    if isinstance(x, Tensor):
        check_float(name, x, shape_doc=shape_doc)
        check_same(name, x, like_name, like)
        return x
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise TypeError(f"{name}: expected a number or a float tensor {shape_doc}, got {type(x).__name__}")
    if not torch.isfinite(torch.tensor(float(x))):
        raise ValueError(f"{name}: expected a finite number, got {x!r}")
    return torch.tensor(float(x), dtype=like.dtype, device=like.device)


def broadcast(shapes: dict[str, torch.Size]) -> torch.Size:
    """The broadcast of several named shapes; ValueError listing them when they do not broadcast."""
    try:
        return torch.broadcast_shapes(*shapes.values())
    except RuntimeError:
        listed = ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
        raise ValueError(f"shapes do not broadcast ({listed})") from None


__all__ = ["unit", "dot", "check_vectors", "operand", "broadcast"]

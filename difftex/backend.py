"""Which implementation runs a texture read: the one place that decides.

difftex has three implementations of its reads, all giving the same values
and gradients to rounding (the tests hold them equal):

* ``"native"``: the C++ CPU kernel (``difftex._native``) for the
  single-level reads (nearest, bilinear, bicubic), the mip filters' taps
  and footprint front end, EWA and the pyramid's box step; float32 /
  float64 tensors on the CPU, where the kernel built.
* ``"grid_sample"``: torch ops, with the single-level reads on
  ``torch.nn.functional.grid_sample`` and hand-written first-order
  backwards (``texture/filters/grid.py``); every device and dtype.
* ``"gather"``: torch ops, with the single-level reads as the gather /
  scatter reference (``texture/filters/gather.py``), differentiable to any
  order; the reference the others are tested against.

A program picks with :func:`backend` (a context manager, or a plain call
that sets the choice until changed):

* ``"auto"`` (default): native where it serves, else grid_sample;
  ``DIFFTEX_NATIVE=0`` in the environment keeps the kernel off (never built);
* ``"native"``: as auto, but a CPU read raises RuntimeError where the kernel
  cannot be built instead of falling back;
* ``"grid_sample"``: the torch path, kernel off;
* ``"reference"``: the gather reference for every read, kernel off.

``rasterize`` / ``depth_peel`` follow the same choice: "auto" and "native"
run their visibility pass and their barycentric pass (forward and
first-order backward) in the native kernel on the CPU (identical triangle
ids), the other two the torch path (geometry/raster.py, the reference).

Whatever the choice, double backward (``create_graph=True``) runs the
differentiable torch ops, and CUDA / MPS / XPU tensors never reach the
CPU kernel.
"""
from __future__ import annotations

import contextlib
import threading

import torch
from torch import Tensor

CHOICES = ("auto", "native", "grid_sample", "reference")

_state = threading.local()


def current() -> str:
    """The choice in force in this thread: one of ``CHOICES``."""
    return getattr(_state, "choice", "auto")


class _Switch(contextlib.AbstractContextManager):
    """The value of :func:`backend`: already in force; as a context manager it restores the previous choice."""

    def __init__(self, previous: str):
        self.previous = previous

    def __exit__(self, *exc) -> None:
        _state.choice = self.previous


def backend(choice: str) -> _Switch:
    """Choose the implementation of difftex's texture reads (see the module notes).

    Args:
        choice: "auto" | "native" | "grid_sample" | "reference".

    Returns:
        A context manager; ``with difftex.backend("reference"): ...`` runs the
        block with that choice and restores the previous one (per thread).
        Called on its own, the choice stays until the next call.

    Raises ValueError naming ``choice`` for an unknown name. Under "native", a
    read of CPU float32 / float64 tensors raises RuntimeError where the kernel
    cannot be built (or ``DIFFTEX_NATIVE=0``) instead of falling back.
    """
    if not isinstance(choice, str) or choice not in CHOICES:
        raise ValueError(f"backend: unknown choice {choice!r}; expected one of {CHOICES}")
    previous = current()
    _state.choice = choice
    return _Switch(previous)


def wants_native(like: Tensor) -> bool:
    """Whether reads of tensors like ``like`` go to the native kernel, where it is built.

    Yes for float32 / float64 CPU tensors under the choices "auto" and
    "native"; ``difftex._native.kernel`` adds whether it built.
    """
    return (current() in ("auto", "native") and like.device.type == "cpu"
            and like.dtype in (torch.float32, torch.float64))


def single_level() -> str:
    """The torch implementation of the single-level (nearest / bilinear / bicubic) reads: "grid_sample" or "gather".

    Where this says "grid_sample", CPU float32 / float64 reads go to the
    native kernel instead where it is built (``wants_native``)."""
    return "gather" if current() == "reference" else "grid_sample"

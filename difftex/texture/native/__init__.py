"""The native CPU kernel of the texture reads (C++ sources in ``csrc/``): built on first use, optional.

The single-level reads (nearest, bilinear, bicubic; ``filters/separable.py``)
are one threaded pass over the points, forward and first-order backward
(``csrc/single.cpp``), the gather reference and the grid_sample path staying
the tested references. Their float32 bilinear / bicubic reads go eight
points at a time where the CPU has AVX2 (``set_simd``), the forward sixteen
where it has AVX-512 (``set_wide``), with the scalar loop's bits.

The trilinear / nearest-mip taps of a pyramid, one a point or N along the
footprint's major axis (the trilinear, nearest-mip, anisotropic and auto
filters), are one pass over the points in C++ on the CPU: no tap list, no
sorting of points by level, no per-level passes, and a backward that
touches only the texels read. EWA is one pass too, forward and backward.
The same module holds two smaller passes: the footprint front end of the
tap filters (level, and the anisotropic / auto tap count and axis, per
point) where no derivative needs a gradient, and the 2 x 2 box step of the
pyramid build. The torch path (``mip_blend`` over grid_sample,
``filters/trilinear.py``; ``filters/ewa.py``; ``lod.py`` and the tap
counts; ``mipmap._box2``) stays the reference the tests compare it with,
and runs wherever this kernel does not: on CUDA, for double backward, with
``DIFFTEX_NATIVE=0`` in the environment, or where the build fails (no C++
compiler or ninja), which is reported once as a warning.

The sources, one per kernel: ``csrc/taps.cpp`` (the taps, forward and
backward), ``csrc/front.cpp``, ``csrc/box.cpp``, ``csrc/ewa.cpp``,
``csrc/single.cpp`` (the single-level reads), ``csrc/cube.cpp`` (the cube-map
front end and read of ``difftex.envmap.cubemap``, declared in ``csrc/cube.h``),
``csrc/sat.cpp`` and ``csrc/ripmap.cpp`` (the box filters "sat" and "ripmap":
table / level build, read and adjoint, declared in ``csrc/boxes.h``),
with ``csrc/bands.h`` (the
threaded, lock-free texture-gradient scatter of single.cpp and taps.cpp),
``csrc/common.h`` (the shared inline helpers and the constants mirrored from
the Python reference), ``csrc/kernels.h`` (the entry points and their
options) and ``csrc/module.cpp`` (the Python bindings). The module exports
its constants (``FAR``, ``RATIO_TOL``, ``WRAP_CODES``, ...), which the tests
check against the Python ones.

The first use compiles the kernel with ``torch.utils.cpp_extension.load``
(about 30-60 s; cached by torch in ``TORCH_EXTENSIONS_DIR``, by default
``~/.cache/torch_extensions``, and reused while the sources are unchanged:
ninja rebuilds what a changed source or header touches). Where no ``ninja``
is on PATH, the one of the ``ninja`` pip package (a dependency) is put there.
"""
from __future__ import annotations

import os
import shutil
import sys
import warnings
from pathlib import Path
from types import ModuleType
from typing import Callable, Optional, Sequence

import torch
from torch import Tensor

from ...backend import current, wants_native

_CSRC = Path(__file__).resolve().parent / "csrc"
_NAME = "difftex_native"
_module: ModuleType | None = None
_tried = False


def enabled() -> bool:
    """Whether the native kernel is wanted (``DIFFTEX_NATIVE`` is not ``0``)."""
    return os.environ.get("DIFFTEX_NATIVE", "1") != "0"


def load() -> ModuleType | None:
    """The compiled kernel module, building it on the first call; None where disabled or the build failed."""
    global _module, _tried
    if not enabled():
        return None
    if _tried:
        return _module
    _tried = True
    try:
        from torch.utils import cpp_extension
        try:
            built = any(Path(cpp_extension._get_build_directory(_NAME, False)).glob(f"{_NAME}*.so"))
        except Exception:  # a private helper: if it moves, just say so every time
            built = False
        if not built:
            print("difftex: building the native CPU kernel (first use only, about a minute; "
                  "DIFFTEX_NATIVE=0 skips it)...", file=sys.stderr, flush=True)
        # MSVC spells it differently. No contraction into fused multiply-adds (on by default where the target
        # has them, e.g. aarch64): the raster kernel must round each product as the torch path does.
        flags = ["/O2", "/fp:precise"] if os.name == "nt" else ["-O3", "-ffp-contract=off"]
        # at::parallel_for runs serially unless the extension itself is built with OpenMP (as torch is
        # on Linux); elsewhere the kernel stays single-threaded rather than depend on a libomp install.
        omp = ["-fopenmp"] if sys.platform.startswith("linux") else []
        _ninja_on_path()
        _module = cpp_extension.load(name=_NAME, sources=[str(p) for p in sorted(_CSRC.glob("*.cpp"))],
                                     extra_include_paths=[str(_CSRC)], extra_cflags=flags + omp,
                                     extra_ldflags=omp, verbose=False)
    except Exception as exc:  # no compiler, no ninja, a failed build: the torch path serves
        warnings.warn(f"difftex: native CPU kernel unavailable, using the torch path ({type(exc).__name__}: "
                      f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else exc})", RuntimeWarning,
                      stacklevel=2)
        _module = None
    return _module


def _ninja_on_path() -> None:
    """Put the ``ninja`` pip package's binary on PATH where no ninja is there (e.g. a venv not activated)."""
    if shutil.which("ninja") is not None:
        return
    try:
        import ninja
    except ImportError:  # then cpp_extension reports the missing ninja, and the torch path serves
        return
    os.environ["PATH"] = ninja.BIN_DIR + os.pathsep + os.environ.get("PATH", "")


def double_backward(recompute: Callable[[], Tensor], saved: Sequence[Optional[Tensor]], need: Sequence[bool],
                    grad: Tensor) -> tuple:
    """A kernel node's backward under ``create_graph=True``: the gradients of the differentiable torch path.

    ``recompute()`` evaluates the node's output from ``saved`` (its inputs, in
    order; None for non-tensor ones) with torch ops; returns one gradient per
    input, None where ``need`` is False, each itself differentiable.
    """
    inputs = [(i, t) for i, t in enumerate(saved) if need[i] and t is not None]
    with torch.enable_grad():
        out = recompute()
    got = torch.autograd.grad(out, [t for _, t in inputs], grad, create_graph=True, allow_unused=True)
    full: list[Optional[Tensor]] = [None] * len(saved)
    for (i, _), g in zip(inputs, got):
        full[i] = g
    return tuple(full)


def level_grads(grads: Sequence[Optional[Tensor]], need: Sequence[bool], levels: Sequence[Tensor]) -> tuple:
    """A kernel node's level gradients, ``[1, C, h, w]`` each, from the kernel's ``[C, h, w]`` (None: not read).

    None where not needed. Where every needed one came back empty (no point
    read a level, e.g. every point masked), the first gets zeros: the texture
    then has a zero gradient, as on the torch path, rather than none.
    """
    out = [g.unsqueeze(0) if g is not None and n else None for g, n in zip(grads, need)]
    if any(need) and all(g is None for g in out):
        first = list(need).index(True)
        out[first] = torch.zeros_like(levels[first])
    return tuple(out)


def kernel(like: Tensor) -> ModuleType | None:
    """The kernel module where ``difftex.backend``'s choice sends reads of tensors like ``like``, else None.

    Builds the kernel on first use. Raises RuntimeError where the choice is
    "native" and the kernel is not available (``DIFFTEX_NATIVE=0``, or the
    build failed).
    """
    if not wants_native(like):
        return None
    module = load()
    if module is None and current() == "native":
        raise RuntimeError("difftex.backend('native'): the native CPU kernel is not available "
                           "(DIFFTEX_NATIVE=0, or its build failed: see the warning)")
    return module

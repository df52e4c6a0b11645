"""The native CPU kernels (C++ in ``difftex/csrc``), built at install time into ``difftex._C``: optional.

The ground floor of the package: ``geometry`` (the rasterizer), ``texture``
(the samplers, the pyramid build) and ``envmap`` (the cube map) all reach
their kernels through this module, and it imports nothing of theirs.

The kernels are torch operators, ``torch.ops.difftex.*``, registered through
torch's LibTorch stable ABI when ``difftex._C`` is imported (so one build
runs on torch 2.10 and later). Nothing is compiled at run time: where the
install could not build them (no C++ compiler, torch missing from the build
environment, torch < 2.10), ``load`` warns once, naming what is missing, and
every read takes the torch path, which computes the same values and stays
the tested reference. ``DIFFTEX_NATIVE=0`` forces the torch path.

``load`` returns a :class:`Kernel`: the operators under short names, with
the read options as small named tuples, plus the module's constants (the
ones mirrored from the Python reference, checked by the tests) and the
SIMD switches the tests turn. The kernels run on CPU tensors only; CUDA
tensors take the torch path (``difftex.backend``). Fake (meta)
implementations make the operators traceable by ``torch.compile`` and
checkable by ``torch.library.opcheck``.
"""
from __future__ import annotations

import importlib
import os
import warnings
from types import ModuleType
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch
from torch import Tensor

from .backend import current, wants_native

__all__ = ["EwaNeeds", "Kernel", "ReadOptions", "TapNeeds", "double_backward", "enabled", "kernel", "level_grads",
           "load"]


@dataclass(frozen=True, kw_only=True, slots=True)
class ReadOptions:
    """How a pyramid read treats the texture: wrap codes (texture/wrap.py WRAP_CODES) per axis, the border
    constant, nearest-mip (one level) instead of a blend of two, and whether D needs a gradient. By keyword
    only, so that no caller counts boolean positions; raises ValueError for a wrap code outside 0-3."""
    wrap_u: int
    wrap_v: int
    border: float = 0.0
    nearest: bool = False
    d_grad: bool = False

    def __post_init__(self) -> None:
        for name in ("wrap_u", "wrap_v"):
            if getattr(self, name) not in (0, 1, 2, 3):
                raise ValueError(f"ReadOptions: {name} must be a wrap code 0-3, got {getattr(self, name)}")

    def flat(self) -> tuple:
        return self.wrap_u, self.wrap_v, float(self.border), self.nearest, self.d_grad


@dataclass(frozen=True, kw_only=True, slots=True)
class TapNeeds:
    """The gradients the taps' backward computes."""
    levels: bool = False
    uv: bool = False
    D: bool = False
    axis: bool = False


@dataclass(frozen=True, kw_only=True, slots=True)
class EwaNeeds:
    """The gradients the EWA backward computes (ellipse: sigma, minor and scale)."""
    levels: bool = False
    uv: bool = False
    ellipse: bool = False
    D: bool = False


class Kernel:
    """The native operators under the names the callers use, and ``difftex._C``'s constants and switches.

    Each method is one ``torch.ops.difftex`` call; the shapes and semantics
    are documented beside the C++ entry points (``csrc/cpu/kernels.h``,
    ``boxes.h``, ``envmap/cube.h``). Gradients a backward was not asked for,
    or levels no point read, come back as None.
    """

    ReadOptions = ReadOptions
    TapNeeds = TapNeeds
    EwaNeeds = EwaNeeds

    def __init__(self, module: ModuleType):
        self._module = module
        self._ops = torch.ops.difftex

    def __getattr__(self, name: str):
        return getattr(self._module, name)  # constants, WRAP_CODES / KIND_CODES, set_simd, ...

    def __dir__(self) -> list[str]:
        return sorted(set(super().__dir__()) | set(dir(self._module)))

    # taps.cpp / front.cpp / box.cpp: the mip taps, their front end, the pyramid's box step
    def forward(self, levels, uv, D, axis, count, opts: ReadOptions) -> Tensor:
        return self._ops.taps_forward(levels, uv, D, axis, count, *opts.flat())

    def backward(self, levels, uv, D, axis, count, grad, opts: ReadOptions, need: TapNeeds):
        gl, *rest = self._ops.taps_backward(levels, uv, D, axis, count, grad, *opts.flat(), need.levels, need.uv,
                                            need.D, need.axis)
        return (_read(gl), *rest)

    def stochastic_forward(self, levels, uv, D, seed: int, first: int, strata: int, opts: ReadOptions) -> Tensor:
        return self._ops.stochastic_taps_forward(levels, uv, D, seed, first, strata, opts.wrap_u, opts.wrap_v,
                                                 float(opts.border))

    def stochastic_backward(self, levels, uv, D, grad, seed: int, first: int, strata: int, opts: ReadOptions,
                            need: TapNeeds):
        gl, *rest = self._ops.stochastic_taps_backward(levels, uv, D, grad, seed, first, strata, opts.wrap_u,
                                                       opts.wrap_v, float(opts.border), need.levels, need.uv,
                                                       need.D)
        return (_read(gl), *rest)

    def probe_offsets(self, count: Tensor, like: Tensor, seed: int, first: int, strata: int) -> Tensor:
        return self._ops.probe_offsets(count, like, seed, first, strata)

    def front(self, dx, dy, bias, *, bias0, height, width, levels, kind, max_aniso, tolerance):
        return self._ops.tap_front(dx, dy, bias, bias0, height, width, levels, kind, max_aniso, tolerance)

    def box2(self, x: Tensor) -> Tensor:
        return self._ops.box2(x)

    def box2_adjoint(self, coarse: Tensor, fine: Optional[Tensor] = None) -> Tensor:
        return self._ops.box2_adjoint(coarse, fine)

    # ewa.cpp
    def ewa(self, levels, uv, sigma, minor, scale, D, full_h, full_w, opts: ReadOptions) -> Tensor:
        if opts.nearest:
            raise ValueError("ewa: nearest-mip is not an EWA option")
        return self._ops.ewa_forward(levels, uv, sigma, minor, scale, D, full_h, full_w, opts.wrap_u, opts.wrap_v,
                                     opts.border, opts.d_grad)

    def ewa_backward(self, levels, uv, sigma, minor, scale, D, grad, full_h, full_w, opts: ReadOptions,
                     need: EwaNeeds):
        gl, *rest = self._ops.ewa_backward(levels, uv, sigma, minor, scale, D, grad, full_h, full_w, opts.wrap_u,
                                           opts.wrap_v, opts.border, opts.d_grad, need.levels, need.uv,
                                           need.ellipse, need.D)
        return (_read(gl), *rest)

    # single.cpp
    def sample(self, texture, uv, kind: int, opts: ReadOptions) -> Tensor:
        return self._ops.sample_forward(texture, uv, kind, opts.wrap_u, opts.wrap_v, opts.border)

    def sample_backward(self, texture, uv, grad, kind: int, opts: ReadOptions, *, need_texture: bool,
                        need_uv: bool):
        return self._ops.sample_backward(texture, uv, grad, kind, opts.wrap_u, opts.wrap_v, opts.border,
                                         need_texture, need_uv)

    # raster.cpp
    def raster(self, pos, faces, H, W, cull, bits, floor_z, floor_id, *, count: bool = False, layers: int = 1):
        return self._ops.raster(pos, faces, H, W, cull, bits, floor_z, floor_id, count, layers)

    def raster_fragments(self, pos, faces, tri_id, *, packed: bool = False, offset: int = 0,
                         derivatives: bool = True):
        return self._ops.raster_fragments(pos, faces, tri_id, packed, offset, derivatives)

    def raster_fused(self, pos, faces, H, W, cull, bits, *, derivatives: bool = True, keep_depth: bool = False,
                     layers: int = 1):
        return self._ops.raster_fused(pos, faces, H, W, cull, bits, derivatives, keep_depth, layers)

    def raster_fragments_backward(self, pos, faces, tri_id, idx, grads, packed: bool) -> Tensor:
        return self._ops.raster_fragments_backward(pos, faces, tri_id, idx, grads, packed)

    # cube.cpp
    def cube_front(self, dirs, dx, dy, bias, *, bias0, S, levels, band):
        return self._ops.cube_front(dirs, dx, dy, bias, bias0, S, levels, band)

    def cube_front_backward(self, dirs, dx, dy, bias, *, bias0, S, levels, band, guv, gD, need_derivs, need_bias):
        return self._ops.cube_front_backward(dirs, dx, dy, bias, bias0, S, levels, band, guv, gD, need_derivs,
                                             need_bias)

    def cube_read(self, levels, ring_idx, ring_w, face, uv, D, nearest: bool, d_grad: bool) -> Tensor:
        return self._ops.cube_read(levels, ring_idx, ring_w, face, uv, D, nearest, d_grad)

    def cube_read_backward(self, levels, ring_idx, ring_w, face, uv, D, grad, nearest, d_grad, *, need_levels,
                           need_uv, need_D):
        gl, *rest = self._ops.cube_read_backward(levels, ring_idx, ring_w, face, uv, D, grad, nearest, d_grad,
                                                 need_levels, need_uv, need_D)
        return (_read(gl), *rest)

    # sat.cpp / ripmap.cpp: the box filters
    def sat_forward(self, texture, pu, cu, pv, cv, *, jacobians: bool = False, coef_grads: bool = True):
        return self._ops.sat_forward(texture, pu, cu, pv, cv, jacobians, coef_grads)

    def sat_backward(self, texture, pu, cu, pv, cv, grad) -> Tensor:
        return self._ops.sat_backward(texture, pu, cu, pv, cv, grad)

    def ripmap_build(self, texture, n_u: int, n_v: int, wanted: Sequence[bool]):
        built = self._ops.ripmap_build(texture, n_u, n_v, [int(w) for w in wanted])
        if built and built[0] is None and wanted[0]:  # level (0, 0) is the texture (an op output may not alias it)
            built[0] = texture.contiguous()
        return built

    def ripmap_adjoint(self, grads, n_u: int, n_v: int, H: int, W: int) -> Tensor:
        return self._ops.ripmap_adjoint(grads, n_u, n_v, H, W)

    def ripmap_read(self, levels, n_u, uv, Du, Dv, opts: ReadOptions) -> Tensor:
        return self._ops.ripmap_read(levels, n_u, uv, Du, Dv, opts.wrap_u, opts.wrap_v, opts.border, opts.d_grad)

    def ripmap_read_backward(self, levels, n_u, uv, Du, Dv, grad, opts: ReadOptions, *, need_levels, need_uv,
                             need_D):
        gl, *rest = self._ops.ripmap_read_backward(levels, n_u, uv, Du, Dv, grad, opts.wrap_u, opts.wrap_v,
                                                   opts.border, opts.d_grad, need_levels, need_uv, need_D)
        return (_read(gl), *rest)


def _read(grads: list) -> list:
    """A backward's level gradients with None for the levels not read (the ops return them with no rows)."""
    return [g if g.shape[0] else None for g in grads]


_kernel: Kernel | None = None
_tried = False

#: How to get the kernels where the install did not build them.
HOW_TO_BUILD = ("install torch >= 2.10 and a C++17 compiler, then reinstall difftex with "
                "`pip install --no-build-isolation .` (or `make test`)")


def enabled() -> bool:
    """Whether the native kernels are wanted (``DIFFTEX_NATIVE`` is not ``0``)."""
    return os.environ.get("DIFFTEX_NATIVE", "1") != "0"


def load() -> Kernel | None:
    """The native kernels, or None where disabled or not built (warned once). Never compiles anything."""
    global _kernel, _tried
    if not enabled():
        return None
    if _tried:
        return _kernel
    _tried = True
    try:
        _C = importlib.import_module(f"{__package__}._C")
    except ImportError as exc:
        warnings.warn(f"difftex: the native CPU kernels are not built ({exc}); using the torch path (same "
                      f"results, slower). To get them: {HOW_TO_BUILD}", RuntimeWarning, stacklevel=2)
        return None
    _register_fakes()
    _kernel = Kernel(_C)
    return _kernel


def kernel(like: Tensor) -> Kernel | None:
    """The kernels where ``difftex.backend``'s choice sends reads of tensors like ``like``, else None.

    Raises RuntimeError where the choice is "native" and the kernels are not
    available (``DIFFTEX_NATIVE=0``, or not built: see the warning).
    """
    if not wants_native(like):
        return None
    k = load()
    if k is None and current() == "native":
        raise RuntimeError("difftex.backend('native'): the native CPU kernels are not available "
                           f"(DIFFTEX_NATIVE=0, or not built: {HOW_TO_BUILD})")
    return k


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


_fakes_registered = False


def _register_fakes() -> None:
    """Shapes and dtypes of every operator's outputs from its inputs', for torch.compile and opcheck.

    Which level gradients a backward returns (None: no point read the
    level) and how many pixels a triangle covers depend on the data, so
    those outputs' sizes are unbacked (``new_dynamic_size``) or, for the
    optional gradients, given for every level.
    """
    global _fakes_registered
    if _fakes_registered:
        return
    _fakes_registered = True
    from torch.library import get_ctx, register_fake

    def like(t: Tensor, *shape: int, dtype: Optional[torch.dtype] = None) -> Tensor:
        return t.new_empty(shape, dtype=dtype or t.dtype)

    def level_grads(levels, dtype) -> list:
        # Which levels a point reads depends on the data: a read level's gradient has its rows, an unread
        # one none (difftex._native._read), so the first size is unbacked.
        return [levels[0].new_empty((get_ctx().new_dynamic_size(), *t.shape[1:]), dtype=dtype) for t in levels]

    @register_fake("difftex::taps_forward")
    def _(levels, uv, D, axis, count, wrap_u, wrap_v, border, nearest, d_grad):
        return like(uv, levels[0].shape[0], uv.shape[0])

    @register_fake("difftex::taps_backward")
    def _(levels, uv, D, axis, count, grad, wrap_u, wrap_v, border, nearest, d_grad, need_levels, need_uv, need_D,
          need_axis):
        return (level_grads(levels, uv.dtype), torch.empty_like(uv) if need_uv else None,
                torch.empty_like(D) if need_D else None, torch.empty_like(uv) if need_axis else None)

    @register_fake("difftex::stochastic_taps_forward")
    def _(levels, uv, D, seed, first, strata, wrap_u, wrap_v, border):
        return like(uv, levels[0].shape[0], uv.shape[0])

    @register_fake("difftex::stochastic_taps_backward")
    def _(levels, uv, D, grad, seed, first, strata, wrap_u, wrap_v, border, need_levels, need_uv, need_D):
        return (level_grads(levels, uv.dtype), torch.empty_like(uv) if need_uv else None,
                torch.empty_like(D) if need_D else None)

    @register_fake("difftex::probe_offsets")
    def _(count, like_, seed, first, strata):
        return like_.new_empty(count.shape[0])

    @register_fake("difftex::tap_front")
    def _(dx, dy, bias, bias0, H, W, levels, kind, max_aniso, tolerance):
        M = dx.shape[0]
        taps = kind != 0
        return (like(dx, M), like(dx, M, 2) if taps else like(dx, 0, 2),
                like(dx, M, dtype=torch.int64) if taps else like(dx, 0, dtype=torch.int64))

    @register_fake("difftex::box2")
    def _(x):
        return like(x, *x.shape[:-2], x.shape[-2] // 2, x.shape[-1] // 2)

    @register_fake("difftex::box2_adjoint")
    def _(coarse, fine):
        return like(coarse, *coarse.shape[:-2], 2 * coarse.shape[-2], 2 * coarse.shape[-1])

    @register_fake("difftex::ewa_forward")
    def _(levels, uv, sigma, minor, scale, D, full_h, full_w, wrap_u, wrap_v, border, d_grad):
        return like(uv, levels[0].shape[0], uv.shape[0])

    @register_fake("difftex::ewa_backward")
    def _(levels, uv, sigma, minor, scale, D, grad, full_h, full_w, wrap_u, wrap_v, border, d_grad, need_levels,
          need_uv, need_ellipse, need_D):
        return (level_grads(levels, uv.dtype), torch.empty_like(uv) if need_uv else None,
                *[torch.empty_like(t) if need_ellipse else None for t in (sigma, minor, scale)],
                torch.empty_like(D) if need_D else None)

    def single_shape(texture, uv):
        return (uv.shape[0], texture.shape[1], *uv.shape[1:-1])

    @register_fake("difftex::sample_forward")
    def _(texture, uv, kind, wrap_u, wrap_v, border):
        return like(uv, *single_shape(texture, uv))

    @register_fake("difftex::sample_backward")
    def _(texture, uv, grad, kind, wrap_u, wrap_v, border, need_texture, need_uv):
        return (torch.empty_like(texture) if need_texture else None, torch.empty_like(uv) if need_uv else None)

    @register_fake("difftex::raster")
    def _(pos, faces, H, W, cull, bits, floor_z, floor_id, count, layers):
        n = pos.shape[0] * H * W
        return like(pos, n * layers, dtype=torch.int64), like(pos, n, dtype=torch.float64)

    @register_fake("difftex::raster_fragments")
    def _(pos, faces, tri_id, packed, offset, derivatives):
        N = get_ctx().new_dynamic_size()
        B, H, W = tri_id.shape
        idx = like(pos, N, dtype=torch.int64)

        def deriv(*shape):  # empty [0] where the derivatives are not asked for
            return like(pos, *shape) if derivatives else like(pos, 0)
        if packed:
            return [idx, like(pos, B, H, W, 4), deriv(B, H, W, 4)]
        return [idx, like(pos, N, 3), deriv(N, 3), deriv(N, 3), like(pos, B, H, W, 3), like(pos, B, H, W),
                deriv(B, H, W, 3), deriv(B, H, W, 3)]

    @register_fake("difftex::raster_fused")
    def _(pos, faces, H, W, cull, bits, derivatives, keep_depth, layers):
        B = pos.shape[0]
        n = B * H * W

        def deriv(*shape):  # empty [0] where the derivatives are not asked for
            return like(pos, *shape) if derivatives else like(pos, 0)
        out = [like(pos, n, dtype=torch.int64) for _ in range(layers)]
        out.append(like(pos, n if keep_depth else 0, dtype=torch.float64))
        for _ in range(layers):
            N = get_ctx().new_dynamic_size()
            out += [like(pos, N, dtype=torch.int64), like(pos, N, 3), deriv(N, 3), deriv(N, 3), like(pos, B, H, W, 3),
                    like(pos, B, H, W), deriv(B, H, W, 3), deriv(B, H, W, 3)]
        return out

    @register_fake("difftex::raster_fragments_backward")
    def _(pos, faces, tri_id, idx, grads, packed):
        return torch.empty_like(pos)

    @register_fake("difftex::cube_front")
    def _(dirs, dx, dy, bias, bias0, S, levels, band):
        M = dirs.shape[0]
        return like(dirs, M, dtype=torch.int8), like(dirs, M, 2), like(dirs, M if dx.numel() else 0)

    @register_fake("difftex::cube_front_backward")
    def _(dirs, dx, dy, bias, bias0, S, levels, band, guv, gD, need_derivs, need_bias):
        d = need_derivs and dx.numel() > 0
        return (torch.empty_like(dirs), torch.empty_like(dirs) if d else None, torch.empty_like(dirs) if d else None,
                like(dirs, dirs.shape[0]) if need_bias and bias.numel() else None)

    @register_fake("difftex::cube_read")
    def _(levels, ring_idx, ring_w, face, uv, D, nearest, d_grad):
        return like(uv, levels[0].shape[1], uv.shape[0])

    @register_fake("difftex::cube_read_backward")
    def _(levels, ring_idx, ring_w, face, uv, D, grad, nearest, d_grad, need_levels, need_uv, need_D):
        return (level_grads(levels, uv.dtype), torch.empty_like(uv) if need_uv else None,
                torch.empty_like(D) if need_D and D.numel() else None)

    @register_fake("difftex::sat_forward")
    def _(texture, pu, cu, pv, cv, jacobians, coef_grads):
        C, M = texture.shape[0], pu.shape[0]
        out = [like(pu, C, M, dtype=torch.float64)]
        if jacobians:
            out += [like(pu, C, M, pu.shape[1], dtype=torch.float64) for _ in range(2)]
            out += [like(pu, C, M, pv.shape[1], dtype=torch.float64) for _ in range(2)]
        return out

    @register_fake("difftex::sat_backward")
    def _(texture, pu, cu, pv, cv, grad):
        return torch.empty_like(texture)

    @register_fake("difftex::ripmap_build")
    def _(texture, n_u, n_v, wanted):
        C, H, W = texture.shape
        # The wanted levels and those on their way (column 0 up to row j, then row j up to column i); level
        # (0, 0) comes back as None where it is the texture itself (contiguous).
        built = set()
        for j in range(n_v):
            for i in range(n_u):
                if wanted[j * n_u + i]:
                    built |= {(0, r) for r in range(j + 1)} | {(c, j) for c in range(i + 1)}
        return [like(texture, C, -(-H // 2 ** j), -(-W // 2 ** i))
                if (i, j) in built and not (i == j == 0 and texture.is_contiguous()) else None
                for j in range(n_v) for i in range(n_u)]

    @register_fake("difftex::ripmap_adjoint")
    def _(grads, n_u, n_v, H, W):
        first = next(g for g in grads if g.numel())
        return like(first, first.shape[0], H, W)

    @register_fake("difftex::ripmap_read")
    def _(levels, n_u, uv, Du, Dv, wrap_u, wrap_v, border, d_grad):
        C = next(t for t in levels if t.numel()).shape[0]
        return like(uv, C, uv.shape[0])

    @register_fake("difftex::ripmap_read_backward")
    def _(levels, n_u, uv, Du, Dv, grad, wrap_u, wrap_v, border, d_grad, need_levels, need_uv, need_D):
        return (level_grads(levels, uv.dtype), torch.empty_like(uv) if need_uv else None, torch.empty_like(Du) if need_D else None,
                torch.empty_like(Dv) if need_D else None)

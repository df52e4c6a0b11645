"""The single-level read that every filter calls: one autograd node over the three implementations.

``difftex.backend`` picks the implementation: the native CPU kernel
(``difftex._native``, ``csrc/single.cpp``: float32 / float64 on the
CPU, where it is built), the grid_sample path (``grid.py``: forward and
first-order backward on grid_sample) or the gather reference
(``gather.py``). Double backward always runs the reference backward, which
is itself differentiable.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ...backend import single_level
from ... import _native as native
from ..wrap import WRAP_CODES
from .gather import separable_backward, separable_forward
from .grid import FastSample, fast_forward


class SeparableSample(torch.autograd.Function):
    """Autograd wrapper: texture [Bt,C,H,W], uv [B,M,2] -> [B,C,M], Bt = B or 1."""

    @staticmethod
    def forward(ctx, texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float) -> Tensor:
        ctx.save_for_backward(texture, uv)
        ctx.args = (kind, wrap_u, wrap_v, border)
        ctx.fast = ctx.native = None
        if single_level() == "gather":
            return separable_forward(texture, uv, kind, wrap_u, wrap_v, border)
        kernel = native.kernel(uv)
        if kernel is not None:
            ctx.native = _native_args(kernel, texture, uv, kind, wrap_u, wrap_v, border)
            return kernel.sample(*ctx.native)
        # The fast path keeps what its hand-written backward needs (the
        # padded texture, the grid); no graph.
        ctx.fast = FastSample(texture, uv, kind, wrap_u, wrap_v, border, tex_grad=ctx.needs_input_grad[0])
        return ctx.fast.out

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        texture, uv = ctx.saved_tensors
        kind, wrap_u, wrap_v, border = ctx.args
        need_tex, need_uv = ctx.needs_input_grad[:2]
        if ctx.native is not None and not torch.is_grad_enabled():
            tex_c, uv_c, code, opts = ctx.native
            grad_tex, grad_uv = native.load().sample_backward(tex_c, uv_c, grad_out, code, opts,
                                                              need_texture=need_tex, need_uv=need_uv)
        elif ctx.fast is not None and not torch.is_grad_enabled():
            grad_tex, grad_uv = ctx.fast.backward(grad_out, need_tex, need_uv)
        else:  # double backward (create_graph=True) or the reference path
            grad_tex, grad_uv = separable_backward(texture, uv, grad_out, kind, wrap_u, wrap_v, border,
                                                   need_tex, need_uv)
        if need_uv and grad_uv is None:  # nearest: piecewise constant in uv
            grad_uv = torch.zeros_like(uv)
        return grad_tex, grad_uv, None, None, None, None


def _native_args(kernel, texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float) -> tuple:
    """The kernel's (texture, uv, kind, options) arguments: uv contiguous, the texture planar or channels_last.

    A channels_last texture is read in place (interleaved texels: fewer
    cache lines a read, csrc/single.cpp) and its gradient comes back
    channels_last too; any other layout is copied into planes.
    """
    if not texture.is_contiguous(memory_format=torch.channels_last):
        texture = texture.contiguous()
    key = (wrap_u, wrap_v, border, math.copysign(1.0, border))  # -0.0 == 0.0 as keys; one module a process
    opts = _OPTIONS.get(key)
    if opts is None:  # built once per mode: the binding's constructor was a tenth of a call's overhead
        if len(_OPTIONS) >= 256:  # many border values: start over rather than grow
            _OPTIONS.clear()
        opts = _OPTIONS[key] = kernel.ReadOptions(wrap_u=WRAP_CODES[wrap_u], wrap_v=WRAP_CODES[wrap_v], border=border)
    return texture, uv.contiguous(), kernel.KIND_CODES[kind], opts


_OPTIONS: dict = {}


def separable_sample(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float = 0.0) -> Tensor:
    """Sample one level: texture [Bt,C,H,W], uv [B, *S, 2] -> [B, C, *S], S any pixel shape ([M], [Ho, Wo], ...).

    Bt is B, or 1 for one texture shared by the B rows of points.

    No input checks: callers (``difftex.sample`` and the mip filters) have
    validated shapes, dtypes and modes already.
    """
    no_graph = single_level() == "grid_sample" and not (torch.is_grad_enabled() and
                                                         (texture.requires_grad or uv.requires_grad))
    kernel = native.kernel(uv) if no_graph else None
    if kernel is not None:
        # Any pixel shape in place: a reshape and a view each cost about 60 us of a cold call (after a read
        # that streamed the texture through the caches), 5% of a 512^2 bilinear forward.
        return kernel.sample(*_native_args(kernel, texture, uv, kind, wrap_u, wrap_v, float(border)))
    if uv.dim() != 3:  # the other paths read flat point lists
        B = uv.shape[0]
        out = separable_sample(texture, uv.reshape(B, -1, 2), kind, wrap_u, wrap_v, border)
        return out.view(B, out.shape[1], *uv.shape[1:-1])
    if no_graph:
        with torch.no_grad():
            return fast_forward(texture, uv, kind, wrap_u, wrap_v, float(border))
    return SeparableSample.apply(texture, uv, kind, wrap_u, wrap_v, float(border))

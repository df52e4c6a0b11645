"""Nearest, bilinear and bicubic sampling of one texture level: the gather / scatter reference.

All three are separable: along each axis a pixel reads a few texels
(1, 2 or 4) with weights that depend on the fractional texel coordinate.
One autograd Function serves all three, so gather, wrap handling, the
texture gradient (a scatter of the same weights) and the uv gradient (the
weights' derivatives) are written once.

The backward pass recomputes indices and weights from ``uv`` instead of
saving the gathered texels: it keeps memory at the size of the inputs, and
because it is written in differentiable torch ops it can itself be
differentiated (double backward), which grid_sample cannot.

Flat layout used here: texture ``[Bt, C, H, W]``, uv ``[B, M, 2]`` (one
row of M sample points per texture, or B rows sharing one texture when
Bt = 1), output ``[B, C, M]``; ``difftex.sample`` does the reshaping and
broadcasting around it.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..wrap import floor_index, wrap_index

# grid_sample's bicubic uses the Keys cubic convolution with a = -0.75.
_CUBIC_A = -0.75


def _cubic_near(t: Tensor) -> tuple[Tensor, Tensor]:
    """Keys kernel and its derivative for |t| <= 1."""
    a = _CUBIC_A
    return ((a + 2) * t - (a + 3)) * t * t + 1, (3 * (a + 2) * t - 2 * (a + 3)) * t


def _cubic_far(t: Tensor) -> tuple[Tensor, Tensor]:
    """Keys kernel and its derivative for 1 < |t| < 2."""
    a = _CUBIC_A
    return ((a * t - 5 * a) * t + 8 * a) * t - 4 * a, (3 * a * t - 10 * a) * t + 8 * a


# Period in uv of the wraps that repeat (mirror repeats after a flip and back).
_PERIOD = {"repeat": 1.0, "mirror": 2.0}
# Past this distance in uv from [0, 1] every tap of every filter is off the
# texture for any size n >= 1 (x = u * n - 0.5 <= -8.5, bicubic reaches 2
# texels): clamp and border read the same there at any distance.
_FAR = 8.0


def reduce_coordinate(u: Tensor, mode: str) -> Tensor:
    """u moved to a coordinate that reads the same texels under ``mode``, with ``|u| <= 9``.

    ``u * n`` must stay finite and keep its fraction: a finite uv of 1e38 in
    float32 times 8 texels is inf, and inf - floor(inf) is NaN. Repeat and
    mirror drop whole periods (exact in floating point for ``|u| >=`` one
    period; smaller values are left untouched, so ordinary coordinates read
    bit for bit as before); clamp and border stop at ``_FAR`` past the
    edge, where every tap is off the texture already. NaN and inf stay
    non-finite (the pixel shows them). Gradient 1 (0 where clamped: the
    read is constant there).
    """
    p = _PERIOD.get(mode)
    if p is not None:
        return torch.where(u.abs() >= p, u - p * torch.floor(u.detach() / p), u)
    # 0 * u keeps inf non-finite (NaN) instead of clamping it to a finite read.
    return u.clamp(-_FAR, 1 + _FAR) + 0 * u


def reduce_uv(uv: Tensor, wrap_u: str, wrap_v: str) -> Tensor:
    """``reduce_coordinate`` on the last axis of uv [..., 2], per axis mode."""
    if wrap_u == wrap_v:
        return reduce_coordinate(uv, wrap_u)
    return torch.stack((reduce_coordinate(uv[..., 0], wrap_u), reduce_coordinate(uv[..., 1], wrap_v)), -1)


# Tap offsets from floor(x) (round(x) for nearest) along one axis.
_OFFSETS = {"nearest": (0,), "linear": (0, 1), "cubic": (-1, 0, 1, 2)}

# Bound on gathered texels held at once (K taps x C channels x points):
# 2**24 floats is 64 MiB in float32.
_CHUNK_ELEMENTS = 1 << 24


def _axis_weights(t: Tensor, kind: str, derivs: bool) -> tuple[Tensor, Tensor | None]:
    """Per-tap weights (and d/dx) from the fractional coordinate t [..., M] -> [..., K, M]."""
    if kind == "nearest":
        # 1 where x is finite, NaN where it is not: a bad uv shows in its pixel.
        return (1 + 0 * t).unsqueeze(-2), None
    if kind == "linear":
        w = torch.stack((1 - t, t), -2)
        d = torch.stack((-torch.ones_like(t), torch.ones_like(t)), -2) if derivs else None
        return w, d
    w0, d0 = _cubic_far(t + 1)
    w1, d1 = _cubic_near(t)
    w2, d2 = _cubic_near(1 - t)
    w3, d3 = _cubic_far(2 - t)
    w = torch.stack((w0, w1, w2, w3), -2)
    d = torch.stack((d0, d1, -d2, -d3), -2) if derivs else None
    return w, d


class _Taps:
    """Texel indices and separable weights of every tap of a chunk of points.

    Shapes, for Bt textures, M points and K taps per axis:
    ``idx`` [Bt, K*K*M] flat texel indices (y tap major, then x tap, then
    point), ``valid`` [Bt, K, K, M] or None, ``wx``/``wy`` [Bt, K, M], and with
    ``derivs`` ``dwx``/``dwy`` [Bt, K, M] = d(weight)/d(texel coordinate).
    """

    def __init__(self, texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, derivs: bool = False):
        H, W = texture.shape[-2:]
        # [Bt, 2, M] keeps the points contiguous, the layout of the gathers.
        xy = (reduce_uv(uv, wrap_u, wrap_v) * uv.new_tensor([W, H]) - 0.5).transpose(1, 2).contiguous()
        base = torch.round(xy) if kind == "nearest" else torch.floor(xy)
        w, d = _axis_weights(xy - base, kind, derivs)
        offs = torch.tensor(_OFFSETS[kind], device=uv.device).view(-1, 1)
        taps = floor_index(base).unsqueeze(2) + offs  # [Bt, 2, K, M]
        ix, vx = wrap_index(taps[:, 0], W, wrap_u)
        iy, vy = wrap_index(taps[:, 1], H, wrap_v)
        K = offs.shape[0]
        self.K = K
        self.idx = (iy.unsqueeze(2) * W + ix.unsqueeze(1)).reshape(iy.shape[0], -1)
        if vx is None and vy is None:
            self.valid = None
        else:
            vx = torch.ones_like(ix, dtype=torch.bool) if vx is None else vx
            vy = torch.ones_like(iy, dtype=torch.bool) if vy is None else vy
            self.valid = vy.unsqueeze(2) & vx.unsqueeze(1)
        self.wx, self.wy = w[:, 0], w[:, 1]
        self.dwx, self.dwy = (d[:, 0], d[:, 1]) if d is not None else (None, None)

    def read(self, flat: Tensor, border: float) -> Tensor:
        """Gathered texels [Bt, C, K, K, M]; border taps read the constant."""
        Bt, C = flat.shape[:2]
        vals = torch.gather(flat, 2, self.idx.unsqueeze(1).expand(-1, C, -1)).view(Bt, C, self.K, self.K, -1)
        if self.valid is not None:
            vals = torch.where(self.valid.unsqueeze(1), vals, vals.new_tensor(border))
        return vals


def _chunks(M: int, per_point: int):
    step = max(1, _CHUNK_ELEMENTS // max(per_point, 1))
    return [(s, min(s + step, M)) for s in range(0, M, step)]


def _contract(vals: Tensor, wx: Tensor, wy: Tensor) -> Tensor:
    """sum_{a,b} wy[a] wx[b] vals[..., a, b, m]: [Bt,C,K,K,M] -> [Bt,C,M]."""
    rows = (vals * wx.unsqueeze(1).unsqueeze(2)).sum(3)
    return (rows * wy.unsqueeze(1)).sum(2)


def _one_row(texture: Tensor, uv: Tensor) -> Tensor:
    """One texture for several rows of points: gather from it as one long row."""
    return uv.reshape(1, -1, 2) if texture.shape[0] == 1 and uv.shape[0] > 1 else uv


def separable_forward(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """Filtered values, flat layout (see module docstring)."""
    Bt, C, H, W = texture.shape
    B = uv.shape[0]
    uv = _one_row(texture, uv)
    flat = texture.reshape(Bt, C, H * W)
    M, K = uv.shape[1], len(_OFFSETS[kind])
    parts = []
    for a, b in _chunks(M, C * K * K):
        taps = _Taps(texture, uv[:, a:b], kind, wrap_u, wrap_v)
        parts.append(_contract(taps.read(flat, border), taps.wx, taps.wy))
    out = parts[0] if len(parts) == 1 else torch.cat(parts, -1)
    return out.view(C, B, -1).transpose(0, 1).contiguous() if B != Bt else out  # DESIGN.md: contiguous


def separable_backward(texture: Tensor, uv: Tensor, grad_out: Tensor, kind: str, wrap_u: str, wrap_v: str,
                       border: float, need_tex: bool, need_uv: bool,
                       into: Tensor | None = None) -> tuple[Tensor | None, Tensor | None]:
    """Gradients w.r.t. texture and uv, in differentiable ops (double backward).

    ``into``: optional texture-shaped buffer that the texture gradient is
    added to in place (and returned), instead of a new one; first order only.
    """
    Bt, C, H, W = texture.shape
    B = uv.shape[0]
    uv = _one_row(texture, uv)
    # A point whose uv is NaN / inf passes nothing back: no texture gradient (its NaN weights must not reach
    # the texels it happens to index) and no uv gradient (as the native and grid_sample backends; its NaN
    # would reach whatever the uv came from). The uv is replaced before use, so that the double backward
    # sends no NaN either.
    finite = torch.isfinite(uv).all(-1, keepdim=True)
    uv = torch.where(finite, uv, 0.0)
    if B != Bt:
        grad_out = grad_out.transpose(0, 1).reshape(1, C, -1)
    flat = texture.reshape(Bt, C, H * W)
    grad_out = grad_out.contiguous()
    need_uv = need_uv and kind != "nearest"
    M, K = uv.shape[1], len(_OFFSETS[kind])
    grad_flat = None
    if need_tex:
        grad_flat = torch.zeros_like(flat) if into is None else into.view(Bt, C, H * W)
    grad_uv = []
    for a, b in _chunks(M, C * K * K):
        taps = _Taps(texture, uv[:, a:b], kind, wrap_u, wrap_v, derivs=need_uv)
        g = grad_out[:, :, a:b]
        if need_tex:
            w = taps.wy.unsqueeze(2) * taps.wx.unsqueeze(1)  # [Bt, K, K, m]
            keep = finite[:, a:b].view(Bt, 1, 1, -1)
            if taps.valid is not None:
                keep = keep & taps.valid
            w = torch.where(keep, w, 0.0)
            src = (g.view(Bt, C, 1, 1, -1) * w.unsqueeze(1)).reshape(Bt, C, -1)
            index = taps.idx.unsqueeze(1).expand(-1, C, -1)
            grad_flat = grad_flat.scatter_add(2, index, src) if into is None else grad_flat.scatter_add_(2, index, src)
        if need_uv:
            gv = (g.view(Bt, C, 1, 1, -1) * taps.read(flat, border)).sum(1)  # [Bt, K, K, m]
            gx = _contract(gv.unsqueeze(1), taps.dwx, taps.wy)[:, 0] * W
            gy = _contract(gv.unsqueeze(1), taps.wx, taps.dwy)[:, 0] * H
            grad_uv.append(torch.where(finite[:, a:b], torch.stack((gx, gy), -1), 0.0))
    grad_tex = grad_flat.view(Bt, C, H, W) if need_tex else None
    if not need_uv:
        return grad_tex, None
    grad_uv = grad_uv[0] if len(grad_uv) == 1 else torch.cat(grad_uv, 1)
    return grad_tex, grad_uv.view(B, -1, 2)

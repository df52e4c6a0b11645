"""Bump and normal mapping: per-pixel normals perturbed by a height map's slope or read from a normal map.

Both work in the tangent space of :mod:`.frames` (rows T, B, N of a
[B, Ho, Wo, 3, 3] frame, T along +u, B along +v) and read their texture
with :func:`difftex.sample`, so every filter and wrap mode of ``sample``
applies. The bump slope is the derivative of the *filtered* height (the
bilinear / bicubic / trilinear ... interpolant), taken by differentiating
``sample`` with respect to uv: it is the exact slope of the surface the
filter reconstructs, and it is itself differentiable (``sample``'s backward
is twice differentiable), so a fit can learn the height map through it.
"""
from __future__ import annotations

from typing import Optional, Union

import torch
from torch import Tensor

from .._checks import broadcast_batch, check_float, check_same, describe
from ..texture.options import check_filter
from ..texture.pyramid.mipmap import Mipmap
from ..texture.sample import sample
from ..texture.wrap import Wrap
from .common import broadcast, operand, unit

SLOPE_METHODS = ("analytic", "difference")
GREEN = ("down", "up")


def _base(texture: Union[Tensor, Mipmap], name: str, channels: int) -> Tensor:
    base = texture.levels[0] if isinstance(texture, Mipmap) else texture
    check_float(name, base, 4, shape_doc=f"[B, {channels}, H, W]")
    if base.shape[1] != channels:
        raise ValueError(f"{name}: expected {channels} channel{'s' if channels > 1 else ''} [B, {channels}, H, W], "
                         f"got {describe(base)}")
    return base


def _check_frames(frames: object, uv: Tensor, base: Tensor) -> Tensor:
    check_float("frames", frames, 5, shape_doc="[B, Ho, Wo, 3, 3]")
    check_same("frames", frames, "uv", uv)  # type: ignore[arg-type]
    _, Ho, Wo, _ = uv.shape
    if tuple(frames.shape[1:]) != (Ho, Wo, 3, 3):  # type: ignore[union-attr]
        raise ValueError(f"frames: expected [B, Ho, Wo, 3, 3] = [B, {Ho}, {Wo}, 3, 3] (rows T, B, N per pixel of uv), "
                         f"got {describe(frames)}")  # type: ignore[arg-type]
    return frames  # type: ignore[return-value]


def height_slope(
    height: Union[Tensor, Mipmap],
    uv: Tensor,
    *,
    method: str = "analytic",
    filter: str = "bilinear",
    wrap: Wrap = "repeat",
    border_value: float = 0.0,
    uv_dx: Optional[Tensor] = None,
    uv_dy: Optional[Tensor] = None,
    lod_bias: Union[float, Tensor] = 0.0,
    max_aniso: float = 16,
) -> Tensor:
    """The slope (dh/du, dh/dv) of the filtered height map at uv, in height units per uv unit.

    Args:
        height: [B, 1, H, W] height map (or a one-channel Mipmap).
        uv, uv_dx, uv_dy, filter, wrap, border_value, lod_bias, max_aniso:
            as :func:`difftex.sample` (the mip filters need uv_dx / uv_dy).
        method: "analytic": the derivative of the filter's interpolant
            (``sample`` differentiated with respect to uv; for "bilinear"
            dh/du is constant in u between texel centres, where it jumps,
            and linear in v (likewise dh/dv); "bicubic"
            is continuous but, with grid_sample's Keys a = -0.75, does
            not reproduce a linear ramp: its slope on a ramp of slope s
            runs from 0.75 s to 1.49 s within each texel; the mip
            filters differentiate each level's
            bilinear taps at the level their footprint chooses);
            "difference": the seed notes' forward difference
            ``(h(u + 1/W) - h(u)) * W`` (one level-0 texel; likewise in v).

    Returns:
        [B, Ho, Wo, 2]: dh/du, dh/dv (uv units: a ramp rising by s across
        the whole texture has slope s).

    Differentiable with respect to the height map and uv (and, for the mip
    filters, uv_dx / uv_dy); under ``torch.no_grad`` nothing is recorded.
    Raises ValueError for "nearest" with "analytic" (its slope is zero
    almost everywhere), an unknown method, a height map that is not one
    channel, and everything ``sample`` rejects.
    """
    if not isinstance(method, str) or method not in SLOPE_METHODS:
        raise ValueError(f"method: unknown slope method {method!r}; expected one of {SLOPE_METHODS}")
    check_filter(filter)
    base = _base(height, "height", 1)
    check_float("uv", uv, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    kw = dict(filter=filter, wrap=wrap, border_value=border_value, lod_bias=lod_bias, max_aniso=max_aniso)
    if method == "difference":
        H, W = base.shape[-2:]
        step = torch.tensor([[1.0 / W, 0.0], [0.0, 1.0 / H]], dtype=uv.dtype, device=uv.device)
        pts = torch.cat([uv, uv + step[0], uv + step[1]], dim=2)
        rep = lambda t: None if t is None else torch.cat([t] * 3, dim=2)
        bias = rep(lod_bias) if isinstance(lod_bias, Tensor) and lod_bias.dim() == 3 else lod_bias
        h = sample(height, pts, uv_dx=rep(uv_dx), uv_dy=rep(uv_dy), **{**kw, "lod_bias": bias})[:, 0]
        h0, hu, hv = h.chunk(3, dim=2)
        return torch.stack([(hu - h0) * W, (hv - h0) * H], dim=-1)
    if filter == "nearest":
        raise ValueError("filter: 'nearest' has a zero slope almost everywhere; expected a filter with a "
                         "differentiable interpolant (bilinear, bicubic, a mip filter) or method='difference'")
    B = broadcast_batch(["height", "uv"], [base.shape[0], uv.shape[0]])
    record = torch.is_grad_enabled()
    with torch.enable_grad():
        pts = uv.expand(B, -1, -1, -1)
        if not pts.requires_grad:
            pts = pts.detach().requires_grad_(True)
        h = sample(height, pts, uv_dx=uv_dx, uv_dy=uv_dy, **kw)
        # Each output pixel reads only its own uv, so the gradient of the sum is the per-pixel slope.
        (slope,) = torch.autograd.grad(h, pts, torch.ones_like(h), create_graph=record)
    return slope if record else slope.detach()


def bump(
    height: Union[Tensor, Mipmap],
    uv: Tensor,
    frames: Tensor,
    scale: Union[float, Tensor] = 1.0,
    *,
    method: str = "analytic",
    filter: str = "bilinear",
    wrap: Wrap = "repeat",
    border_value: float = 0.0,
    uv_dx: Optional[Tensor] = None,
    uv_dy: Optional[Tensor] = None,
    lod_bias: Union[float, Tensor] = 0.0,
    max_aniso: float = 16,
) -> Tensor:
    """Bump mapping: normals perturbed by the slope of a height map.

    In tangent space the perturbed normal is
    ``normalize(-scale * dh/du, -scale * dh/dv, 1)`` (the seed notes' form,
    Blinn 1978 for a unit-speed parameterisation), returned in world space
    ``normalize(N - scale * (dh/du T + dh/dv B))``. A linear ramp
    ``h = s * u`` tilts the normal by ``atan(s * scale)`` towards -T
    (downhill); a constant height leaves N unchanged.

    Args:
        height: [B, 1, H, W] height map (or a Mipmap of one).
        uv: [B, Ho, Wo, 2] texture coordinates per pixel.
        frames: [B, Ho, Wo, 3, 3] per-pixel orthonormal frames, rows T, B, N
            (:meth:`TangentFrames.at` or :func:`surface_frames`).
        scale: bump height scale, a number or a tensor broadcasting to
            [B, Ho, Wo] (learnable). The slope is in uv units, so the
            apparent depth does not depend on the texture's resolution; the
            seed notes' per-texel constant c is ``scale / W``.
        method: "analytic" (derivative of the filtered interpolant) or
            "difference" (the seed's one-texel forward difference); see
            :func:`height_slope`.
        filter, wrap, border_value, uv_dx, uv_dy, lod_bias, max_aniso: as
            :func:`difftex.sample`.

    Returns:
        [B, Ho, Wo, 3] unit world-space normals (zero where the frame's N is zero).

    Differentiable with respect to the height map, scale, frames and uv.
    Raises ValueError / TypeError naming the argument for a height map
    that is not one channel, frames of another shape, a non-float or
    mismatched scale, and what :func:`height_slope` rejects.
    """
    base = _base(height, "height", 1)
    check_float("uv", uv, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_same("uv", uv, "height", base)
    _check_frames(frames, uv, base)
    s = operand("scale", scale, uv, "broadcasting to [B, Ho, Wo]", "uv")
    if s.dim() > 0:
        if s.dim() > 3:
            raise ValueError(f"scale: expected a number or a tensor broadcasting to [B, Ho, Wo], got {describe(s)}")
        broadcast({"scale": s.shape, "uv's [B, Ho, Wo]": uv.shape[:3]})
        s = s.unsqueeze(-1)
    slope = height_slope(height, uv, method=method, filter=filter, wrap=wrap, border_value=border_value,
                         uv_dx=uv_dx, uv_dy=uv_dy, lod_bias=lod_bias, max_aniso=max_aniso)
    broadcast_batch(["slope", "frames"], [slope.shape[0], frames.shape[0]])
    t, b, n = frames.unbind(-2)
    return unit(n - s * (slope[..., :1] * t + slope[..., 1:] * b))


def normal_map(
    texture: Union[Tensor, Mipmap],
    uv: Tensor,
    frames: Tensor,
    *,
    green: str = "down",
    filter: str = "bilinear",
    wrap: Wrap = "repeat",
    border_value: float = 0.0,
    uv_dx: Optional[Tensor] = None,
    uv_dy: Optional[Tensor] = None,
    lod_bias: Union[float, Tensor] = 0.0,
    max_aniso: float = 16,
) -> Tensor:
    """Tangent-space normal mapping: normals decoded from a sampled normal map.

    The filtered texel c (three channels in [0, 1]) decodes to the
    tangent-space normal ``normalize(2 c - 1)`` = (x, y, z) and the result
    is ``normalize(x T + y B + z N)``. The flat colour (0.5, 0.5, 1) is the
    identity (returns N). Filtering happens on the encoded colours (as a GPU
    does) and the decoded vector is renormalised.

    Args:
        texture: [B, 3, H, W] normal map (or a Mipmap of one).
        uv: [B, Ho, Wo, 2]; frames: [B, Ho, Wo, 3, 3] rows T, B, N.
        green: "down": the green channel points along +v, down the texture
            rows (DESIGN.md's v; DirectX-style maps); "up": along -v
            (OpenGL-style maps, e.g. Blender's), so y is negated.
        filter, wrap, border_value, uv_dx, uv_dy, lod_bias, max_aniso: as
            :func:`difftex.sample`.

    Returns:
        [B, Ho, Wo, 3] unit world-space normals (zero where the decoded
        vector is zero).

    Differentiable with respect to the texture, uv and frames. Raises
    ValueError for a texture that is not 3 channels, frames of another
    shape, an unknown ``green``, and what :func:`difftex.sample` rejects.
    """
    if not isinstance(green, str) or green not in GREEN:
        raise ValueError(f"green: expected one of {GREEN}, got {green!r}")
    base = _base(texture, "texture", 3)
    check_float("uv", uv, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_same("uv", uv, "texture", base)
    _check_frames(frames, uv, base)
    c = sample(texture, uv, filter=filter, wrap=wrap, border_value=border_value, uv_dx=uv_dx, uv_dy=uv_dy,
               lod_bias=lod_bias, max_aniso=max_aniso).movedim(1, -1)
    local = unit(2 * c - 1)
    if green == "up":
        local = local * local.new_tensor([1.0, -1.0, 1.0])
    broadcast_batch(["texture", "frames"], [local.shape[0], frames.shape[0]])
    return unit((local.unsqueeze(-1) * frames).sum(-2))


__all__ = ["bump", "normal_map", "height_slope", "SLOPE_METHODS"]

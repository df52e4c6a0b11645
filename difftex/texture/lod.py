"""The level-of-detail formula and the pixel footprint, written once for every mip filter.

A pixel's footprint in the texture is the image of the unit pixel under the
Jacobian ``J = [uv_dx * (W, H), uv_dy * (W, H)]`` (columns: texels per pixel
column / row of level 0). The filters read it four ways:

* trilinear: ``L = max(|J e_x|, |J e_y|)`` (the seed formula);
* anisotropic: the major axis of the ellipse ``J J^T`` and the number of taps
  along it;
* EWA: the ellipse itself, its minor axis choosing the level.
* ripmap and summed-area table: the axis-aligned bounding box (``log2_extents``), one level per axis.

and all turn a length into a level with the same ``level()``:
``D = clamp(log2(length) + lod_bias, 0, levels - 1)``.

Degenerate footprints never produce NaN, in value or gradient: a zero or
NaN Jacobian is a zero footprint (level 0), an infinite one an infinite
footprint (the coarsest level); both pass zero gradient. Lengths are
computed from ``J / s`` with ``s = max |J_ij|`` (a detached constant per
pixel; the lengths are homogeneous of degree 1, so the gradient is still
exact) so that squaring cannot overflow or underflow.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
from torch import Tensor

from .._checks import broadcast_batch, check_float, check_same
from .pyramid.mipmap import Mipmap, level_count

# Stands for log2 of a zero / infinite length: far outside any level range,
# yet finite so that sums with lod_bias stay finite and clamp cleanly.
FAR = 1.0e4


class Footprint(NamedTuple):
    """Per-pixel footprint; every field has the pixel shape ``[...]`` unless noted.

    p, q: [..., 2] footprint vectors (texels of level 0 per pixel column /
        row) divided by ``scale``; zero where the footprint is degenerate.
    log2_scale: log2 of ``scale`` (detached), 0 where degenerate.
    zero: bool, footprint treated as a point (zero or NaN derivatives).
    inf: bool, footprint treated as infinite (an infinite derivative).
    """

    p: Tensor
    q: Tensor
    log2_scale: Tensor
    zero: Tensor
    inf: Tensor


def footprint(uv_dx: Tensor, uv_dy: Tensor, height: int, width: int) -> Footprint:
    """Scaled, sanitized footprint vectors of level 0 (see ``Footprint``)."""
    # Component-major [4, ...]: the per-pixel math here and in ``ellipse``
    # runs on contiguous rows, several times faster on CPU than on a
    # trailing axis of 4 (measured: amax 8x, a broadcast divide 6x).
    J = torch.stack((uv_dx[..., 0] * width, uv_dx[..., 1] * height, uv_dy[..., 0] * width, uv_dy[..., 1] * height))
    with torch.no_grad():
        top = J.abs().amax(0)  # NaN wins over inf here
        nan = torch.isnan(top)
        inf = torch.isinf(top)
        finite = ~(nan | inf)
        s = torch.nan_to_num(top, nan=0.0, posinf=0.0)
        zero = s == 0
        s = s + zero.to(s.dtype)
    # A non-finite pixel becomes the zero footprint: nan_to_num zeroes its
    # non-finite entries (and their gradient), the mask its finite ones.
    # Products with masks rather than torch.where: 8x faster on CPU.
    Js = torch.nan_to_num(J, nan=0.0, posinf=0.0, neginf=0.0) * finite.to(J.dtype) / s
    zero = zero & finite | nan
    return Footprint(Js[0:2].movedim(0, -1), Js[2:4].movedim(0, -1), torch.log2(s), zero, inf)


def _mask(m: Tensor, like: Tensor) -> Tensor:
    return m.to(like.dtype)


def _log2_len2(len2: Tensor, fp: Footprint) -> Tensor:
    """log2 of a length given its scaled square ``len2``, with the degenerate cases."""
    ok = _mask(~(fp.zero | fp.inf) & (len2 > 0), len2)
    # log2 is only ever evaluated at positive arguments (1 where masked), so
    # the masked-out pixels get an exact zero gradient instead of 0 * inf.
    v = 0.5 * torch.log2(len2 * ok + (1 - ok)) + fp.log2_scale
    far = (2 * _mask(fp.inf, len2) - 1) * FAR
    return v * ok + far * (1 - ok)


def log2_length(uv_dx: Tensor, uv_dy: Tensor, height: int, width: int) -> Tensor:
    """``log2 L``, ``L = max(|uv_dx * (W, H)|, |uv_dy * (W, H)|)`` in texels: the seed's trilinear length.

    Squares are taken unscaled (the cheap path trilinear needs): a length
    whose square overflows is beyond any pyramid (coarsest level) and one
    whose square underflows (< 1e-19 texels in float32) is below level 0
    unless lod_bias > 60, so the clamped level is the same as with
    ``footprint``'s scaling. NaN gives level 0 (``-FAR``), inf the top.
    """
    size2 = uv_dx.new_tensor([float(width) ** 2, float(height) ** 2])

    def len2_of(a: Tensor, b: Tensor) -> Tensor:
        # A matmul against (W^2, H^2) is ~8x faster than .sum(-1) over a
        # size-2 axis on CPU (measured); NaN and inf propagate the same.
        return torch.maximum((a * a) @ size2, (b * b) @ size2)

    with torch.no_grad():
        raw = len2_of(uv_dx, uv_dy)  # NaN wins over inf (maximum propagates NaN)
        ok = ((raw > 0) & (raw < float("inf"))).to(raw.dtype)
        # -FAR for NaN or zero, +FAR for infinite (or overflowing) lengths.
        far = (raw.nan_to_num(0.0) > 0).to(raw.dtype) * (2 * FAR) - FAR
    if torch.is_grad_enabled() and (uv_dx.requires_grad or uv_dy.requires_grad):
        # Inputs of the masked pixels are zeroed before squaring so that their
        # gradient is an exact 0 rather than 0 * inf; nan_to_num turns the
        # inf * 0 of the mask into 0 and passes no gradient there.
        m = ok.unsqueeze(-1)
        len2 = len2_of(torch.nan_to_num(uv_dx * m), torch.nan_to_num(uv_dy * m))
    else:
        len2 = raw
    # Arithmetic blends instead of torch.where (several times slower here);
    # safe because every term is finite: log2 sees 1 where masked.
    v = 0.5 * torch.log2(torch.nan_to_num(len2 * ok, posinf=1.0) + (1 - ok))
    return v * ok + far * (1 - ok)


def _safe_sqrt(x: Tensor) -> Tensor:
    """sqrt of a finite x, 0 (with zero gradient) where x <= 0."""
    pos = _mask(x > 0, x)
    return torch.sqrt(x * pos + (1 - pos)) * pos


class Ellipse(NamedTuple):
    """Axes of the footprint ellipse (the image of the unit pixel, J J^T), level-0 texels.

    major, minor: [...] the singular values of J (the lengths that the seed's
        L measures: one pixel step, i.e. the ellipse's full diameters over
        the unit-diameter pixel), divided by the footprint scale (times
        ``2 ** log2_scale`` they are texels). ``major >= minor >= 0``.
    log2_major, log2_minor: [...] log2 of the unscaled lengths, with the
        degenerate cases of ``Footprint``.
    direction: [..., 2] unit vector of the major axis in texel space; (1, 0)
        where the footprint is a circle (any direction would do).
    jjt: [..., 3] the scaled ``J J^T`` as (xx, xy, yy).
    """

    major: Tensor
    minor: Tensor
    log2_major: Tensor
    log2_minor: Tensor
    direction: Tensor
    jjt: Tensor


def ellipse(fp: Footprint) -> Ellipse:
    """Closed-form singular values and major direction of the 2 x 2 footprint Jacobian."""
    # Contiguous components from footprint's component-major layout; every
    # value here is finite (footprint sanitizes), so masks are products.
    p0, p1, q0, q1 = fp.p[..., 0], fp.p[..., 1], fp.q[..., 0], fp.q[..., 1]
    a = p0 * p0 + q0 * q0
    c = p1 * p1 + q1 * q1
    b = p0 * p1 + q0 * q1
    half_diff = 0.5 * (a - c)
    disc = _safe_sqrt(half_diff * half_diff + b * b)
    lam_max = 0.5 * (a + c) + disc
    major = _safe_sqrt(lam_max)
    # minor = |det J| / major: the difference lam_min = (a + c) / 2 - disc
    # cancels catastrophically for thin ellipses, the product does not.
    det = (p0 * q1 - q0 * p1).abs()
    major_ok = _mask(major > 0, major)
    minor = torch.minimum(det / (major + (1 - major_ok)) * major_ok, major)
    # Direction of the major axis: angle 0.5 * atan2(2b, a - c), undefined
    # for a circle; there every filter is direction-free, so pick (1, 0).
    eps = torch.finfo(a.dtype).eps
    aniso = _mask(disc > eps * (a + c), a)
    theta = 0.5 * torch.atan2(2 * b * aniso, 2 * half_diff * aniso + (1 - aniso))
    direction = torch.stack((torch.cos(theta), torch.sin(theta)), -1)
    return Ellipse(major, minor, _log2_len2(major * major, fp), _log2_len2(minor * minor, fp), direction,
                   torch.stack((a, b, c), -1))


def log2_extents(fp: Footprint) -> Tensor:
    """log2 of the footprint's axis-aligned bounding box: [..., 2], width along u and height along v, level-0 texels.

    The box of the parallelogram ``J [-1/2, 1/2]^2`` (the filters' pixel
    footprint) is ``|J_u0| + |J_u1|`` texels wide along u, likewise along v;
    the ripmap and summed-area filters read it (axis-aligned extents). A
    zero side (a footprint flat along that axis) and a zero / NaN footprint
    give ``-FAR`` (level 0), an infinite one ``+FAR``, with zero gradient.
    """
    ext = fp.p.abs() + fp.q.abs()  # scaled by the footprint's s: every entry <= 2
    return torch.stack((_log2_len2(ext[..., 0] * ext[..., 0], fp), _log2_len2(ext[..., 1] * ext[..., 1], fp)), -1)


def level(log2_len: Tensor, lod_bias: Tensor | float, levels: int) -> Tensor:
    """The level-of-detail formula: ``D = clamp(log2_len + lod_bias, 0, levels - 1)``.

    The gradient with respect to ``log2_len`` and ``lod_bias`` is the
    derivative from below: 1 where ``0 < log2_len + lod_bias <= levels - 1``,
    0 elsewhere, so at an exact ``D = 0`` it is 0 (clamped below) and at an
    exact top level 1 (DESIGN.md, "mip level"). A NaN sum (a NaN bias) gives
    level 0 and zero gradient.
    """
    # nan_to_num: NaN -> 0 with zero gradient (+-inf clamp to the ends).
    x = torch.nan_to_num(log2_len + lod_bias, nan=0.0)
    top = float(levels - 1)
    d = x.clamp(0.0, top)
    if not d.requires_grad:
        return d
    # torch.clamp passes the gradient at both ends; the derivative from below passes it at the top only.
    # Products rather than torch.where (several times faster on CPU); d is finite.
    inside = ((x > 0.0) & (x <= top)).to(d.dtype)
    return d * inside + d.detach() * (1 - inside)


def size_and_levels(texture_size: object) -> tuple[int, int, int | None]:
    if isinstance(texture_size, Mipmap):
        H, W = texture_size.shape[-2:]
        return H, W, len(texture_size)
    if isinstance(texture_size, Tensor):
        if texture_size.dim() < 2:
            raise ValueError(f"texture_size: expected a texture [..., H, W] or (H, W), got a tensor of shape "
                             f"{tuple(texture_size.shape)}")
        H, W = texture_size.shape[-2:]
        return int(H), int(W), None
    if isinstance(texture_size, (tuple, list)) and len(texture_size) == 2 and all(
            isinstance(v, int) and not isinstance(v, bool) for v in texture_size):
        H, W = texture_size
        if H >= 1 and W >= 1:
            return H, W, None
    raise ValueError(f"texture_size: expected (H, W) ints >= 1, a texture tensor [..., H, W] or a Mipmap, "
                     f"got {texture_size!r}")


def lod(uv_dx: Tensor, uv_dy: Tensor, texture_size: Sequence[int] | Tensor | object, *,
        lod_bias: Tensor | float = 0.0, levels: int | None = None) -> Tensor:
    """The per-pixel mip level that ``filter="trilinear"`` uses.

    Args:
        uv_dx, uv_dy: [B, Ho, Wo, 2] uv per pixel column / row (DESIGN.md).
        texture_size: (H, W) of level 0, or the texture [..., H, W], or a Mipmap.
        lod_bias: added to the level before clamping; scalar or [B, Ho, Wo].
        levels: number of levels to clamp to; default the Mipmap's count,
            else the full chain ``1 + ceil(log2(max(H, W)))``.

    Returns:
        [B, Ho, Wo] ``D = clamp(log2 L + lod_bias, 0, levels - 1)``,
        ``L = max(|uv_dx * (W, H)|, |uv_dy * (W, H)|)`` in texels.

    Differentiable in uv_dx, uv_dy and lod_bias (zero gradient where
    clamped); zero / NaN derivatives give level 0 and infinite ones the last
    level, with zero gradient. Raises ValueError / TypeError naming the
    argument on bad shapes or dtypes.
    """
    check_float("uv_dx", uv_dx, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_float("uv_dy", uv_dy, 4, last=2, shape_doc="[B, Ho, Wo, 2]")
    check_same("uv_dy", uv_dy, "uv_dx", uv_dx)
    if uv_dx.shape != uv_dy.shape:
        raise ValueError(f"uv_dy: expected the shape of uv_dx {tuple(uv_dx.shape)}, got {tuple(uv_dy.shape)}")
    H, W, n = size_and_levels(texture_size)
    if levels is not None:
        if isinstance(levels, bool) or not isinstance(levels, int) or levels < 1:
            raise ValueError(f"levels: expected an int >= 1, got {levels!r}")
        n = levels
    if n is None:
        n = level_count(H, W)
    check_lod_bias(lod_bias, uv_dx)
    return level(log2_length(uv_dx, uv_dy, H, W), lod_bias, n)


def check_lod_bias(lod_bias: object, uv_dx: Tensor) -> None:
    """A number, a 0-d tensor or [B, Ho, Wo] like ``uv_dx`` (either B may be 1); ValueError / TypeError otherwise."""
    if isinstance(lod_bias, Tensor):
        check_float("lod_bias", lod_bias, (0, 3), shape_doc="scalar or [B, Ho, Wo]")
        check_same("lod_bias", lod_bias, "uv_dx", uv_dx)
        if lod_bias.dim() == 3:
            if lod_bias.shape[1:] != uv_dx.shape[1:3]:
                raise ValueError(f"lod_bias: expected a scalar or [B, Ho, Wo] like uv_dx "
                                 f"{tuple(uv_dx.shape[:3])}, got {tuple(lod_bias.shape)}")
            broadcast_batch(["uv_dx", "lod_bias"], [uv_dx.shape[0], lod_bias.shape[0]])
    elif isinstance(lod_bias, bool) or not isinstance(lod_bias, (int, float)):
        raise TypeError(f"lod_bias: expected a number or a float tensor [B, Ho, Wo], got {type(lod_bias).__name__}")

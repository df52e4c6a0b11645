"""The texture matrix: an affine or projective map of uv (with its derivatives), and a builder for it."""
from __future__ import annotations

import math
from typing import Optional, Union

import torch

from .common import TensorLike, UVResult, as_float, broadcast, check_derivs, check_tensor, result


def texture_matrix(uv: torch.Tensor, matrix: torch.Tensor, *,
                   uv_dx: Optional[torch.Tensor] = None,
                   uv_dy: Optional[torch.Tensor] = None) -> UVResult:
    """Apply a 3 x 3 homogeneous texture matrix to uv (OpenGL's texture matrix).

    ``[x, y, w] = matrix @ [u, v, 1]``, result ``(x / w, y / w)``; for an
    affine matrix (last row 0, 0, 1) that is just ``A uv + t``.  Like
    OpenGL's texture matrix it moves the coordinates, so the texture appears
    moved by the inverse (a uv shift of +0.1 slides the image by -0.1).

    Args:
        uv: [..., 2].
        matrix: [..., 3, 3], broadcast against uv's leading dimensions (a
            single [3, 3] applies to all).  See :func:`uv_transform`.
        uv_dx, uv_dy: optional [..., 2] uv per pixel column / row.

    Returns:
        uv [..., 2], or ``(uv, uv_dx, uv_dy)`` transformed by the Jacobian
        (the linear part for affine matrices; the projective quotient rule
        otherwise).  ``w = 0`` (points at infinity of a projective matrix)
        gives +-inf in both coordinates (the sign of x, resp. y; +inf where
        that is 0) and +inf derivatives, with zero gradients there; affine
        matrices never do.

    Differentiable w.r.t. uv, matrix and the derivatives.  Raises ValueError
    naming the argument for shapes other than [..., 2] / [..., 3, 3],
    TypeError for non-floating tensors.
    """
    uv = check_tensor(uv, "uv", 2)
    if not isinstance(matrix, torch.Tensor) or not matrix.is_floating_point():
        raise TypeError(f"matrix must be a floating tensor of shape [..., 3, 3], got "
                        f"{matrix.dtype if isinstance(matrix, torch.Tensor) else type(matrix).__name__}")
    if matrix.dim() < 2 or matrix.shape[-2:] != (3, 3):
        raise ValueError(f"matrix must have shape [..., 3, 3], got {tuple(matrix.shape)}")
    broadcast(uv.shape[:-1], matrix.shape[:-2], "matrix's batch shape", "uv's")
    duvs = check_derivs(uv_dx, uv_dy, "uv", 2, uv)
    m = matrix
    u, v = uv[..., 0], uv[..., 1]
    x = m[..., 0, 0] * u + m[..., 0, 1] * v + m[..., 0, 2]
    y = m[..., 1, 0] * u + m[..., 1, 1] * v + m[..., 1, 2]
    w = m[..., 2, 0] * u + m[..., 2, 1] * v + m[..., 2, 2]
    # w = 0 is a point at infinity: every coordinate is infinite there (0 / 0
    # would make the one with x = 0 NaN), signed like x (+inf for x = 0), and
    # its derivatives +inf (an unbounded footprint). The double where keeps the
    # division's backward off w = 0: the result is constant there, gradient 0.
    at_inf = w == 0
    w = torch.where(at_inf, 1.0, w)

    out = torch.stack([torch.where(at_inf, torch.where(x < 0, -math.inf, math.inf), x / w),
                       torch.where(at_inf, torch.where(y < 0, -math.inf, math.inf), y / w)], dim=-1)
    douts = []
    for d in duvs:
        du, dv = d[..., 0], d[..., 1]
        dx = m[..., 0, 0] * du + m[..., 0, 1] * dv
        dy = m[..., 1, 0] * du + m[..., 1, 1] * dv
        dw = m[..., 2, 0] * du + m[..., 2, 1] * dv
        jac = torch.stack([(dx * w - x * dw) / (w * w), (dy * w - y * dw) / (w * w)], dim=-1)
        douts.append(torch.where(at_inf[..., None], math.inf, jac))
    return result(out, douts)


def uv_transform(shift: TensorLike = (0.0, 0.0), angle: Union[float, torch.Tensor] = 0.0,
                 scale: TensorLike = 1.0, *, center: TensorLike = (0.5, 0.5),
                 dtype: Optional[torch.dtype] = None, device=None) -> torch.Tensor:
    """Build an affine texture matrix: scale, then rotate about ``center``, then shift.

    ``uv' = R(angle) S(scale) (uv - center) + center + shift``.

    Args:
        shift: [..., 2] (or a pair) added to uv.
        angle: [...] radians; ``R = [[cos, -sin], [sin, cos]]`` acting on
            (u, v).  With v running down the rows a positive angle turns the
            u axis towards +v, i.e. clockwise as displayed.
        scale: a number (uniform), or [..., 2] per-axis factors.
        center: [..., 2] fixed point of the rotation and scale (default the
            texture centre).
        dtype, device: for the result when no argument is a tensor (default
            float32, CPU); otherwise taken from the tensor arguments.

    Returns:
        [..., 3, 3] with last row (0, 0, 1), batch shape broadcast from the
        arguments.  Use with :func:`texture_matrix`; its inverse
        (``torch.linalg.inv``) undoes it.

    Differentiable w.r.t. every tensor argument.  Raises ValueError naming the
    argument for shift / scale / center without a last dimension of 2,
    TypeError naming it for a value that is not numbers (a str, ...).
    """
    tensors = [t for t in (shift, angle, scale, center) if isinstance(t, torch.Tensor)]
    if dtype is None:
        # An integer tensor argument (scale=torch.tensor(2)) must not make
        # the result integer: that would truncate the shift and centre.
        floats = [t.dtype for t in tensors if t.is_floating_point()]
        dtype = floats[0] if floats else torch.get_default_dtype()
    elif not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating dtype, got {dtype}")
    if device is None and tensors:
        device = tensors[0].device

    def conv(x, name, shape_doc):
        return x.to(dtype=dtype, device=device) if isinstance(x, torch.Tensor) else \
            as_float(x, name, shape_doc, dtype, device)

    shift, angle = conv(shift, "shift", "[..., 2]"), conv(angle, "angle", "[...]")
    scale, center = conv(scale, "scale", "[] or [..., 2]"), conv(center, "center", "[..., 2]")
    if shift.dim() < 1 or shift.shape[-1] != 2:
        raise ValueError(f"shift must have shape [..., 2], got {tuple(shift.shape)}")
    if center.dim() < 1 or center.shape[-1] != 2:
        raise ValueError(f"center must have shape [..., 2], got {tuple(center.shape)}")
    if scale.dim() == 0:
        scale = scale.expand(2)
    elif scale.shape[-1] != 2:
        raise ValueError(f"scale must be a number or have shape [..., 2], got {tuple(scale.shape)}")
    c, s = torch.cos(angle), torch.sin(angle)
    sx, sy = scale[..., 0], scale[..., 1]
    a00, a01, a10, a11 = c * sx, -s * sy, s * sx, c * sy
    cu, cv = center[..., 0], center[..., 1]
    t0 = cu + shift[..., 0] - (a00 * cu + a01 * cv)
    t1 = cv + shift[..., 1] - (a10 * cu + a11 * cv)
    a00, a01, a10, a11, t0, t1 = torch.broadcast_tensors(a00, a01, a10, a11, t0, t1)
    zero, one = torch.zeros_like(a00), torch.ones_like(a00)
    rows = [torch.stack([a00, a01, t0], -1), torch.stack([a10, a11, t1], -1),
            torch.stack([zero, zero, one], -1)]
    return torch.stack(rows, dim=-2)

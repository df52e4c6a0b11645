"""The uv generators: planar, cylindrical, spherical, box and normal projection (see ``difftex.mapping``)."""
from __future__ import annotations

import math
from typing import Optional, Union

import torch

from .common import (EPS, TensorLike, UVResult, as_float, as_param, azimuth, broadcast, check_derivs, check_tensor,
                     cube_tables, dot, finite_only, major_face, nan_where, pick, result, sphere_uv)


def planar_uv(points: torch.Tensor, origin: TensorLike, axis_u: TensorLike, axis_v: TensorLike, *,
              points_dx: Optional[torch.Tensor] = None,
              points_dy: Optional[torch.Tensor] = None) -> UVResult:
    """Planar (orthographic) projection: ``u = (p - origin) . axis_u``, ``v = (p - origin) . axis_v``.

    Args:
        points: [..., 3] positions.
        origin: [..., 3] (or a 3-sequence) point that maps to uv (0, 0), the
            top-left corner of the texture.
        axis_u, axis_v: [..., 3] vectors, not normalised: their length is
            1 / (extent covered by one texture width / height).  With image
            rows running down, a texture that should appear upright on a
            y-up plane takes ``axis_v = (0, -1 / height, 0)``.
        points_dx, points_dy: optional [..., 3] d(points)/d(pixel column / row).

    Returns:
        uv [..., 2] (broadcast shape), or ``(uv, uv_dx, uv_dy)`` when the
        point derivatives are given.  Not clamped: wrap modes decide.

    Differentiable w.r.t. every tensor argument.  Raises ValueError naming
    the argument for a last dimension other than 3 or non-broadcastable
    shapes, TypeError for non-floating tensors.
    """
    points = check_tensor(points, "points", 3)
    origin = as_param(origin, "origin", 3, points)
    axis_u = as_param(axis_u, "axis_u", 3, points)
    axis_v = as_param(axis_v, "axis_v", 3, points)
    dps = check_derivs(points_dx, points_dy, "points", 3, points)
    d = points - origin
    uv = torch.stack([dot(d, axis_u), dot(d, axis_v)], dim=-1)
    duv = [torch.stack([dot(dp, axis_u), dot(dp, axis_v)], dim=-1) for dp in dps]
    return result(uv, duv)


def _first(x: torch.Tensor, where: torch.Tensor) -> list[float]:
    """The first [3] vector of x (broadcast against ``where`` [..., 1]) where ``where`` holds, for messages."""
    shape = torch.broadcast_shapes(x.shape, where.shape[:-1] + (3,))
    i = int(where.expand(*shape[:-1], 1).reshape(-1).nonzero()[0])
    return [round(float(c), 6) for c in x.detach().expand(shape).reshape(-1, 3)[i]]


def _cylinder_frame(axis: torch.Tensor, ref: Optional[torch.Tensor]):
    """Unit vectors (e1, e2) spanning the plane orthogonal to ``axis``, phi = 0 along e1."""
    n = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True).clamp_min(EPS)
    given = ref is not None
    if ref is None:
        ex = torch.tensor([1.0, 0.0, 0.0], dtype=axis.dtype, device=axis.device)
        ey = torch.tensor([0.0, 1.0, 0.0], dtype=axis.dtype, device=axis.device)
        # x unless the axis is close to x, where its projection would degenerate.
        ref = torch.where(n[..., :1].abs() > 0.9, ey, ex)
    e1 = ref - dot(ref, n)[..., None] * n
    e1_len = torch.linalg.vector_norm(e1, dim=-1, keepdim=True)
    if given:
        # Along the axis, ref has no direction in the plane of phi: u would be
        # 0.5 everywhere (or follow rounding noise), never what was asked.
        tol = torch.finfo(ref.dtype).eps ** 0.5
        flat = (e1_len <= tol * torch.linalg.vector_norm(ref, dim=-1, keepdim=True)).detach()
        if bool(flat.any()):
            raise ValueError(f"ref: must not be parallel to axis (its part orthogonal to the axis must be at "
                             f"least {tol:.1e} of its length); got ref {_first(ref, flat)} with axis "
                             f"{_first(axis, flat)}")
    e1 = e1 / e1_len.clamp_min(EPS)
    n, e1 = torch.broadcast_tensors(n, e1)
    e2 = torch.linalg.cross(n, e1, dim=-1)
    return e1, e2


def cylindrical_uv(points: torch.Tensor, center: TensorLike, axis: TensorLike, *,
                   ref: Optional[TensorLike] = None,
                   points_dx: Optional[torch.Tensor] = None,
                   points_dy: Optional[torch.Tensor] = None) -> UVResult:
    """Cylindrical projection: u from the angle around ``axis``, v from the height along it.

    Args:
        points: [..., 3] positions.
        center: [..., 3] centre of the cylinder (on the axis, at mid-height).
        axis: [..., 3] vector from ``center`` to the centre of the top cap;
            its length is half the height.  The top cap maps to v = 0 (the
            texture's top row), the bottom cap to v = 1:
            ``v = (1 - h) / 2`` with ``h = (p - center) . axis / |axis|^2``.
        ref: optional [..., 3] direction of phi = 0 (projected onto the plane
            orthogonal to the axis).  Default: +x, or +y when the axis is
            within ~25 degrees of x.  With ``axis = +z`` the default gives
            ``phi = atan2(y - yc, x - xc)``, the same u as :func:`spherical_uv`.
        points_dx, points_dy: optional [..., 3] d(points)/d(pixel column / row).

    Returns:
        uv [..., 2] with ``u = (phi + pi) / 2pi``, phi in (-pi, pi] measured
        from ``ref`` towards ``axis x ref``; or ``(uv, uv_dx, uv_dy)``.  The
        seam (u jumping 1 -> 0) is at phi = pi, opposite ``ref``; uv_dx /
        uv_dy are continuous across it.  Within :data:`EPS` of the axis
        u = 0.5 (see the module notes).

    Differentiable w.r.t. points, center, axis and the derivatives; outputs
    and gradients are finite on the axis.  Raises ValueError naming the
    argument for a last dimension other than 3 or a ``ref`` (nearly)
    parallel to ``axis`` (its part orthogonal to the axis under sqrt(eps) of
    its length: no phi = 0 direction), TypeError for non-floating tensors.
    """
    points = check_tensor(points, "points", 3)
    center = as_param(center, "center", 3, points)
    axis = as_param(axis, "axis", 3, points)
    if ref is not None:
        ref = as_param(ref, "ref", 3, points)
    dps = check_derivs(points_dx, points_dy, "points", 3, points)
    e1, e2 = _cylinder_frame(axis, ref)
    # A non-finite point must not reach the dot products: their backward
    # multiplies it by the (zero) incoming gradient, and 0 * NaN would reach
    # the shared axis / ref / center.
    d = points - center
    (*d,), dps, ok, oks_d = finite_only(list(d.unbind(-1)), [list(dp.unbind(-1)) for dp in dps])
    d, dps = torch.stack(d, -1), [torch.stack(dp, -1) for dp in dps]
    inv_len2 = 1.0 / dot(axis, axis).clamp_min(EPS * EPS)
    a, b = dot(d, e1), dot(d, e2)
    phi, dphis = azimuth(a, b, [dot(dp, e1) for dp in dps], [dot(dp, e2) for dp in dps])
    h = dot(d, axis) * inv_len2
    uv = torch.stack([(phi + math.pi) / (2 * math.pi), 0.5 * (1.0 - h)], dim=-1)
    duv = [nan_where(torch.stack([dphi / (2 * math.pi), -0.5 * dot(dp, axis) * inv_len2], dim=-1), o)
           for dphi, dp, o in zip(dphis, dps, oks_d)]
    return result(nan_where(uv, ok), duv)


def spherical_uv(points: torch.Tensor, center: TensorLike = (0.0, 0.0, 0.0), *,
                 points_dx: Optional[torch.Tensor] = None,
                 points_dy: Optional[torch.Tensor] = None) -> UVResult:
    """Spherical (latitude / longitude) projection about ``center``, +z up.

    The seed formula: ``theta = arccos((z - zc) / r)``, ``phi = atan2(y - yc,
    x - xc)``, ``u = (phi + pi) / 2pi``, ``v = theta / pi``; theta is
    computed as ``atan2(r_xy, z - zc)``, which equals the arccos but has a
    finite derivative at the poles.  The +z pole maps to v = 0 (top row),
    -z to v = 1; the seam (u = 1 -> 0) is on the -x half-plane.

    Args:
        points: [..., 3] positions (any radius: only the direction matters).
        center: [..., 3] centre of the sphere.
        points_dx, points_dy: optional [..., 3] d(points)/d(pixel column / row).

    Returns:
        uv [..., 2], or ``(uv, uv_dx, uv_dy)``.  Within :data:`EPS` of the z
        axis u = 0.5; at the centre v = 0.5 as well.

    Differentiable w.r.t. points, center and the derivatives; finite values
    and gradients at the poles and the centre.  Raises ValueError naming the
    argument for a last dimension other than 3, TypeError for non-floating
    tensors.
    """
    points = check_tensor(points, "points", 3)
    center = as_param(center, "center", 3, points)
    dps = check_derivs(points_dx, points_dy, "points", 3, points)
    d = points - center
    uv, duv = sphere_uv(d[..., 0], d[..., 1], d[..., 2],
                         [dp[..., 0] for dp in dps], [dp[..., 1] for dp in dps],
                         [dp[..., 2] for dp in dps])
    return result(uv, duv)


def normal_uv(normals: torch.Tensor, *,
              normals_dx: Optional[torch.Tensor] = None,
              normals_dy: Optional[torch.Tensor] = None) -> UVResult:
    """Normal-vector projection onto a sphere: the spherical map of the normal direction.

    ``normal_uv(n) == spherical_uv(n, center=0)``: a surface point takes the
    uv of the point of the unit sphere with the same normal (+z up, v = 0 at
    +z, seam on -x).  Normals need not be unit length.

    Args:
        normals: [..., 3].
        normals_dx, normals_dy: optional [..., 3] d(normal)/d(pixel column / row)
            (of the interpolated, not necessarily normalised, normal).

    Returns:
        uv [..., 2], or ``(uv, uv_dx, uv_dy)``.  A zero normal gives (0.5, 0.5).

    Differentiable w.r.t. normals and their derivatives, NaN-free for zero
    and polar normals.  Raises ValueError naming the argument for a last
    dimension other than 3, TypeError for non-floating tensors.
    """
    normals = check_tensor(normals, "normals", 3)
    dns = check_derivs(normals_dx, normals_dy, "normals", 3, normals)
    uv, duv = sphere_uv(normals[..., 0], normals[..., 1], normals[..., 2],
                         [d[..., 0] for d in dns], [d[..., 1] for d in dns], [d[..., 2] for d in dns])
    return result(uv, duv)


def box_uv(points: torch.Tensor, normals: torch.Tensor, *,
           center: TensorLike = (0.0, 0.0, 0.0), size: Union[float, torch.Tensor] = 1.0,
           layout: str = "shared",
           points_dx: Optional[torch.Tensor] = None,
           points_dy: Optional[torch.Tensor] = None) -> UVResult:
    """Box projection: project each point from the cube face its normal points to.

    The face of a point is the OpenGL cube-map face of its normal (largest
    |component|; ties prefer x over y over z; a zero normal gives +X), i.e.
    ``direction_to_cube(normals)[0]``.  Within the face the point is
    projected orthographically with the cube-map orientation of
    :func:`direction_to_cube`: the image appears unmirrored, upright (+y up
    on the side faces) seen from outside the box.  On the surface of the box
    the result equals ``direction_to_cube(points - center)``.

    Args:
        points: [..., 3] positions.
        normals: [..., 3] normals (not necessarily unit); only their
            direction's dominant axis is used, so no gradient flows to them.
        center, size: the box ``center +- size / 2`` covers each face's
            texture once; points outside it get uv outside [0, 1].  size is
            one edge length for all three axes: a number or a [...] tensor
            broadcast against the points' batch shape (not a per-axis [3]).
        layout: ``"shared"``: every face uses the whole [0, 1]^2 square;
            ``"atlas"``: a 3 x 2 atlas, columns of width 1/3 and rows of
            height 1/2, row 0 = (+X, -X, +Y), row 1 = (-Y, +Z, -Z).
        points_dx, points_dy: optional [..., 3] d(points)/d(pixel column / row).

    Returns:
        uv [..., 2], or ``(uv, uv_dx, uv_dy)``.  The derivatives are those of
        the face the pixel is on (the face is piecewise constant).

    Differentiable w.r.t. points, center, size and the point derivatives.
    Raises ValueError naming the argument for bad shapes, an unknown layout
    or a size that is not positive, TypeError for non-floating tensors or
    non-numeric parameters.
    """
    points = check_tensor(points, "points", 3)
    normals = check_tensor(normals, "normals", 3)
    center = as_param(center, "center", 3, points)
    if layout not in ("shared", "atlas"):
        raise ValueError(f"layout must be 'shared' or 'atlas', got {layout!r}")
    if not isinstance(size, torch.Tensor):
        size = as_float(size, "size", "[...] (a number or one per point)", points.dtype, points.device)
    elif not size.is_floating_point():
        size = size.to(points.dtype)
    broadcast(points.shape[:-1], size.shape, "size", "points' batch shape")
    # The scale is 2 / size: 0 gave inf / NaN uv, a negative size a mirrored box.
    if size.numel() and not bool((size.detach() > 0).all()):
        bad = size.detach()[~(size.detach() > 0)].reshape(-1)[0].item()
        raise ValueError(f"size must be positive (the box's edge length), got {bad}")
    dps = check_derivs(points_dx, points_dy, "points", 3, points)
    try:
        shape = torch.broadcast_shapes(points.shape, normals.shape, center.shape)
    except RuntimeError:
        raise ValueError(f"points {tuple(points.shape)}, normals {tuple(normals.shape)} and "
                         f"center {tuple(center.shape)} must broadcast") from None
    face = major_face(normals.expand(shape))
    sc_ax, sc_sg, tc_ax, tc_sg, _, _ = cube_tables(face)
    sc_sg, tc_sg = sc_sg.to(points.dtype), tc_sg.to(points.dtype)
    scale = 2.0 / size[..., None] if size.dim() else 2.0 / size
    q = (points - center) * scale  # [-1, 1]^3 inside the box
    u = 0.5 * (sc_sg * pick(q, sc_ax) + 1.0)
    v = 0.5 * (tc_sg * pick(q, tc_ax) + 1.0)
    duv = [torch.stack([0.5 * sc_sg * pick(dp * scale, sc_ax),
                        0.5 * tc_sg * pick(dp * scale, tc_ax)], dim=-1) for dp in dps]
    uv = torch.stack([u, v], dim=-1)
    if layout == "atlas":
        cell = torch.stack([(face % 3), (face // 3)], dim=-1).to(points.dtype)
        factor = torch.tensor([1.0 / 3.0, 0.5], dtype=points.dtype, device=points.device)
        uv = (uv + cell) * factor
        duv = [d * factor for d in duv]
    return result(uv, duv)

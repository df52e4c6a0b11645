"""Procedural uv generators: planar, cylindrical, spherical, box, normal projection,
environment-map directions (equirectangular, cube map) and the texture matrix.

Every generator is a plain differentiable torch function, batched over the
leading dimensions of its inputs (``[..., 3]`` points -> ``[..., 2]`` uv, so
``[B, H, W, 3]`` per-pixel positions give ``[B, H, W, 2]`` uv as DESIGN.md
wants), float32 / float64, any device.

Screen-space derivatives.  Each generator optionally takes the derivatives
of its input with respect to the pixel column / row (``points_dx``,
``points_dy``, as ``interpolate(derivatives=True)`` gives them) and then
returns ``(uv, uv_dx, uv_dy)`` computed by the chain rule with the analytic
Jacobian of the mapping.  This is not a convenience: finite differences of
uv across the atan2 seam of the spherical / cylindrical / equirectangular
maps jump by a whole texture width, which makes mip selection pick the
coarsest level along the seam; the analytic Jacobian is continuous there.

Singular points.  The angle ``phi = atan2(b, a)`` is undefined on the axis
(``a = b = 0``, the poles of a sphere, the axis of a cylinder) and the polar
angle is undefined at the centre.  Closer than :data:`EPS` (in the units of
the points) to the axis, ``phi`` is taken as 0 (so ``u = 0.5``); at the
centre itself the polar angle is pi/2 (``v = 0.5``).  Exactly on the axis
the distance to it is a cone point without a linear derivative, and its
derivative (like phi's) is taken as 0 there, so uv_dx / uv_dy are 0 there
except the cylinder's height term; just off it (r >= EPS) they are exact and grow
like 1 / r, as the true footprint does.  Denominators of the
Jacobians are clamped at ``EPS**2`` and the square root / atan2 are guarded
with the double-``where`` trick, so outputs and gradients stay finite
(large near the axis, where the true derivative diverges) and never NaN.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Union

import torch

__all__ = [
    "EPS",
    "planar_uv",
    "cylindrical_uv",
    "spherical_uv",
    "box_uv",
    "normal_uv",
    "direction_to_equirect_uv",
    "equirect_uv_to_direction",
    "direction_to_cube",
    "cube_to_direction",
    "texture_matrix",
    "uv_transform",
    "CUBE_FACES",
]

#: Distance (in the units of the input points) below which a point counts as
#: lying on the axis / at the centre of a polar mapping; see the module notes.
EPS = 1e-9

#: Cube-map face order (OpenGL ``GL_TEXTURE_CUBE_MAP_POSITIVE_X + i``).
CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")

# OpenGL 4.6 table 8.19: for face i, s_c = SC_SGN * r[SC_AX], t_c = TC_SGN * r[TC_AX],
# m_a = MA_SGN * r[MA_AX] (> 0 on that face), s = (s_c / m_a + 1) / 2, t likewise.
_SC_AX = (2, 2, 0, 0, 0, 0)
_SC_SGN = (-1.0, 1.0, 1.0, 1.0, 1.0, -1.0)
_TC_AX = (1, 1, 2, 2, 1, 1)
_TC_SGN = (-1.0, -1.0, 1.0, -1.0, -1.0, -1.0)
_MA_AX = (0, 0, 1, 1, 2, 2)
_MA_SGN = (1.0, -1.0, 1.0, -1.0, 1.0, -1.0)

TensorLike = Union[torch.Tensor, Sequence[float], float]
UVResult = Union[torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]


# --------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------


def _check_tensor(x, name: str, k: int) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape [..., {k}], got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor (float32 / float64), got dtype {x.dtype}")
    if x.dim() < 1 or x.shape[-1] != k:
        raise ValueError(f"{name} must have shape [..., {k}], got {tuple(x.shape)}")
    return x


def _as_param(x, name: str, k: int, like: torch.Tensor) -> torch.Tensor:
    """A parameter given as a tensor or a plain sequence, on ``like``'s device, broadcastable with ``like``."""
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x, dtype=like.dtype, device=like.device)
    x = _check_tensor(x, name, k)
    _broadcast(like.shape, x.shape, name, "points")
    return x


def _broadcast(shape: torch.Size, other: torch.Size, name: str, against: str) -> torch.Size:
    """The broadcast of ``against``'s shape and ``name``'s shape ``other``; ValueError naming both if none."""
    try:
        return torch.broadcast_shapes(shape, other)
    except RuntimeError:
        raise ValueError(f"{name} must broadcast with {against} {tuple(shape)}, got {tuple(other)}") from None


def _check_derivs(dx, dy, name: str, k: int, value: torch.Tensor) -> list[torch.Tensor]:
    """The given derivatives as a list ([] when none), each broadcast to ``value``."""
    if dx is None and dy is None:
        return []
    if dx is None or dy is None:
        given = f"{name}_dx" if dy is None else f"{name}_dy"
        raise ValueError(f"{name}_dx and {name}_dy must be given together, got only {given}")
    out = []
    for d, n in ((dx, f"{name}_dx"), (dy, f"{name}_dy")):
        _check_tensor(d, n, k)
        out.append(d.expand(_broadcast(value.shape, d.shape, n, name)))
    return out


def _result(uv: torch.Tensor, duv: list[torch.Tensor]) -> UVResult:
    # The derivatives get uv's full batch shape, which parameters (origin,
    # center, ...) may have widened beyond the points'.
    return (uv, duv[0].expand_as(uv), duv[1].expand_as(uv)) if duv else uv


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


# --------------------------------------------------------------------------
# polar machinery shared by spherical / cylindrical / normal / equirect
# --------------------------------------------------------------------------


def _azimuth(a, b, das, dbs):
    """phi = atan2(b, a) and its directional derivatives, NaN-free on the axis."""
    r2 = a * a + b * b
    ok = r2 > EPS * EPS
    # Double where: atan2's backward at (0, 0) is 0/0, so feed it a harmless
    # point where the result is discarded anyway.
    a_s = torch.where(ok, a, torch.ones_like(a))
    b_s = torch.where(ok, b, torch.zeros_like(b))
    phi = torch.where(ok, torch.atan2(b_s, a_s), torch.zeros_like(a))
    den = r2.clamp_min(EPS * EPS)
    dphis = [(a * db - b * da) / den for da, db in zip(das, dbs)]
    return phi, dphis


def _polar(a, b, c, das, dbs, dcs):
    """theta = angle from the +c axis, atan2(sqrt(a^2 + b^2), c), and its derivatives."""
    r2 = a * a + b * b
    ok = r2 > EPS * EPS
    # sqrt has an infinite derivative at 0: same double-where guard.
    rho = torch.where(ok, torch.sqrt(torch.where(ok, r2, torch.ones_like(r2))), torch.zeros_like(r2))
    big2 = r2 + c * c
    ok3 = big2 > EPS * EPS
    rho_s = torch.where(ok3, rho, torch.ones_like(rho))
    c_s = torch.where(ok3, c, torch.zeros_like(c))
    theta = torch.where(ok3, torch.atan2(rho_s, c_s), torch.full_like(c, math.pi / 2))
    rho_den = rho.clamp_min(EPS)
    big_den = big2.clamp_min(EPS * EPS)
    dthetas = []
    for da, db, dc in zip(das, dbs, dcs):
        drho = (a * da + b * db) / rho_den
        dthetas.append((c * drho - rho * dc) / big_den)
    return theta, dthetas


def _sphere_uv(a, b, c, das, dbs, dcs):
    """u = (atan2(b, a) + pi) / 2pi, v = angle from +c / pi, with derivatives."""
    phi, dphis = _azimuth(a, b, das, dbs)
    theta, dthetas = _polar(a, b, c, das, dbs, dcs)
    uv = torch.stack([(phi + math.pi) / (2 * math.pi), theta / math.pi], dim=-1)
    duv = [torch.stack([dp / (2 * math.pi), dt / math.pi], dim=-1) for dp, dt in zip(dphis, dthetas)]
    return uv, duv


# --------------------------------------------------------------------------
# object-space generators
# --------------------------------------------------------------------------


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
    points = _check_tensor(points, "points", 3)
    origin = _as_param(origin, "origin", 3, points)
    axis_u = _as_param(axis_u, "axis_u", 3, points)
    axis_v = _as_param(axis_v, "axis_v", 3, points)
    dps = _check_derivs(points_dx, points_dy, "points", 3, points)
    d = points - origin
    uv = torch.stack([_dot(d, axis_u), _dot(d, axis_v)], dim=-1)
    duv = [torch.stack([_dot(dp, axis_u), _dot(dp, axis_v)], dim=-1) for dp in dps]
    return _result(uv, duv)


def _cylinder_frame(axis: torch.Tensor, ref: Optional[torch.Tensor]):
    """Unit vectors (e1, e2) spanning the plane orthogonal to ``axis``, phi = 0 along e1."""
    n = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True).clamp_min(EPS)
    if ref is None:
        ex = torch.tensor([1.0, 0.0, 0.0], dtype=axis.dtype, device=axis.device)
        ey = torch.tensor([0.0, 1.0, 0.0], dtype=axis.dtype, device=axis.device)
        # x unless the axis is close to x, where its projection would degenerate.
        ref = torch.where(n[..., :1].abs() > 0.9, ey, ex)
    e1 = ref - _dot(ref, n)[..., None] * n
    e1 = e1 / torch.linalg.vector_norm(e1, dim=-1, keepdim=True).clamp_min(EPS)
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
    argument for a last dimension other than 3, TypeError for non-floating
    tensors.
    """
    points = _check_tensor(points, "points", 3)
    center = _as_param(center, "center", 3, points)
    axis = _as_param(axis, "axis", 3, points)
    if ref is not None:
        ref = _as_param(ref, "ref", 3, points)
    dps = _check_derivs(points_dx, points_dy, "points", 3, points)
    e1, e2 = _cylinder_frame(axis, ref)
    d = points - center
    inv_len2 = 1.0 / _dot(axis, axis).clamp_min(EPS * EPS)
    a, b = _dot(d, e1), _dot(d, e2)
    phi, dphis = _azimuth(a, b, [_dot(dp, e1) for dp in dps], [_dot(dp, e2) for dp in dps])
    h = _dot(d, axis) * inv_len2
    uv = torch.stack([(phi + math.pi) / (2 * math.pi), 0.5 * (1.0 - h)], dim=-1)
    duv = [torch.stack([dphi / (2 * math.pi), -0.5 * _dot(dp, axis) * inv_len2], dim=-1)
           for dphi, dp in zip(dphis, dps)]
    return _result(uv, duv)


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
    points = _check_tensor(points, "points", 3)
    center = _as_param(center, "center", 3, points)
    dps = _check_derivs(points_dx, points_dy, "points", 3, points)
    d = points - center
    uv, duv = _sphere_uv(d[..., 0], d[..., 1], d[..., 2],
                         [dp[..., 0] for dp in dps], [dp[..., 1] for dp in dps],
                         [dp[..., 2] for dp in dps])
    return _result(uv, duv)


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
    normals = _check_tensor(normals, "normals", 3)
    dns = _check_derivs(normals_dx, normals_dy, "normals", 3, normals)
    uv, duv = _sphere_uv(normals[..., 0], normals[..., 1], normals[..., 2],
                         [d[..., 0] for d in dns], [d[..., 1] for d in dns], [d[..., 2] for d in dns])
    return _result(uv, duv)


def _cube_tables(face: torch.Tensor):
    """Per-element (sc axis, sc sign, tc axis, tc sign, ma axis, ma sign) for face indices."""
    dev = face.device
    tabs = []
    for t, is_axis in ((_SC_AX, True), (_SC_SGN, False), (_TC_AX, True), (_TC_SGN, False),
                       (_MA_AX, True), (_MA_SGN, False)):
        tab = torch.tensor(t, device=dev, dtype=torch.int64 if is_axis else torch.float64)
        tabs.append(tab[face])
    return tabs


def _pick(x: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """x[..., axis[...]] for [..., 3] x, differentiable w.r.t. x."""
    x, axis3 = torch.broadcast_tensors(x, axis[..., None].expand(*axis.shape, 3))
    return torch.gather(x, -1, axis3[..., :1]).squeeze(-1)


def _major_face(v: torch.Tensor) -> torch.Tensor:
    """OpenGL cube face of each vector: 2 * (axis of largest |component|) + (component < 0)."""
    axis = torch.argmax(v.detach().abs(), dim=-1)
    comp = torch.gather(v.detach(), -1, axis[..., None]).squeeze(-1)
    return 2 * axis + (comp < 0).long()


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
    Raises ValueError naming the argument for bad shapes or an unknown
    layout, TypeError for non-floating tensors.
    """
    points = _check_tensor(points, "points", 3)
    normals = _check_tensor(normals, "normals", 3)
    center = _as_param(center, "center", 3, points)
    if layout not in ("shared", "atlas"):
        raise ValueError(f"layout must be 'shared' or 'atlas', got {layout!r}")
    if not isinstance(size, torch.Tensor):
        size = torch.as_tensor(size, dtype=points.dtype, device=points.device)
    _broadcast(points.shape[:-1], size.shape, "size", "points' batch shape")
    dps = _check_derivs(points_dx, points_dy, "points", 3, points)
    try:
        shape = torch.broadcast_shapes(points.shape, normals.shape, center.shape)
    except RuntimeError:
        raise ValueError(f"points {tuple(points.shape)}, normals {tuple(normals.shape)} and "
                         f"center {tuple(center.shape)} must broadcast") from None
    face = _major_face(normals.expand(shape))
    sc_ax, sc_sg, tc_ax, tc_sg, _, _ = _cube_tables(face)
    sc_sg, tc_sg = sc_sg.to(points.dtype), tc_sg.to(points.dtype)
    scale = 2.0 / size[..., None] if size.dim() else 2.0 / size
    q = (points - center) * scale  # [-1, 1]^3 inside the box
    u = 0.5 * (sc_sg * _pick(q, sc_ax) + 1.0)
    v = 0.5 * (tc_sg * _pick(q, tc_ax) + 1.0)
    duv = [torch.stack([0.5 * sc_sg * _pick(dp * scale, sc_ax),
                        0.5 * tc_sg * _pick(dp * scale, tc_ax)], dim=-1) for dp in dps]
    uv = torch.stack([u, v], dim=-1)
    if layout == "atlas":
        cell = torch.stack([(face % 3), (face // 3)], dim=-1).to(points.dtype)
        factor = torch.tensor([1.0 / 3.0, 0.5], dtype=points.dtype, device=points.device)
        uv = (uv + cell) * factor
        duv = [d * factor for d in duv]
    return _result(uv, duv)


# --------------------------------------------------------------------------
# environment-map directions
# --------------------------------------------------------------------------


def direction_to_equirect_uv(dirs: torch.Tensor, *,
                             dirs_dx: Optional[torch.Tensor] = None,
                             dirs_dy: Optional[torch.Tensor] = None) -> UVResult:
    """Equirectangular (latitude / longitude) uv of directions, y-up world.

    Convention: ``v = theta / pi`` with theta the angle from +y (the top row
    is straight up); ``u = (phi + pi) / 2pi`` with ``phi = atan2(x, -z)``:
    the default OpenGL view direction -z is the centre of the panorama
    (u = 0.5), +x is u = 0.75 (right of centre, so the panorama is not
    mirrored for a viewer inside looking along -z), -x is u = 0.25, and the
    seam (u = 1 -> 0) is behind, at +z.  Inverse: :func:`equirect_uv_to_direction`.

    Args:
        dirs: [..., 3] directions, any non-zero length.
        dirs_dx, dirs_dy: optional [..., 3] d(dir)/d(pixel column / row), e.g.
            of the reflected view vector.

    Returns:
        uv [..., 2], or ``(uv, uv_dx, uv_dy)``; the derivatives are
        continuous across the seam.  Straight up / down u = 0.5; a zero
        direction gives (0.5, 0.5).

    Differentiable w.r.t. dirs and their derivatives, NaN-free everywhere.
    Raises ValueError naming the argument for a last dimension other than 3,
    TypeError for non-floating tensors.
    """
    dirs = _check_tensor(dirs, "dirs", 3)
    dds = _check_derivs(dirs_dx, dirs_dy, "dirs", 3, dirs)
    uv, duv = _sphere_uv(-dirs[..., 2], dirs[..., 0], dirs[..., 1],
                         [-d[..., 2] for d in dds], [d[..., 0] for d in dds], [d[..., 1] for d in dds])
    return _result(uv, duv)


def equirect_uv_to_direction(uv: torch.Tensor) -> torch.Tensor:
    """Unit direction of an equirectangular uv; the inverse of :func:`direction_to_equirect_uv`.

    Args:
        uv: [..., 2].

    Returns:
        [..., 3] unit directions.

    Differentiable w.r.t. uv.  Raises ValueError naming the argument for a
    last dimension other than 2, TypeError for non-floating tensors.
    """
    uv = _check_tensor(uv, "uv", 2)
    phi = uv[..., 0] * (2 * math.pi) - math.pi
    theta = uv[..., 1] * math.pi
    s = torch.sin(theta)
    return torch.stack([s * torch.sin(phi), torch.cos(theta), -s * torch.cos(phi)], dim=-1)


def direction_to_cube(dirs: torch.Tensor, *,
                      dirs_dx: Optional[torch.Tensor] = None,
                      dirs_dy: Optional[torch.Tensor] = None):
    """Cube-map face and uv of directions, OpenGL convention.

    Faces are numbered as ``GL_TEXTURE_CUBE_MAP_POSITIVE_X + i``: 0 +X,
    1 -X, 2 +Y, 3 -Y, 4 +Z, 5 -Z (:data:`CUBE_FACES`); the face is the
    largest |component| (ties prefer x over y over z; a zero direction gives
    +X).  Within the face, OpenGL 4.6 table 8.19: ``u = (s_c / |m_a| + 1) / 2``,
    ``v = (t_c / |m_a| + 1) / 2`` with (s_c, t_c, m_a) = (-z, -y, x) on +X,
    (z, -y, x) on -X, (x, z, y) on +Y, (x, -z, y) on -Y, (x, -y, z) on +Z,
    (-x, -y, z) on -Z; OpenGL's t is our v, i.e. row 0 of each face image is
    t = 0 as the faces are stored in files.  The face centre is (0.5, 0.5).

    Args:
        dirs: [..., 3] directions, any non-zero length.
        dirs_dx, dirs_dy: optional [..., 3] d(dir)/d(pixel column / row).

    Returns:
        ``(face, uv)``: face [...] int64, uv [..., 2]; or
        ``(face, uv, uv_dx, uv_dy)`` with the derivatives of the face's own
        projection (the face is piecewise constant).

    Differentiable w.r.t. dirs and their derivatives (not the face index);
    a zero direction gives finite values and gradients.  Raises ValueError
    naming the argument for a last dimension other than 3, TypeError for
    non-floating tensors.
    """
    dirs = _check_tensor(dirs, "dirs", 3)
    dds = _check_derivs(dirs_dx, dirs_dy, "dirs", 3, dirs)
    face = _major_face(dirs)
    sc_ax, sc_sg, tc_ax, tc_sg, ma_ax, ma_sg = _cube_tables(face)
    sc_sg, tc_sg, ma_sg = (t.to(dirs.dtype) for t in (sc_sg, tc_sg, ma_sg))
    sc = sc_sg * _pick(dirs, sc_ax)
    tc = tc_sg * _pick(dirs, tc_ax)
    ma = (ma_sg * _pick(dirs, ma_ax)).clamp_min(EPS)  # > 0 except for the zero vector
    uv = torch.stack([0.5 * (sc / ma + 1.0), 0.5 * (tc / ma + 1.0)], dim=-1)
    duv = []
    for dd in dds:
        dsc = sc_sg * _pick(dd, sc_ax)
        dtc = tc_sg * _pick(dd, tc_ax)
        dma = ma_sg * _pick(dd, ma_ax)
        duv.append(torch.stack([0.5 * (dsc * ma - sc * dma) / (ma * ma),
                                0.5 * (dtc * ma - tc * dma) / (ma * ma)], dim=-1))
    return (face, uv, duv[0], duv[1]) if duv else (face, uv)


def cube_to_direction(face: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Direction (not normalised, |m_a| = 1) of a cube-map face and uv; inverse of :func:`direction_to_cube`.

    Args:
        face: [...] integer face indices 0..5 (:data:`CUBE_FACES`).
        uv: [..., 2] uv within the face.

    Returns:
        [..., 3] the point of the cube [-1, 1]^3 on that face.

    Differentiable w.r.t. uv.  Raises ValueError naming the argument for bad
    shapes, TypeError for a non-integer face or non-floating uv.
    """
    uv = _check_tensor(uv, "uv", 2)
    if not isinstance(face, torch.Tensor) or face.is_floating_point() or face.is_complex():
        raise TypeError(f"face must be an integer tensor of shape [...], got "
                        f"{type(face).__name__ if not isinstance(face, torch.Tensor) else face.dtype}")
    if face.shape != uv.shape[:-1]:
        raise ValueError(f"face must have shape uv.shape[:-1] = {tuple(uv.shape[:-1])}, got {tuple(face.shape)}")
    if face.dtype == torch.bool:
        raise TypeError("face must be an integer tensor of shape [...] with values 0..5, got dtype torch.bool")
    face = face.long()
    if face.numel() and not bool(((face >= 0) & (face <= 5)).all()):
        raise ValueError(f"face must hold values 0..5, got values in [{int(face.min())}, {int(face.max())}]")
    sc_ax, sc_sg, tc_ax, tc_sg, ma_ax, ma_sg = _cube_tables(face)
    sc = (2.0 * uv[..., 0] - 1.0) * sc_sg.to(uv.dtype)
    tc = (2.0 * uv[..., 1] - 1.0) * tc_sg.to(uv.dtype)
    ma = ma_sg.to(uv.dtype)
    axes = torch.arange(3, device=uv.device)
    out = (torch.where(sc_ax[..., None] == axes, sc[..., None], 0.0)
           + torch.where(tc_ax[..., None] == axes, tc[..., None], 0.0)
           + torch.where(ma_ax[..., None] == axes, ma[..., None], 0.0))
    return out


# --------------------------------------------------------------------------
# texture matrix
# --------------------------------------------------------------------------


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
        gives inf; affine matrices never do.

    Differentiable w.r.t. uv, matrix and the derivatives.  Raises ValueError
    naming the argument for shapes other than [..., 2] / [..., 3, 3],
    TypeError for non-floating tensors.
    """
    uv = _check_tensor(uv, "uv", 2)
    if not isinstance(matrix, torch.Tensor) or not matrix.is_floating_point():
        raise TypeError(f"matrix must be a floating tensor of shape [..., 3, 3], got "
                        f"{matrix.dtype if isinstance(matrix, torch.Tensor) else type(matrix).__name__}")
    if matrix.dim() < 2 or matrix.shape[-2:] != (3, 3):
        raise ValueError(f"matrix must have shape [..., 3, 3], got {tuple(matrix.shape)}")
    _broadcast(uv.shape[:-1], matrix.shape[:-2], "matrix's batch shape", "uv's")
    duvs = _check_derivs(uv_dx, uv_dy, "uv", 2, uv)
    m = matrix
    u, v = uv[..., 0], uv[..., 1]
    x = m[..., 0, 0] * u + m[..., 0, 1] * v + m[..., 0, 2]
    y = m[..., 1, 0] * u + m[..., 1, 1] * v + m[..., 1, 2]
    w = m[..., 2, 0] * u + m[..., 2, 1] * v + m[..., 2, 2]
    out = torch.stack([x / w, y / w], dim=-1)
    douts = []
    for d in duvs:
        du, dv = d[..., 0], d[..., 1]
        dx = m[..., 0, 0] * du + m[..., 0, 1] * dv
        dy = m[..., 1, 0] * du + m[..., 1, 1] * dv
        dw = m[..., 2, 0] * du + m[..., 2, 1] * dv
        douts.append(torch.stack([(dx * w - x * dw) / (w * w), (dy * w - y * dw) / (w * w)], dim=-1))
    return _result(out, douts)


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
    argument for shift / scale / center without a last dimension of 2.
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

    def conv(x):
        return x.to(dtype=dtype, device=device) if isinstance(x, torch.Tensor) else \
            torch.as_tensor(x, dtype=dtype, device=device)

    shift, angle, scale, center = conv(shift), conv(angle), conv(scale), conv(center)
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

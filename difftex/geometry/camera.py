"""Camera matrices: world -> view (look_at) and view -> clip (perspective, orthographic).

All matrices are OpenGL style and act on column vectors, ``clip = P @ V @
[x, y, z, 1]``; the camera looks down its -z axis with +y up, so after the
projection NDC y = +1 is the top of the image (row 0, DESIGN.md section 2)
and NDC z runs from -1 at the near plane to +1 at the far plane (smaller is
nearer). :func:`transform` applies a matrix to [..., 3] points.

Every function accepts Python floats or tensors (float32 / float64), keeps
the dtype and device of its float tensor inputs (float64 if any is, else
float32; with none, ``torch.get_default_dtype()`` when that is float32 or
float64, else float32) and is
differentiable with respect to tensor arguments.
"""

from __future__ import annotations

import math
from typing import Union

import torch
from torch import Tensor

__all__ = ["look_at", "perspective", "orthographic", "transform"]

Scalar = Union[float, Tensor]


def _common(*args: object, dtype: torch.dtype | None, device: torch.device | str | None) -> tuple[torch.dtype, torch.device]:
    """dtype / device from the tensor arguments unless given explicitly."""
    tensors = [a for a in args if isinstance(a, Tensor)]
    if dtype is None:
        floats = [t.dtype for t in tensors if t.is_floating_point()]
        if floats:
            dtype = torch.float64 if torch.float64 in floats else torch.float32
        else:
            # No float tensor to follow: torch's default dtype, as torch.tensor(1.0) and
            # difftex.mapping.uv_transform do (float32 where the default is a half type).
            default = torch.get_default_dtype()
            dtype = default if default in (torch.float32, torch.float64) else torch.float32
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype must be float32 or float64, got {dtype}")
    if device is None:
        device = tensors[0].device if tensors else torch.device("cpu")
    return dtype, torch.device(device)


def _as_tensor(x: object, name: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    if isinstance(x, Tensor):
        if x.dtype.is_complex or not (x.dtype.is_floating_point or x.dtype in (torch.int32, torch.int64)):
            raise TypeError(f"{name} must be a real tensor, got dtype {x.dtype}")
        t = x.to(dtype=dtype, device=device)
    else:
        try:
            t = torch.as_tensor(x, dtype=dtype, device=device)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"{name} must be a float or a tensor, got {type(x).__name__}") from None
    if not bool(torch.isfinite(t.detach()).all()):
        raise ValueError(f"{name} must be finite, got {x!r}")
    return t


def _vec3(x: object, name: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    t = _as_tensor(x, name, dtype, device)
    if t.dim() == 0 or t.shape[-1] != 3:
        raise ValueError(f"{name} must have shape [..., 3], got {tuple(t.shape)}")
    return t


def look_at(
    eye: Tensor | tuple[float, float, float],
    at: Tensor | tuple[float, float, float] = (0.0, 0.0, 0.0),
    up: Tensor | tuple[float, float, float] = (0.0, 1.0, 0.0),
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """World-to-view matrix of a camera at ``eye`` looking at ``at``.

    Args:
        eye, at, up: [..., 3] world positions / direction (batch dims
            broadcast). ``up`` need not be orthogonal to the view direction.
        dtype, device: override the ones taken from tensor arguments.

    Returns:
        [..., 4, 4] rigid transform: the camera sits at the origin of view
        space looking down -z, ``up`` projects onto +y, +x is to the right.

    Differentiable with respect to eye, at and up. Raises ValueError when
    eye == at or up is parallel to the view direction.
    """
    dtype, device = _common(eye, at, up, dtype=dtype, device=device)
    eye_t = _vec3(eye, "eye", dtype, device)
    at_t = _vec3(at, "at", dtype, device)
    up_t = _vec3(up, "up", dtype, device)
    eye_t, at_t, up_t = torch.broadcast_tensors(eye_t, at_t, up_t)
    fwd = at_t - eye_t
    fn = fwd.norm(dim=-1, keepdim=True)
    if bool((fn.detach() == 0).any()):
        raise ValueError("look_at: eye and at must differ")
    f = fwd / fn
    side = torch.linalg.cross(f, up_t, dim=-1)
    sn = side.norm(dim=-1, keepdim=True)
    if bool((sn.detach() <= 1e-12 * up_t.detach().norm(dim=-1, keepdim=True).clamp_min(1e-300)).any()):
        raise ValueError("look_at: up must not be parallel to the view direction (at - eye)")
    s = side / sn
    u = torch.linalg.cross(s, f, dim=-1)
    rot = torch.stack((s, u, -f), dim=-2)  # rows: camera x, y, z axes in world
    trans = -(rot @ eye_t.unsqueeze(-1)).squeeze(-1)
    top = torch.cat((rot, trans.unsqueeze(-1)), dim=-1)
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=dtype, device=device)
    bottom[..., 0, 3] = 1
    return torch.cat((top, bottom), dim=-2)


def perspective(
    fov_y: Scalar,
    aspect: Scalar = 1.0,
    near: Scalar = 0.1,
    far: Scalar = 100.0,
    *,
    degrees: bool = False,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """OpenGL perspective projection (view -> clip), like ``gluPerspective``.

    Args:
        fov_y: full vertical field of view, in radians (or degrees with
            ``degrees=True``), in (0, pi).
        aspect: width / height of the image; use W / H of the raster so
            pixels are square.
        near, far: distances to the clipping planes, 0 < near < far.
        dtype, device: override the ones taken from tensor arguments.

    Returns:
        [..., 4, 4]; a view-space point at distance ``near`` maps to NDC
        z = -1, at ``far`` to +1; clip w = -z_view (distance in front).

    Differentiable with respect to tensor arguments. Raises ValueError on
    out-of-range values.
    """
    dtype, device = _common(fov_y, aspect, near, far, dtype=dtype, device=device)
    fov = _as_tensor(fov_y, "fov_y", dtype, device)
    if degrees:
        fov = fov * (math.pi / 180.0)
    a = _as_tensor(aspect, "aspect", dtype, device)
    n = _as_tensor(near, "near", dtype, device)
    f = _as_tensor(far, "far", dtype, device)
    if bool(((fov.detach() <= 0) | (fov.detach() >= math.pi)).any()):
        raise ValueError(f"fov_y must lie in (0, pi) radians, got {fov_y!r}{' degrees' if degrees else ''}")
    if bool((a.detach() <= 0).any()):
        raise ValueError(f"aspect must be positive, got {aspect!r}")
    if bool(((n.detach() <= 0) | (f.detach() <= n.detach())).any()):
        raise ValueError(f"need 0 < near < far, got near={near!r}, far={far!r}")
    fov, a, n, f = torch.broadcast_tensors(fov, a, n, f)
    t = 1.0 / torch.tan(fov / 2)
    z = torch.zeros_like(t)
    rows = (
        (t / a, z, z, z),
        (z, t, z, z),
        (z, z, (f + n) / (n - f), 2 * f * n / (n - f)),
        (z, z, -torch.ones_like(t), z),
    )
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def orthographic(
    left: Scalar,
    right: Scalar,
    bottom: Scalar,
    top: Scalar,
    near: Scalar = 0.1,
    far: Scalar = 100.0,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """OpenGL orthographic projection (view -> clip), like ``glOrtho``.

    Args:
        left, right, bottom, top: view-space extent of the image, left <
            right, bottom < top; x = left lands on NDC -1, y = top on NDC +1
            (the top row of the image).
        near, far: distances of the clipping planes along -z, near < far
            (near may be zero or negative for an orthographic camera).
        dtype, device: override the ones taken from tensor arguments.

    Returns:
        [..., 4, 4] with clip w = 1.

    Differentiable with respect to tensor arguments. Raises ValueError on an
    empty volume.
    """
    dtype, device = _common(left, right, bottom, top, near, far, dtype=dtype, device=device)
    l, r, b, t, n, f = (
        _as_tensor(x, nm, dtype, device)
        for x, nm in ((left, "left"), (right, "right"), (bottom, "bottom"), (top, "top"), (near, "near"), (far, "far"))
    )
    if bool((r.detach() <= l.detach()).any()) or bool((t.detach() <= b.detach()).any()) or bool((f.detach() <= n.detach()).any()):
        raise ValueError(
            f"need left < right, bottom < top, near < far, got {left!r}, {right!r}, {bottom!r}, {top!r}, {near!r}, {far!r}"
        )
    l, r, b, t, n, f = torch.broadcast_tensors(l, r, b, t, n, f)
    z = torch.zeros_like(l)
    o = torch.ones_like(l)
    rows = (
        (2 / (r - l), z, z, -(r + l) / (r - l)),
        (z, 2 / (t - b), z, -(t + b) / (t - b)),
        (z, z, -2 / (f - n), -(f + n) / (f - n)),
        (z, z, z, o),
    )
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def transform(points: Tensor, matrix: Tensor) -> Tensor:
    """Apply a 4x4 matrix to points, returning homogeneous coordinates.

    Args:
        points: [..., V, 3] positions (w = 1 is appended) or [..., V, 4].
        matrix: [..., 4, 4], e.g. ``perspective(...) @ look_at(...)``;
            batch dims broadcast with those of ``points``.

    Returns:
        [..., V, 4], e.g. clip-space positions for :func:`difftex.rasterize`.

    Differentiable with respect to both. Raises ValueError on bad shapes.
    """
    if not isinstance(points, Tensor) or not isinstance(matrix, Tensor):
        raise TypeError("points and matrix must be torch.Tensors")
    if points.dim() < 2 or points.shape[-1] not in (3, 4):
        raise ValueError(f"points must have shape [..., V, 3] or [..., V, 4], got {tuple(points.shape)}")
    if matrix.dim() < 2 or matrix.shape[-2:] != (4, 4):
        raise ValueError(f"matrix must have shape [..., 4, 4], got {tuple(matrix.shape)}")
    if not (points.dtype.is_floating_point and matrix.dtype.is_floating_point):
        raise TypeError(f"points and matrix must be floating point, got {points.dtype} and {matrix.dtype}")
    try:
        torch.broadcast_shapes(points.shape[:-2], matrix.shape[:-2])
    except RuntimeError:
        raise ValueError(f"points' batch shape {tuple(points.shape[:-2])} and matrix's "
                         f"{tuple(matrix.shape[:-2])} must broadcast") from None
    dtype = torch.promote_types(points.dtype, matrix.dtype)
    points, matrix = points.to(dtype), matrix.to(dtype)
    if points.shape[-1] == 3:
        points = torch.cat((points, torch.ones_like(points[..., :1])), dim=-1)
    return points @ matrix.transpose(-1, -2)

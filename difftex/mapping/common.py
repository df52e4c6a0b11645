"""What the uv generators and the environment-map directions share: argument checks, the polar
angles with their screen-space derivatives, and the OpenGL cube-face table.

The singular points of the angles are defined once here (see ``difftex.mapping``'s notes).
"""
from __future__ import annotations

import math
from typing import Sequence, Union

import torch

#: Distance (in the units of the input points) below which a point counts as
#: lying on the axis / at the centre of a polar mapping; see the module notes.
EPS = 1e-9

#: Floor of a cube face's m_a (the major component of a direction, or its
#: component along a neighbouring face's axis) in float64: its square stays
#: a normal number (the native kernel's i2), and directions down to it map
#: exactly. (An absolute 1e-9 once sent shorter directions to the wrong texel.)
DIR_FLOOR = 1e-150
#: The same in float32 (and narrower), where the reciprocals taken of it and
#: their products with a face's derivatives stay finite.
DIR_FLOOR_FLOAT32 = 1e-30


def dir_floor(dtype: torch.dtype) -> float:
    """The floor of m_a in ``dtype`` (the native kernel mirrors both constants)."""
    return DIR_FLOOR if dtype == torch.float64 else DIR_FLOOR_FLOAT32


#: Cube-map face order (OpenGL ``GL_TEXTURE_CUBE_MAP_POSITIVE_X + i``).
CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")

# OpenGL 4.6 table 8.19: for face i, s_c = SC_SGN * r[SC_AX], t_c = TC_SGN * r[TC_AX],
# m_a = MA_SGN * r[MA_AX] (> 0 on that face), s = (s_c / m_a + 1) / 2, t likewise.
SC_AX = (2, 2, 0, 0, 0, 0)
SC_SGN = (-1.0, 1.0, 1.0, 1.0, 1.0, -1.0)
TC_AX = (1, 1, 2, 2, 1, 1)
TC_SGN = (-1.0, -1.0, 1.0, -1.0, -1.0, -1.0)
MA_AX = (0, 0, 1, 1, 2, 2)
MA_SGN = (1.0, -1.0, 1.0, -1.0, 1.0, -1.0)

TensorLike = Union[torch.Tensor, Sequence[float], float]
UVResult = Union[torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]


# --------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------


def check_tensor(x, name: str, k: int) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape [..., {k}], got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor (float32 / float64), got dtype {x.dtype}")
    if x.dim() < 1 or x.shape[-1] != k:
        raise ValueError(f"{name} must have shape [..., {k}], got {tuple(x.shape)}")
    return x


def as_float(x, name: str, shape_doc: str, dtype: torch.dtype, device) -> torch.Tensor:
    """A number or (nested) sequence of numbers as a tensor; TypeError naming ``name`` for anything else."""
    # torch.as_tensor reads a str as a sequence type it cannot convert ("new(): invalid data type 'str'").
    bad = isinstance(x, (str, bytes))
    if not bad:
        try:
            return torch.as_tensor(x, dtype=dtype, device=device)
        except (TypeError, ValueError, RuntimeError):
            bad = True
    raise TypeError(f"{name} must be a tensor or numbers of shape {shape_doc}, got {type(x).__name__} {x!r}")


def as_param(x, name: str, k: int, like: torch.Tensor) -> torch.Tensor:
    """A parameter given as a tensor or a plain sequence, on ``like``'s device, broadcastable with ``like``."""
    if not isinstance(x, torch.Tensor):
        x = as_float(x, name, f"[..., {k}]", like.dtype, like.device)
    x = check_tensor(x, name, k)
    broadcast(like.shape, x.shape, name, "points")
    return x


def broadcast(shape: torch.Size, other: torch.Size, name: str, against: str) -> torch.Size:
    """The broadcast of ``against``'s shape and ``name``'s shape ``other``; ValueError naming both if none."""
    try:
        return torch.broadcast_shapes(shape, other)
    except RuntimeError:
        raise ValueError(f"{name} must broadcast with {against} {tuple(shape)}, got {tuple(other)}") from None


def check_derivs(dx, dy, name: str, k: int, value: torch.Tensor) -> list[torch.Tensor]:
    """The given derivatives as a list ([] when none), each broadcast to ``value``."""
    if dx is None and dy is None:
        return []
    if dx is None or dy is None:
        given = f"{name}_dx" if dy is None else f"{name}_dy"
        raise ValueError(f"{name}_dx and {name}_dy must be given together, got only {given}")
    out = []
    for d, n in ((dx, f"{name}_dx"), (dy, f"{name}_dy")):
        check_tensor(d, n, k)
        out.append(d.expand(broadcast(value.shape, d.shape, n, name)))
    return out


def result(uv: torch.Tensor, duv: list[torch.Tensor]) -> UVResult:
    # The derivatives get uv's full batch shape, which parameters (origin,
    # center, ...) may have widened beyond the points'.
    return (uv, duv[0].expand_as(uv), duv[1].expand_as(uv)) if duv else uv


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


# --------------------------------------------------------------------------
# polar machinery shared by spherical / cylindrical / normal / equirect
# --------------------------------------------------------------------------


def finite_only(vals, derivs):
    """Non-finite inputs kept out of the arithmetic: ``(vals, derivs, ok, oks_d)``.

    ``vals`` is a list of same-shaped [...] components of the points,
    ``derivs`` a list (one per derivative, e.g. d/dx and d/dy) of such lists.
    Where a component of a point is NaN / inf, ``ok`` is False and the
    point's values and derivatives are replaced by 0; where a component of
    derivative k is, ``oks_d[k]`` is False and that derivative is. The
    replaced points compute harmless finite numbers, so backward never forms
    0 * NaN: a product's backward multiplies the incoming gradient (0 for a
    masked-out element) by the other factor, and 0 * NaN would put NaN into
    every parameter the points share (a centre, an axis). The callers put NaN
    back into those elements' outputs (:func:`nan_where`).
    """
    ok = torch.ones((), dtype=torch.bool, device=vals[0].device)
    for v in vals:
        ok = ok & torch.isfinite(v)
    oks_d = []
    for ds in derivs:
        ok_d = ok
        for d in ds:
            ok_d = ok_d & torch.isfinite(d)
        oks_d.append(ok_d)
    vals = [torch.where(ok, v, 0.0) for v in vals]
    derivs = [[torch.where(ok_d, d, 0.0) for d in ds] for ds, ok_d in zip(derivs, oks_d)]
    return vals, derivs, ok, oks_d


def nan_where(x: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """x with NaN where ``ok`` [...] is False (x [...] or [..., k]); no gradient flows to those elements."""
    if x.dim() > ok.dim():
        ok = ok[..., None]
    return torch.where(ok, x, float("nan"))


def _radius(a, b):
    """(hypot(a, b) with a finite gradient at 0, hypot clamped at EPS, ok = hypot > EPS).

    hypot, not sqrt(a^2 + b^2): the squares overflow float32 beyond ~1.8e19.
    """
    ok = torch.hypot(a.detach(), b.detach()) > EPS
    # Double where: hypot's backward at (0, 0) is 0/0; feed it a harmless point where the result is discarded.
    r = torch.where(ok, torch.hypot(torch.where(ok, a, 1.0), torch.where(ok, b, 0.0)), 0.0)
    return r, r.clamp_min(EPS), ok


def _azimuth(a, b, das, dbs):
    rho, rho_c, ok = _radius(a, b)
    # Same guard for atan2's backward at (0, 0).
    phi = torch.where(ok, torch.atan2(torch.where(ok, b, 0.0), torch.where(ok, a, 1.0)), 0.0)
    # (a db - b da) / rho^2, with the quotients taken first so no square overflows.
    an, bn = a / rho_c, b / rho_c
    dphis = [(an * db - bn * da) / rho_c for da, db in zip(das, dbs)]
    return phi, dphis, rho, rho_c, an, bn


def azimuth(a, b, das, dbs):
    """phi = atan2(b, a) and its directional derivatives, NaN-free on the axis.

    A non-finite a or b (or derivative) gives NaN in that element only, and
    no NaN in the gradients of the other elements' inputs.
    """
    (a, b), ds, ok, oks_d = finite_only([a, b], [list(d) for d in zip(das, dbs)])
    phi, dphis, *_ = _azimuth(a, b, [d[0] for d in ds], [d[1] for d in ds])
    return nan_where(phi, ok), [nan_where(d, o) for d, o in zip(dphis, oks_d)]


def _polar(a, b, c, rho, rho_c, an, bn, das, dbs, dcs):
    big, big_c, ok3 = _radius(rho, c)
    theta = torch.where(ok3, torch.atan2(torch.where(ok3, rho, 1.0), torch.where(ok3, c, 0.0)), math.pi / 2)
    cn, rn = c / big_c, rho / big_c
    dthetas = []
    for da, db, dc in zip(das, dbs, dcs):
        drho = an * da + bn * db
        # (c drho - rho dc) / (rho^2 + c^2), quotients first.
        dthetas.append((cn * drho - rn * dc) / big_c)
    return theta, dthetas


def sphere_uv(a, b, c, das, dbs, dcs):
    """u = (atan2(b, a) + pi) / 2pi, v = angle from +c / pi, with derivatives.

    A non-finite input gives NaN in its own uv (and derivative) element only.
    """
    (a, b, c), ds, ok, oks_d = finite_only([a, b, c], [list(d) for d in zip(das, dbs, dcs)])
    das, dbs, dcs = [d[0] for d in ds], [d[1] for d in ds], [d[2] for d in ds]
    phi, dphis, rho, rho_c, an, bn = _azimuth(a, b, das, dbs)
    theta, dthetas = _polar(a, b, c, rho, rho_c, an, bn, das, dbs, dcs)
    uv = torch.stack([(phi + math.pi) / (2 * math.pi), theta / math.pi], dim=-1)
    duv = [nan_where(torch.stack([dp / (2 * math.pi), dt / math.pi], dim=-1), o)
           for dp, dt, o in zip(dphis, dthetas, oks_d)]
    return nan_where(uv, ok), duv


# --------------------------------------------------------------------------
# object-space generators


def cube_tables(face: torch.Tensor):
    """Per-element (sc axis, sc sign, tc axis, tc sign, ma axis, ma sign) for face indices."""
    dev = face.device
    tabs = []
    for t, is_axis in ((SC_AX, True), (SC_SGN, False), (TC_AX, True), (TC_SGN, False),
                       (MA_AX, True), (MA_SGN, False)):
        tab = torch.tensor(t, device=dev, dtype=torch.int64 if is_axis else torch.float64)
        tabs.append(tab[face])
    return tabs


def pick(x: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """x[..., axis[...]] for [..., 3] x, differentiable w.r.t. x."""
    x, axis3 = torch.broadcast_tensors(x, axis[..., None].expand(*axis.shape, 3))
    return torch.gather(x, -1, axis3[..., :1]).squeeze(-1)


def major_face(v: torch.Tensor) -> torch.Tensor:
    """OpenGL cube face of each vector: 2 * (axis of largest |component|) + (component < 0)."""
    axis = torch.argmax(v.detach().abs(), dim=-1)
    comp = torch.gather(v.detach(), -1, axis[..., None]).squeeze(-1)
    return 2 * axis + (comp < 0).long()

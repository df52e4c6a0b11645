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


def as_param(x, name: str, k: int, like: torch.Tensor) -> torch.Tensor:
    """A parameter given as a tensor or a plain sequence, on ``like``'s device, broadcastable with ``like``."""
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x, dtype=like.dtype, device=like.device)
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


def azimuth(a, b, das, dbs):
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


def polar(a, b, c, das, dbs, dcs):
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


def sphere_uv(a, b, c, das, dbs, dcs):
    """u = (atan2(b, a) + pi) / 2pi, v = angle from +c / pi, with derivatives."""
    phi, dphis = azimuth(a, b, das, dbs)
    theta, dthetas = polar(a, b, c, das, dbs, dcs)
    uv = torch.stack([(phi + math.pi) / (2 * math.pi), theta / math.pi], dim=-1)
    duv = [torch.stack([dp / (2 * math.pi), dt / math.pi], dim=-1) for dp, dt in zip(dphis, dthetas)]
    return uv, duv


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

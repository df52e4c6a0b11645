"""Gradient (Perlin) noise in 3D, its fractal sum (fBm), and the wood / marble solid textures built on it.

Perlin's gradient noise ("An image synthesizer", SIGGRAPH 1985; the quintic
fade of "Improving noise", SIGGRAPH 2002): every integer lattice point
``k`` carries a pseudo-random unit gradient ``g_k``; the noise at ``p`` is
the blend of the eight corner ramps ``g_k . (p - k)`` of its cell with the
fade weights ``f(t) = 6 t^5 - 15 t^4 + 10 t^3`` per axis. It is zero on the
lattice, C2 everywhere (so its gradient is smooth enough for finite
differences and gradchecks), periodic with period 256 along each axis and
bounded by ``sqrt(3) / 2`` in magnitude for unit gradients.

The lattice hash is a permutation table, and the gradients are a table of
256 unit vectors; both come from a CPU ``torch.Generator`` seeded with
``seed``, so a seed gives the same noise on every device and dtype.

The solid textures :func:`wood` and :func:`marble` map object-space points
to RGB; evaluate them per pixel (a solid texture) or bake them into an
ordinary 2D texture with :func:`difftex.bake`.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Sequence

import torch
from torch import Tensor

from .._checks import check_float, describe

__all__ = ["perlin", "fbm", "turbulence", "wood", "marble", "NOISE_BOUND"]

#: Largest |perlin(p)| for unit gradients in 3D (sqrt(n) / 2 with n = 3).
NOISE_BOUND = math.sqrt(3.0) / 2
_PERIOD = 256


def _check_seed(seed: object) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"seed: expected an int, got {type(seed).__name__}")
    return seed


@lru_cache(maxsize=32)
def _tables_cpu(seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """Permutation [512] int64 (doubled: hashes need no modulo), gradients [256, 3] float64, octave shifts [64, 3]."""
    gen = torch.Generator().manual_seed(seed)
    perm = torch.randperm(_PERIOD, generator=gen)
    grads = torch.randn(_PERIOD, 3, generator=gen, dtype=torch.float64)
    grads = grads / grads.norm(dim=1, keepdim=True)
    # Per-octave shifts decorrelate the octaves at the lattice points, where every octave would be 0.
    shifts = torch.rand(64, 3, generator=gen, dtype=torch.float64) * _PERIOD
    return torch.cat((perm, perm)), grads, shifts


def _tables(seed: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    perm, grads, shifts = _tables_cpu(seed)
    return perm.to(device), grads.to(device=device, dtype=dtype), shifts.to(device=device, dtype=dtype)


def _check_points(points: object) -> Tensor:
    return check_float("points", points, last=3, shape_doc="[..., 3]")


def _fade(t: Tensor) -> Tensor:
    return t * t * t * (t * (t * 6 - 15) + 10)


def _perlin(p: Tensor, perm: Tensor, grads: Tensor) -> Tensor:
    """Noise at p [..., 3] (already checked) -> [...]; differentiable in p through the ramps and the fades."""
    # Past 2**52 the fraction is gone anyway; the period lets us drop whole periods exactly.
    p = p - _PERIOD * torch.floor(p.detach() / _PERIOD)
    # Just below a multiple of the period the difference rounds up to the period itself (float32: p in about
    # (-7.6e-6, 0)); there the noise is the period's start, not cell 255 at t = 1 clamped to 255.
    p = torch.where(p.detach() >= _PERIOD, p - _PERIOD, p)
    cell = torch.floor(p.detach())
    t = p - cell  # in [0, 1); its gradient is 1 (the floor is a constant)
    i = torch.nan_to_num(cell, nan=0.0, posinf=0.0, neginf=0.0).long().clamp_(0, _PERIOD - 1)
    f = _fade(t)
    out = None
    for dz in (0, 1):
        hz = perm[i[..., 2] + dz]
        for dy in (0, 1):
            hy = perm[i[..., 1] + dy + hz]
            for dx in (0, 1):
                h = perm[i[..., 0] + dx + hy]
                g = grads[h]  # [..., 3]
                off = t - t.new_tensor([dx, dy, dz])
                ramp = (g * off).sum(-1)
                w = ((f[..., 0] if dx else 1 - f[..., 0]) * (f[..., 1] if dy else 1 - f[..., 1])
                     * (f[..., 2] if dz else 1 - f[..., 2]))
                out = w * ramp if out is None else out + w * ramp
    return out


def perlin(points: Tensor, *, seed: int = 0) -> Tensor:
    """Perlin gradient noise at 3D points.

    Args:
        points: [..., 3] float32 / float64 points in lattice units (one unit
            is one noise cell; scale the points for a finer or coarser noise).
        seed: int; the same seed gives the same noise on every device.

    Returns:
        [...] noise values in ``[-NOISE_BOUND, NOISE_BOUND]``
        (``NOISE_BOUND = sqrt(3) / 2``), zero on the integer lattice, mean
        zero over space (in expectation over seeds), period 256 per axis.

    Differentiable with respect to ``points`` (C2, so also twice). Raises
    TypeError on a non-float ``points`` or a non-int ``seed``, ValueError
    naming ``points`` when its last dimension is not 3. NaN / inf points
    give NaN values.
    """
    points = _check_points(points)
    perm, grads, _ = _tables(_check_seed(seed), points.dtype, points.device)
    return _perlin(points, perm, grads)


def _check_octaves(octaves: object, amplitudes: Tensor | None, points: Tensor, gain: float) -> Tensor:
    if amplitudes is None:
        if isinstance(octaves, bool) or not isinstance(octaves, int) or not 1 <= octaves <= 64:
            raise ValueError(f"octaves: expected an int in [1, 64], got {octaves!r}")
        return points.new_tensor([gain ** k for k in range(octaves)])
    amplitudes = check_float("amplitudes", amplitudes, ndim=1, shape_doc="[K] (one per octave)")
    if not 1 <= amplitudes.shape[0] <= 64:
        raise ValueError(f"amplitudes: expected 1 to 64 octaves, got {describe(amplitudes)}")
    if amplitudes.device != points.device:
        raise ValueError(f"amplitudes: expected device {points.device} like points, got {describe(amplitudes)}")
    return amplitudes.to(torch.promote_types(amplitudes.dtype, points.dtype))


def _octave_sum(points: Tensor, amplitudes: Tensor | None, octaves: int, lacunarity: float, gain: float, seed: int,
                absolute: bool) -> Tensor:
    points = _check_points(points)
    amps = _check_octaves(octaves, amplitudes, points, gain)
    if not (isinstance(lacunarity, (int, float)) and math.isfinite(lacunarity) and lacunarity > 0):
        raise ValueError(f"lacunarity: expected a finite number > 0, got {lacunarity!r}")
    perm, grads, shifts = _tables(_check_seed(seed), points.dtype, points.device)
    out = None
    for k in range(amps.shape[0]):
        n = _perlin(points * lacunarity ** k + shifts[k], perm, grads)
        term = amps[k] * (n.abs() if absolute else n)
        out = term if out is None else out + term
    return out


def fbm(points: Tensor, amplitudes: Tensor | None = None, *, octaves: int = 4, lacunarity: float = 2.0,
        gain: float = 0.5, seed: int = 0) -> Tensor:
    """Fractal Brownian motion: ``sum_k a_k perlin(points * lacunarity^k + s_k)``.

    Args:
        points: [..., 3] float points in lattice units of the first octave.
        amplitudes: optional [K] float tensor of per-octave amplitudes
            ``a_k`` (on points' device); default ``gain^k`` for ``octaves``
            octaves.
        octaves: number of octaves when ``amplitudes`` is None (1 to 64).
        lacunarity: frequency ratio of consecutive octaves (> 0).
        gain: amplitude ratio of the default amplitudes.
        seed: int; fixes the lattice tables and the per-octave shifts
            ``s_k`` (which decorrelate the octaves).

    Returns:
        [...] values, bounded by ``NOISE_BOUND * sum_k |a_k|``.

    Differentiable with respect to ``points`` and ``amplitudes``. Raises
    TypeError / ValueError naming the argument on bad input.
    """
    return _octave_sum(points, amplitudes, octaves, lacunarity, gain, seed, absolute=False)


def turbulence(points: Tensor, amplitudes: Tensor | None = None, *, octaves: int = 4, lacunarity: float = 2.0,
               gain: float = 0.5, seed: int = 0) -> Tensor:
    """Perlin's turbulence ``sum_k a_k |perlin(points * lacunarity^k + s_k)|``; arguments as :func:`fbm`.

    Returns [...] values in ``[0, NOISE_BOUND * sum_k |a_k|]``. Differentiable
    in ``points`` and ``amplitudes`` (the absolute value has a kink where an
    octave is zero; its gradient there is 0).
    """
    return _octave_sum(points, amplitudes, octaves, lacunarity, gain, seed, absolute=True)


def _colour(name: str, c: object, like: Tensor) -> Tensor:
    t = torch.as_tensor(c, dtype=like.dtype, device=like.device)
    if t.shape != (3,):
        raise ValueError(f"{name}: expected 3 RGB values, got shape {tuple(t.shape)}")
    return t


def _mix(a: Tensor, b: Tensor, s: Tensor) -> Tensor:
    return a + (b - a) * s.unsqueeze(-1)


def wood(points: Tensor, *, frequency: float = 6.0, grain: float = 0.15, noise_scale: float = 2.0, seed: int = 0,
         light: Sequence[float] = (0.80, 0.58, 0.34), dark: Sequence[float] = (0.45, 0.26, 0.12)) -> Tensor:
    """A wood solid texture: rings around the z axis, wobbled by fBm.

    The ring phase is ``frequency * (r + grain * fbm(noise_scale * p))``
    with ``r`` the distance of ``p`` from the z axis; the colour blends ``light``
    and ``dark`` by ``(0.5 + 0.5 cos(2 pi phase))^3`` (thin dark rings).

    Args:
        points: [..., 3] object-space points (units of the mesh).
        frequency: rings per unit of radius.
        grain: ring wobble in units of radius (``grain * frequency``
            rings); noise_scale: noise cells per unit.
        seed: noise seed. light, dark: RGB colours in [0, 1].

    Returns:
        [..., 3] RGB in the range spanned by ``light`` and ``dark``.

    Differentiable with respect to ``points`` (smooth away from the z axis,
    where ``r`` has a kink). Raises like :func:`fbm`.
    """
    points = _check_points(points)
    lo, hi = _colour("light", light, points), _colour("dark", dark, points)
    n = fbm(points * noise_scale, octaves=3, seed=seed)
    # sqrt(x^2 + y^2 + tiny): finite gradient on the axis itself.
    r = torch.sqrt(points[..., 0] ** 2 + points[..., 1] ** 2 + torch.finfo(points.dtype).tiny)
    phase = frequency * r + grain * frequency * n
    s = (0.5 + 0.5 * torch.cos(2 * math.pi * phase)) ** 3
    return _mix(lo, hi, s)


def marble(points: Tensor, *, frequency: float = 1.5, turbulence_amount: float = 1.2, noise_scale: float = 1.5,
           seed: int = 0, light: Sequence[float] = (0.93, 0.92, 0.88),
           dark: Sequence[float] = (0.25, 0.27, 0.33)) -> Tensor:
    """Perlin's marble: veins ``sin(2 pi (frequency * x + turbulence_amount * turbulence(noise_scale * p)))``.

    Args:
        points: [..., 3] object-space points; the veins run across x.
        frequency: veins per unit along x.
        turbulence_amount: vein distortion, in vein periods per unit of turbulence.
        noise_scale: turbulence cells per unit. seed: noise seed.
        light, dark: RGB colours in [0, 1]; the veins are ``dark``.

    Returns:
        [..., 3] RGB between ``light`` and ``dark``.

    Differentiable with respect to ``points``. Raises like :func:`fbm`.
    """
    points = _check_points(points)
    lo, hi = _colour("light", light, points), _colour("dark", dark, points)
    t = turbulence(points * noise_scale, octaves=4, seed=seed)
    v = torch.sin(2 * math.pi * (frequency * points[..., 0] + turbulence_amount * t))
    # The sixth power narrows the dark veins to where v nears -1.
    s = ((1 - v) * 0.5) ** 6
    return _mix(lo, hi, s)

"""Speed against accuracy of every difftex filter and its peers, on planes, a sphere and the spot cow.

Scenes (every image ``--res`` x ``--res``, 128 by default):

* ``plane-checker-P`` / ``plane-spot-P``: the ground plane of
  :func:`difftex.scenes.grazing_plane` seen ``P`` degrees below the horizon
  (P = 90 is head-on, 5 is grazing; the field of view shrinks with P so that
  every pixel hits the plane), textured with an exact 512^2 checkerboard
  (32 checks a side, values 0.1 / 0.9) or the spot texture, ``repeat``.
* ``sphere-Mx``: a unit icosphere rasterized with :func:`difftex.rasterize`,
  its positions interpolated with derivatives and mapped by
  :func:`difftex.mapping.spherical_uv` (analytic uv_dx / uv_dy), seen so that
  the atan2 seam and the +z pole are in view, at the distance where the
  sphere's front point is minified ``M`` texels a pixel (0.5 = magnified);
  1024^2 checker-plus-noise texture, wrap (repeat, clamp).
* ``spot-D``: the spot mesh and texture from three directions at distance
  ``D``, wrap clamp.

Reference. The 16 x 16 supersampled bilinear render at level 0, box-averaged,
except the checker planes, which have a closed form: the mean of the ideal
checker over the pixel's exact footprint (:func:`checker_pixel_box_mean`,
built on :func:`checker_footprint_mean`, the exact mean over a
parallelogram ``uv + a uv_dx + b uv_dy``, ``a, b in [-1/2, 1/2]``).  Mesh scenes are
scored on the pixels that every supersampling rate covers fully (silhouette
anti-aliasing is not what is measured).

Methods: difftex nearest / bilinear / bicubic (level 0), trilinear,
anisotropic (max_aniso 2, 4, 8, 16), EWA, and "auto" where the installed
difftex has it; peers: ``F.grid_sample`` bilinear at one sample a pixel and
at 2x2, 4x4 and 8x8 supersampled uv (box-averaged), and kornia's
``remap(normalized_coordinates=True, align_corners=False)``.  The peers have
no repeat mode: the texture is padded by one texel (circular for repeat,
replicate for clamp) and uv folded into [0, 1) (``_pad_and_grid``), which
is exact and is part of their timed work.

Timing: only the texture lookup (uv and derivatives given; the supersampled
peers get their n^2 uv for free, so their cost in a real renderer, n^2
rasterization and interpolation, is not counted).  Forward under no_grad and
forward + backward of ``sum()`` with gradients to the texture and uv (the
mip filters build the pyramid inside the timed region).  Methods are run
round-robin, ``--repeats`` rounds a scene in a new random order each round
(so that no method always follows one that evicts the caches), and the
medians reported, so that the load drift of a shared machine hits every
method alike;
``--threads 1`` by default for the same reason.

Outputs in ``--out`` (default results/speed_vs_accuracy): results.csv
(scene, method, psnr, flip, fwd_ms, fwdbwd_ms), speed_vs_accuracy.png (PSNR
against fwd+bwd time, log axis, Pareto fronts), error_grid.png (per-pixel
error images) and summary.md; ``--docs`` also writes docs/speed_vs_accuracy.md
and copies the PNGs to docs/images/.  FLIP (``pip install flip-evaluator``)
is used where it imports, else the column is empty.

    python experiments/speed_vs_accuracy.py [--res 128] [--repeats 5] [--threads 1] [--docs]
"""
from __future__ import annotations

import argparse
import csv
import importlib
import math
import os
import platform
import random
import shutil
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import difftex  # noqa: E402
from difftex import camera  # noqa: E402
from difftex.metrics import psnr as _psnr  # noqa: E402
from difftex.testing.scenes import checker_noise_texture, grazing_plane  # noqa: E402

_sample_mod = importlib.import_module("difftex.texture.options")

try:  # optional perceptual metric; never a dependency of the package
    import flip_evaluator as _flip
except Exception:  # pragma: no cover - depends on the environment
    _flip = None

PITCHES = (90.0, 60.0, 30.0, 15.0, 5.0)
SPHERE_MINIFICATION = (0.5, 5.0, 25.0, 100.0)
SPOT_VIEWS = ((1.6, (1.0, 0.4, 1.0)), (5.0, (-1.0, 0.3, 0.6)), (14.0, (0.3, 0.8, -1.0)))
CHECKER = dict(size=512, checks=32, lo=0.1, hi=0.9)


# --------------------------------------------------------------------------
# closed-form checker reference
# --------------------------------------------------------------------------


def checker_texture(size: int = 512, checks: int = 32, lo: float = 0.1, hi: float = 0.9,
                    channels: int = 3, dtype: torch.dtype = torch.float32) -> Tensor:
    """[1, C, size, size] texel image of the checker whose ideal form :func:`checker_footprint_mean` integrates.

    Texel (i, j) is ``hi`` where ``floor(i / cell) + floor(j / cell)`` is
    odd, ``lo`` elsewhere; cell = size / checks texels, so check edges lie on
    texel edges and mip levels up to log2(cell) are exact checkers too.
    """
    if size % checks:
        raise ValueError(f"checker_texture: size {size} must be a multiple of checks {checks}")
    i = torch.arange(size) // (size // checks)
    board = ((i.view(-1, 1) + i.view(1, -1)) % 2).to(torch.float64)
    return (lo + (hi - lo) * board).expand(channels, size, size).unsqueeze(0).to(dtype).contiguous()


def _tri(x: Tensor) -> Tensor:
    """T(x) = integral_0^x s, s(t) = (-1)^floor(t): a triangle wave of period 2 between 0 and 1."""
    r = torch.remainder(x, 2.0)
    return torch.where(r < 1, r, 2 - r)


def _tri2(x: Tensor) -> Tensor:
    """integral_0^x T: one per period of 2, plus the in-period part (piecewise quadratic)."""
    r = torch.remainder(x, 2.0)
    part = torch.where(r < 1, 0.5 * r * r, 0.5 + 2 * (r - 1) - 0.5 * (r * r - 1))
    return torch.floor(x / 2.0) + part


def checker_footprint_mean(uv: Tensor, uv_dx: Tensor, uv_dy: Tensor, checks: int,
                           lo: float = 0.1, hi: float = 0.9) -> Tensor:
    """Exact mean of the ideal checker over each pixel's parallelogram footprint.

    The checker is ``c(u, v) = lo + (hi - lo) (1 - s(n u) s(n v)) / 2`` with
    ``s(t) = (-1)^floor(t)`` and n = checks per uv unit; the footprint is
    ``uv + a uv_dx + b uv_dy``, a, b uniform in [-1/2, 1/2] (the affine
    approximation of the pixel's preimage that the filters also use).  It
    requires ``uv_dx`` along u only (``uv_dx[..., 1] == 0``), which holds
    exactly for :func:`grazing_plane` (its camera only pitches).  In check
    units, with ``A = n du/dx``, ``B = n du/dy``, ``C = n dv/dy``:

        mean(s s) = int_b s(v0 + b C) Q(b) db,
        Q(b) = int_a s(u0 + b B + a A) da = [T(u0 + bB + A/2) - T(u0 + bB - A/2)] / A,

    with T the triangle wave (antiderivative of s).  s(v0 + bC) is constant
    between the b where v0 + bC is an integer, and on each such piece the
    integral of Q is closed form with T2 = int T:
    ``[T2(u0 + bB + A/2) - T2(u0 + bB - A/2)] / (A B)`` between its ends.
    Where |A| or |B| is tiny the limits (point sample in a, midpoint in b)
    are used, whose error is O(A^2), O(B^2).  Computed in float64.

    Args:
        uv, uv_dx, uv_dy: [B, H, W, 2] as returned by grazing_plane.
        checks: checker squares per uv unit (per texture repeat).

    Returns:
        [B, 1, H, W] float64 mean value (one channel; the checker is grey).
    """
    if float(uv_dx[..., 1].abs().max()) > 1e-9 * max(1.0, float(uv_dx.abs().max())):
        raise ValueError("checker_footprint_mean: uv_dx must run along u only (uv_dx[..., 1] == 0)")
    n = float(checks)
    u0, v0 = (uv[..., 0].double() * n), (uv[..., 1].double() * n)
    A = uv_dx[..., 0].double() * n
    Bq = uv_dy[..., 0].double() * n
    C = uv_dy[..., 1].double() * n
    # Break points of s(v0 + b C) in b: integers k strictly inside v0 +- |C|/2.
    kmin = torch.floor(v0 - C.abs() / 2) + 1
    K = int(torch.ceil(C.abs().max()).item()) + 2
    k = kmin.unsqueeze(-1) + torch.arange(K, dtype=torch.float64)
    Csafe = torch.where(C.abs() > 1e-12, C, torch.ones_like(C))
    bk = ((k - v0.unsqueeze(-1)) / Csafe.unsqueeze(-1)).clamp(-0.5, 0.5)
    bk = torch.where(C.abs().unsqueeze(-1) > 1e-12, bk, torch.full_like(bk, 0.5))
    ends = torch.cat([torch.full_like(bk[..., :1], -0.5), bk, torch.full_like(bk[..., :1], 0.5)], -1)
    ends, _ = torch.sort(ends, -1)
    b0, b1 = ends[..., :-1], ends[..., 1:]
    mid = 0.5 * (b0 + b1)
    sign = 1.0 - 2.0 * torch.remainder(torch.floor(v0.unsqueeze(-1) + mid * C.unsqueeze(-1)), 2.0)
    A_, B_, u_ = A.unsqueeze(-1), Bq.unsqueeze(-1), u0.unsqueeze(-1)
    smallA = A_.abs() < 1e-7
    Asafe = torch.where(smallA, torch.ones_like(A_), A_)

    def Q(b: Tensor) -> Tensor:
        x = u_ + b * B_
        sq = 1.0 - 2.0 * torch.remainder(torch.floor(x), 2.0)
        return torch.where(smallA, sq, (_tri(x + A_ / 2) - _tri(x - A_ / 2)) / Asafe)

    smallB = (B_ * (b1 - b0)).abs() < 1e-6
    Bsafe = torch.where(B_.abs() < 1e-300, torch.ones_like(B_), B_)

    def T2diff(b: Tensor) -> Tensor:
        x = u_ + b * B_
        return (_tri2(x + A_ / 2) - _tri2(x - A_ / 2)) / Asafe

    exact = (T2diff(b1) - T2diff(b0)) / Bsafe
    piece = torch.where(smallB | smallA, Q(mid) * (b1 - b0), exact)
    ss = (sign * piece).sum(-1)
    return (lo + (hi - lo) * (1 - ss) / 2).unsqueeze(1)


def checker_pixel_box_mean(res: int, pitch: float, fov_deg: float, checks: int, lo: float = 0.1,
                           hi: float = 0.9, strips: int = 16) -> Tensor:
    """Mean of the ideal checker over each pixel's true (screen-space box) footprint on the grazing plane.

    The camera of :func:`grazing_plane` only pitches, so along an image row
    v is constant and u affine in the column: a pixel's preimage is a
    trapezoid, and a horizontal strip of it ``1 / strips`` pixels tall is,
    up to the perspective curvature inside the strip (O(strips^-2)), the
    parallelogram at the strip's centre with the full pixel width.  Each
    strip is integrated exactly by :func:`checker_footprint_mean` and the
    strips averaged: exact along the row, no aliasing across check edges,
    only the smooth perspective term approximated.

    Returns:
        [1, 1, res, res] float64.
    """
    uv, dx, dy = grazing_plane(res, pitch, 1.0, fov_deg=fov_deg, ss=strips, dtype=torch.float64)
    n = strips
    # Strip centres at the pixel's centre column: the mean of the two middle
    # sub-columns (u is affine along a row); the strip's width is the whole
    # pixel (n sub-columns), its height one sub-row.
    mid = uv.view(1, res * n, res, n, 2)[:, :, :, n // 2 - 1:n // 2 + 1].mean(3)
    dxs = dx.view(1, res * n, res, n, 2)[:, :, :, 0] * n
    dys = dy.view(1, res * n, res, n, 2)[:, :, :, 0]
    m = checker_footprint_mean(mid, dxs, dys, checks, lo, hi)  # [1, 1, res * n, res]
    return m.view(1, 1, res, n, res).mean(3)


# --------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------


@dataclass
class Scene:
    """One test image: the lookups every method needs, and its reference."""

    name: str
    texture: Tensor                      # [1, C, Ht, Wt]
    wrap: tuple[str, str]
    uv: Tensor                           # [1, R, R, 2]
    uv_dx: Tensor
    uv_dy: Tensor
    uv_ss: dict[int, Tensor]             # n -> [1, nR, nR, 2] supersampled uv (n = 2, 4, 8)
    reference: Tensor                    # [1, C or 1, R, R]
    mask: Tensor                         # [1, 1, R, R] bool, pixels that are scored
    reference_kind: str = "16x16 supersampled bilinear"
    extra: dict = field(default_factory=dict)


def load_spot_texture() -> Tensor:
    """The spot texture [1, 3, 1024, 1024] in [0, 1]."""
    return difftex.load_texture(ROOT / "data" / "spot" / "spot_texture.png")


def _ss_reference(texture: Tensor, uv16: Tensor, wrap: tuple[str, str]) -> Tensor:
    """Box average of 16 x 16 bilinear level-0 samples a pixel, in chunks of rows (memory)."""
    with torch.no_grad():
        rows = []
        for chunk in torch.split(uv16, 256, dim=1):
            rows.append(F.avg_pool2d(difftex.sample(texture, chunk, filter="bilinear", wrap=wrap), 16))
        return torch.cat(rows, 2)


def plane_fov(pitch: float) -> float:
    """Field of view that keeps the top image edge 2 degrees below the horizon (36 at most)."""
    return min(36.0, 2.0 * (pitch - 2.0)) if pitch < 20 else 36.0


def plane_scene(pitch: float, texture_kind: str, res: int, ss_rates=(2, 4, 8)) -> Scene:
    """Ground plane ``pitch`` degrees below the horizon; ``texture_kind`` "checker" or "spot"."""
    fov = plane_fov(pitch)
    uv, dx, dy = grazing_plane(res, pitch, 1.0, fov_deg=fov)
    uv_ss = {n: grazing_plane(res, pitch, 1.0, fov_deg=fov, ss=n)[0] for n in ss_rates}
    wrap = ("repeat", "repeat")
    if texture_kind == "checker":
        tex = checker_texture(**CHECKER)
        ref = checker_pixel_box_mean(res, pitch, fov, CHECKER["checks"], CHECKER["lo"], CHECKER["hi"]).float()
        ref = ref.expand(1, 3, res, res)
        kind = "closed form (ideal checker over the pixel's trapezoid, 16 exact strips)"
        # How far the usual 16x16 reference and the parallelogram footprint
        # that the filters assume are from it (reported, not methods).
        ss16 = _ss_reference(tex, grazing_plane(res, pitch, 1.0, fov_deg=fov, ss=16)[0], wrap)
        par = checker_footprint_mean(*grazing_plane(res, pitch, 1.0, fov_deg=fov, dtype=torch.float64),
                                     CHECKER["checks"], CHECKER["lo"], CHECKER["hi"]).float()
        extra = {"ss16_psnr": _psnr(ss16, ref), "parallelogram_psnr": _psnr(par.expand_as(ref), ref)}
    else:
        tex = load_spot_texture()
        ref = _ss_reference(tex, grazing_plane(res, pitch, 1.0, fov_deg=fov, ss=16)[0], wrap)
        kind = "16x16 supersampled bilinear"
        extra = {}
    mask = torch.ones(1, 1, res, res, dtype=torch.bool)
    return Scene(f"plane-{texture_kind}-{pitch:g}", tex, wrap, uv, dx, dy, uv_ss, ref, mask, kind, extra)


def icosphere(subdivisions: int = 4) -> tuple[Tensor, Tensor]:
    """Unit icosphere (trimesh): positions [V, 3] float32, faces [F, 3] int64, counter-clockwise outside."""
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.int64)


def sphere_uv(mvp: Tensor, res: int | tuple[int, int], verts: Tensor, faces: Tensor,
              derivatives: str = "analytic") -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rasterize the sphere at ``res`` (R, or (rows, columns)) and map it: (uv, uv_dx, uv_dy, mask [1, 1, R, R]).

    ``derivatives="analytic"`` chains the interpolated position derivatives
    through spherical_uv's Jacobian (continuous across the atan2 seam);
    ``"finite"`` takes forward differences of uv between neighbouring pixels,
    the naive alternative that jumps by a whole texture at the seam
    (stability.py shows the difference).
    """
    pos = camera.transform(verts, mvp.unsqueeze(0))
    frags = difftex.rasterize(pos, faces, (res, res) if isinstance(res, int) else tuple(res))
    p, pdx, pdy = difftex.interpolate(verts, faces, frags, derivatives=True)
    uv, dx, dy = difftex.spherical_uv(p, points_dx=pdx, points_dy=pdy)
    mask = frags.mask.unsqueeze(1)
    if derivatives == "finite":
        dx = torch.cat([uv[:, :, 1:] - uv[:, :, :-1], uv[:, :, -1:] - uv[:, :, -2:-1]], 2)
        dy = torch.cat([uv[:, 1:] - uv[:, :-1], uv[:, -1:] - uv[:, -2:-1]], 1)
    m = mask.squeeze(1).unsqueeze(-1)
    return uv * m, dx * m, dy * m, mask


SPHERE_DIR = (-1.0, -0.55, 0.75)  # eye direction: the seam (-x) faces the camera, +z pole in view


def sphere_mvp(minification: float, res: int, tex_h: int, fov_deg: float = 40.0,
               direction=SPHERE_DIR) -> Tensor:
    """World -> clip of a camera looking at the unit sphere so that its front point is ``minification`` texels a pixel.

    At the front point the spherical map runs tex_h / pi texels a radian
    along v (twice the rate along u), and a pixel there spans
    (d - 1) * 2 tan(fov / 2) / res world units, d the centre distance.
    """
    t = 2 * math.tan(math.radians(fov_deg) / 2)
    d = 1.0 + minification * math.pi * res / (tex_h * t)
    e = torch.tensor(direction, dtype=torch.float32)
    eye = e / e.norm() * d
    near = max(1e-3, 0.5 * (d - 1.0))
    proj = camera.perspective(fov_deg, 1.0, near, d + 2.0, degrees=True)
    return proj @ camera.look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))


def _full_coverage(masks: dict[int, Tensor], mask1: Tensor) -> Tensor:
    """Pixels covered at one sample and fully covered at every supersampling rate."""
    out = mask1.clone()
    for n, m in masks.items():
        out &= F.avg_pool2d(m.float(), n) > 1 - 1e-6
    return out


def sphere_scene(minification: float, res: int, ss_rates=(2, 4, 8), texture: Optional[Tensor] = None) -> Scene:
    """The textured icosphere at the given minification of its front point."""
    tex = checker_noise_texture(1024) if texture is None else texture
    verts, faces = icosphere(4)
    mvp = sphere_mvp(minification, res, tex.shape[-2])
    uv, dx, dy, mask1 = sphere_uv(mvp, res, verts, faces)
    uv_ss, masks = {}, {}
    for n in tuple(ss_rates) + (16,):
        u, _, _, m = sphere_uv(mvp, res * n, verts, faces)
        uv_ss[n], masks[n] = u, m
    wrap = ("repeat", "clamp")
    ref = _ss_reference(tex, uv_ss.pop(16), wrap)
    return Scene(f"sphere-{minification:g}x", tex, wrap, uv, dx, dy, uv_ss, ref, _full_coverage(masks, mask1))


def spot_mvp(dist: float, direction) -> Tensor:
    """World -> clip of a camera ``dist`` units from spot's centre along ``direction``, fov 40."""
    at = torch.tensor([0.0, 0.1, 0.2])
    e = torch.tensor(direction, dtype=torch.float32)
    eye = at + e / e.norm() * dist
    proj = camera.perspective(40.0, 1.0, 0.05, dist + 5.0, degrees=True)
    return proj @ camera.look_at(eye, at, torch.tensor([0.0, 1.0, 0.0]))


def spot_scene(dist: float, direction, res: int, ss_rates=(2, 4, 8)) -> Scene:
    """The spot mesh and texture seen from ``direction`` at ``dist`` units (raw pipeline)."""
    mesh = difftex.load_mesh(ROOT / "data" / "spot" / "spot_triangulated.obj")
    tex = load_spot_texture()
    mvp = spot_mvp(dist, direction)
    pos = camera.transform(mesh.positions, mvp.unsqueeze(0))

    def lookup(r: int):
        frags = difftex.rasterize(pos, mesh.faces, (r, r))
        uv, dx, dy = difftex.interpolate(mesh.uv, mesh.faces, frags, derivatives=True, attr_faces=mesh.uv_faces)
        return uv, dx, dy, frags.mask.unsqueeze(1)

    uv, dx, dy, mask1 = lookup(res)
    uv_ss, masks = {}, {}
    for n in tuple(ss_rates) + (16,):
        u, _, _, m = lookup(res * n)
        uv_ss[n], masks[n] = u, m
    wrap = ("clamp", "clamp")
    ref = _ss_reference(tex, uv_ss.pop(16), wrap)
    return Scene(f"spot-{dist:g}", tex, wrap, uv, dx, dy, uv_ss, ref, _full_coverage(masks, mask1))


def build_scenes(res: int, which: str = "all", ss_rates=(2, 4, 8)) -> list[Scene]:
    """Every scene of the experiment (``which``: "all", "plane", "sphere" or "spot").

    ``ss_rates``: the supersampled uv the peers need (none for difftex's filters alone).
    """
    scenes: list[Scene] = []
    if which in ("all", "plane"):
        for kind in ("checker", "spot"):
            scenes += [plane_scene(p, kind, res, ss_rates) for p in PITCHES]
    if which in ("all", "sphere"):
        scenes += [sphere_scene(m, res, ss_rates) for m in SPHERE_MINIFICATION]
    if which in ("all", "spot"):
        scenes += [spot_scene(d, e, res, ss_rates) for d, e in SPOT_VIEWS]
    return scenes


# --------------------------------------------------------------------------
# methods
# --------------------------------------------------------------------------


def _pad_and_grid(tex: Tensor, uv: Tensor, wrap: tuple[str, str]) -> tuple[Tensor, Tensor]:
    """Texture and grid_sample grid that read it like difftex's wrap modes (with padding_mode="border").

    Clamp is grid_sample's "border" as it is; repeat needs a one-texel
    circular pad along that axis and uv folded into [0, 1) (then exact).
    The grid is in the (padded) texture's normalized coordinates,
    align_corners=False.
    """
    H, W = tex.shape[-2:]
    pu, pv = (1 if w == "repeat" else 0 for w in wrap)
    padded = F.pad(tex, (pu, pu, pv, pv), mode="circular") if pu or pv else tex
    fold = torch.stack([uv[..., i] - torch.floor(uv[..., i]) if wrap[i] == "repeat" else uv[..., i]
                        for i in range(2)], -1)
    grid = (fold * uv.new_tensor([W, H]) + uv.new_tensor([pu, pv])) / uv.new_tensor([W + 2 * pu, H + 2 * pv]) * 2 - 1
    return padded, grid


def grid_sample_lookup(tex: Tensor, uv: Tensor, wrap: tuple[str, str]) -> Tensor:
    """F.grid_sample bilinear with difftex's wrap, [1, C, h, w]."""
    padded, grid = _pad_and_grid(tex, uv, wrap)
    return F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=False)


def kornia_lookup(tex: Tensor, uv: Tensor, wrap: tuple[str, str]) -> Tensor:
    """kornia.geometry.transform.remap with normalized coordinates, align_corners=False."""
    from kornia.geometry.transform import remap
    padded, grid = _pad_and_grid(tex, uv, wrap)
    return remap(padded, grid[..., 0], grid[..., 1], mode="bilinear", padding_mode="border",
                 align_corners=False, normalized_coordinates=True)


def method_names(ss_rates=(2, 4, 8)) -> list[str]:
    """Every method of the experiment; "auto" only where difftex.sample has it."""
    names = ["nearest", "bilinear", "bicubic", "trilinear"]
    names += [f"anisotropic-{a}" for a in (2, 4, 8, 16)]
    names += ["ewa"]
    if "auto" in getattr(_sample_mod, "FILTERS", ()):
        names.append("auto")
    names += ["grid_sample"] + [f"grid_sample-ss{n}x{n}" for n in ss_rates] + ["kornia"]
    return names


def make_method(name: str, scene: Scene, tex: Tensor, uv: Tensor, uv_ss: dict[int, Tensor]) -> Callable[[], Tensor]:
    """A closure that renders ``scene`` with ``name`` from the leaf tensors given (for gradients)."""
    w = scene.wrap
    dx, dy = scene.uv_dx, scene.uv_dy
    if name in ("nearest", "bilinear", "bicubic"):
        return lambda: difftex.sample(tex, uv, filter=name, wrap=w)
    if name in ("trilinear", "ewa", "auto"):
        return lambda: difftex.sample(tex, uv, filter=name, wrap=w, uv_dx=dx, uv_dy=dy)
    if name.startswith("anisotropic-"):
        a = int(name.split("-")[1])
        return lambda: difftex.sample(tex, uv, filter="anisotropic", wrap=w, uv_dx=dx, uv_dy=dy, max_aniso=a)
    if name == "grid_sample":
        return lambda: grid_sample_lookup(tex, uv, w)
    if name.startswith("grid_sample-ss"):
        n = int(name.split("ss")[1].split("x")[0])
        return lambda: F.avg_pool2d(grid_sample_lookup(tex, uv_ss[n], w), n)
    if name == "kornia":
        return lambda: kornia_lookup(tex, uv, w)
    raise ValueError(f"unknown method {name!r}")


# --------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------


def masked_psnr(img: Tensor, ref: Tensor, mask: Tensor) -> float:
    """PSNR (peak 1) over the scored pixels, all channels."""
    m = mask.expand_as(img)
    ref = ref.expand_as(img)
    return _psnr(torch.where(m, img, ref), torch.where(m, ref, torch.full_like(ref, float("nan"))))


def flip_error(img: Tensor, ref: Tensor, mask: Tensor) -> Optional[float]:
    """Mean LDR-FLIP over the scored pixels (unscored ones are set to the reference), or None."""
    if _flip is None:
        return None
    m = mask.expand_as(img)
    ref = ref.expand_as(img)
    test = torch.where(m, img, ref)
    to_np = lambda t: np.ascontiguousarray(t[0].permute(1, 2, 0).clamp(0, 1).double().numpy().astype(np.float32))
    emap, _, _ = _flip.evaluate(to_np(ref), to_np(test), "LDR", applyMagma=False)
    emap = np.asarray(emap)
    if emap.ndim == 3:
        emap = emap[..., 0]
    return float(emap[mask[0, 0].numpy()].mean())


def error_image(img: Tensor, ref: Tensor, mask: Tensor) -> Tensor:
    """[R, R] mean absolute error over channels, 0 outside the mask."""
    e = (img - ref.expand_as(img)).abs().mean(1)[0]
    return torch.where(mask[0, 0], e, torch.zeros_like(e))


# --------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------


def run_scene(scene: Scene, methods: list[str], repeats: int) -> tuple[list[dict], dict[str, Tensor]]:
    """Scores and medians of fwd / fwd+bwd for every method, timed round-robin (shuffled each round)."""
    tex = scene.texture.clone().requires_grad_(True)
    uv = scene.uv.clone().requires_grad_(True)
    uv_ss = {n: u.clone().requires_grad_(True) for n, u in scene.uv_ss.items()}
    fns = {m: make_method(m, scene, tex, uv, uv_ss) for m in methods}
    leaves = [tex, uv, *uv_ss.values()]
    images: dict[str, Tensor] = {}
    rows = []
    for m, fn in fns.items():
        with torch.no_grad():
            images[m] = fn()
    times: dict[str, tuple[list[float], list[float]]] = {m: ([], []) for m in methods}
    order = list(fns)
    rng = random.Random(0)
    for rep in range(repeats + 1):  # round 0 warms up (allocator, lazy imports) and is dropped
        # A new order each round: a method timed right after a heavy one (EWA, 8x8) finds its
        # data evicted from the caches (measured: auto, which followed EWA, read up to 1.37x
        # anisotropic-16's forward on the small scenes, against 1.02x when timed alone).
        rng.shuffle(order)
        for m in order:
            fn = fns[m]
            t0 = time.perf_counter()
            with torch.no_grad():
                fn()
            t1 = time.perf_counter()
            for leaf in leaves:
                leaf.grad = None
            fn().sum().backward()
            t2 = time.perf_counter()
            if rep:
                times[m][0].append((t1 - t0) * 1e3)
                times[m][1].append((t2 - t1) * 1e3)
    for m in methods:
        img = images[m]
        rows.append(dict(scene=scene.name, method=m, psnr=masked_psnr(img, scene.reference, scene.mask),
                         flip=flip_error(img, scene.reference, scene.mask),
                         fwd_ms=statistics.median(times[m][0]), fwdbwd_ms=statistics.median(times[m][1])))
    return rows, images


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points (time, psnr) that no other point beats in both (faster and at least as accurate)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -math.inf
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


FAMILIES = (("plane-checker", "plane, checker (closed form)"), ("plane-spot", "plane, spot texture"),
            ("sphere", "sphere (spherical_uv)"), ("spot-", "spot mesh"))


def _method_style(methods: list[str]) -> dict[str, tuple]:
    import matplotlib.pyplot as plt
    cmap = plt.get_cmap("tab20")
    return {m: cmap(i % 20) for i, m in enumerate(methods)}


def _labels(ax, pts: list[tuple[float, float]], names: list[str]) -> None:
    """Method names next to their points, nudged vertically so that no two overlap (log x axis)."""
    xs = [math.log10(t) for t, _ in pts]
    ys = [p for _, p in pts]
    xr = (max(xs) - min(xs)) or 1.0
    yr = (max(ys) - min(ys)) or 1.0
    placed: list[tuple[float, float, float]] = []  # (x0, x1, y) in axis fractions
    for i in sorted(range(len(pts)), key=lambda i: -ys[i]):
        x0 = (xs[i] - min(xs)) / xr
        w = 0.011 * len(names[i]) * 1.2
        y = (ys[i] - min(ys)) / yr
        h = 0.045
        while any(abs(y - py) < h and x0 < px1 and px0 < x0 + w for px0, px1, py in placed):
            y -= h / 2
        placed.append((x0, x0 + w, y))
        yd = min(ys) + y * yr
        ax.annotate(names[i], (pts[i][0], ys[i]), xytext=(pts[i][0] * 1.08, yd), fontsize=9, va="center",
                    arrowprops=dict(arrowstyle="-", color="0.6", lw=0.5) if abs(yd - ys[i]) > 0.02 * yr else None)


def _log_axis(ax) -> None:
    """Log x axis with plain-number major labels only (minor labels overlap)."""
    import matplotlib.ticker as mt
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(mt.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(mt.NullFormatter())


def plot_chart(rows: list[dict], methods: list[str], path: Path) -> None:
    """PSNR against fwd+bwd time: one overall panel (mean over scenes) and one per scene family."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    colors = _method_style(methods)
    markers = "os^Dvp*hX"
    fig, axes = plt.subplots(2, 3, figsize=(18, 11))
    # Overall panels: per method, mean PSNR and median time over all scenes.
    for ax, key, title in ((axes[0, 0], "fwd_ms", "mean over all scenes: forward"),
                           (axes[0, 1], "fwdbwd_ms", "mean over all scenes: forward + backward")):
        pts = []
        for m in methods:
            rs = [r for r in rows if r["method"] == m and math.isfinite(r["psnr"])]
            pts.append((statistics.median(r[key] for r in rs), statistics.mean(r["psnr"] for r in rs)))
        for (t, p), m in zip(pts, methods):
            ax.scatter(t, p, color=colors[m], s=60, zorder=3, edgecolor="k", linewidth=0.5)
        _labels(ax, pts, methods)
        front = pareto(pts)
        ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "k--", lw=1, zorder=2, label="Pareto front")
        _log_axis(ax)
        ax.set_xlabel(f"median {'forward' if key == 'fwd_ms' else 'forward + backward'} time over scenes (ms, log)")
        ax.set_ylabel("mean PSNR over scenes (dB)")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="lower right", fontsize=9)
    panels = [axes[0, 2], axes[1, 0], axes[1, 1], axes[1, 2]]
    for ax, (prefix, title) in zip(panels, FAMILIES):
        scenes = [s for s in dict.fromkeys(r["scene"] for r in rows) if s.startswith(prefix)]
        if not scenes:
            ax.set_visible(False)
            continue
        for si, s in enumerate(scenes):
            rs = [r for r in rows if r["scene"] == s]
            pts = [(r["fwdbwd_ms"], r["psnr"]) for r in rs]
            for r in rs:
                ax.scatter(r["fwdbwd_ms"], r["psnr"], color=colors[r["method"]], marker=markers[si % len(markers)],
                           s=40, edgecolor="k", linewidth=0.4, zorder=3)
            front = sorted(pareto(pts), key=lambda i: pts[i][0])
            ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "-", color="0.4", lw=0.8, zorder=2)
            ax.scatter([], [], marker=markers[si % len(markers)], color="w", edgecolor="k", label=s)
        _log_axis(ax)
        ax.set_xlabel("forward + backward time (ms, log)")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(f"{title}; grey: Pareto front per scene")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="lower right", title="scene (marker)", title_fontsize=8)
    handles = [plt.Line2D([], [], marker="o", ls="", color=colors[m], markeredgecolor="k", label=m) for m in methods]
    fig.legend(handles=handles, loc="lower center", ncol=len(methods) // 2 + 1, fontsize=10, title="method (colour)")
    fig.suptitle("difftex speed vs accuracy (time of the texture lookup only; higher and further left is better)",
                 fontsize=14)
    fig.tight_layout(rect=(0, 0.07, 1, 0.96))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_error_grid(scenes: list[Scene], images: dict[str, dict[str, Tensor]], methods: list[str], path: Path) -> None:
    """Rows: a few scenes (reference image, then |method - reference| per method); shared colour scale."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cols = ["reference"] + methods
    fig, axes = plt.subplots(len(scenes), len(cols), figsize=(1.45 * len(cols), 1.6 * len(scenes) + 0.6),
                             squeeze=False)
    vmax = 0.25
    for i, sc in enumerate(scenes):
        for j, c in enumerate(cols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if c == "reference":
                ref = sc.reference.expand(1, 3, *sc.reference.shape[-2:])
                ref = torch.where(sc.mask.expand_as(ref), ref, torch.zeros_like(ref))
                ax.imshow(ref[0].permute(1, 2, 0).clamp(0, 1).numpy())
                ax.set_ylabel(sc.name, fontsize=9)
            else:
                e = error_image(images[sc.name][c], sc.reference, sc.mask)
                im = ax.imshow(e.numpy(), cmap="magma", vmin=0, vmax=vmax)
            if i == 0:
                ax.set_title(c.replace("grid_sample-", "gs ").replace("anisotropic-", "aniso "), fontsize=9)
    fig.colorbar(im, ax=axes, orientation="horizontal", fraction=0.03, pad=0.02,
                 label=f"mean |error| over channels (clipped at {vmax})")
    fig.savefig(path, dpi=80, bbox_inches="tight")
    plt.close(fig)


def summary_markdown(rows: list[dict], methods: list[str], meta: str) -> str:
    """Table of PSNR per scene family plus mean, and median times, per method."""
    fams = [(p, t) for p, t in FAMILIES]
    head = "| method | " + " | ".join(t for _, t in fams) + " | mean PSNR | FLIP (mean) | fwd ms | fwd+bwd ms |"
    lines = [meta, "", "PSNR in dB (mean over the scenes of the family), time: median over all scenes.", "",
             head, "| --- |" + " ---: |" * (len(fams) + 4)]
    for m in methods:
        rs = [r for r in rows if r["method"] == m]
        cells = []
        for p, _ in fams:
            v = [r["psnr"] for r in rs if r["scene"].startswith(p)]
            cells.append(f"{statistics.mean(v):.2f}" if v else "-")
        flips = [r["flip"] for r in rs if r["flip"] is not None]
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {statistics.mean(r['psnr'] for r in rs):.2f} | "
                     + (f"{statistics.mean(flips):.4f}" if flips else "n/a")
                     + f" | {statistics.median(r['fwd_ms'] for r in rs):.2f} | "
                       f"{statistics.median(r['fwdbwd_ms'] for r in rs):.2f} |")
    lines += ["", "Per scene (PSNR dB / fwd+bwd ms):", ""]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    lines.append("| method | " + " | ".join(scenes) + " |")
    lines.append("| --- |" + " ---: |" * len(scenes))
    for m in methods:
        cell = {r["scene"]: r for r in rows if r["method"] == m}
        lines.append(f"| {m} | " + " | ".join(f"{cell[s]['psnr']:.1f} / {cell[s]['fwdbwd_ms']:.0f}"
                                            for s in scenes) + " |")
    return "\n".join(lines)


# The part of docs/speed_vs_accuracy.md that --docs rewrites; the prose around it is kept.
_DOC_START = "<!-- generated by experiments/speed_vs_accuracy.py --docs: start -->"
_DOC_END = "<!-- generated: end -->"


def main(argv: Optional[list[str]] = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=5, help="timed rounds per scene (after one warm-up round)")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1: steadiest on a "
                    "shared machine; 0 keeps torch's default)")
    ap.add_argument("--scenes", default="all", choices=("all", "plane", "sphere", "spot"))
    ap.add_argument("--out", default="results/speed_vs_accuracy")
    ap.add_argument("--docs", action="store_true", help="also write docs/speed_vs_accuracy.md and docs/images/*.png")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    t_start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    methods = method_names()
    scenes = build_scenes(args.res, args.scenes)
    t_scenes = time.perf_counter() - t_start
    print(f"{len(scenes)} scenes built in {t_scenes:.1f} s; methods: {', '.join(methods)}; "
          f"FLIP {'available' if _flip is not None else 'not installed: column left empty'}", flush=True)
    rows: list[dict] = []
    images: dict[str, dict[str, Tensor]] = {}
    for sc in scenes:
        t0 = time.perf_counter()
        r, imgs = run_scene(sc, methods, args.repeats)
        rows += r
        images[sc.name] = imgs
        best = max(r, key=lambda x: x["psnr"])
        print(f"{sc.name:22s} ({time.perf_counter() - t0:5.1f} s, {int(sc.mask.sum())} px scored, "
              f"ref: {sc.reference_kind}) best {best['method']} {best['psnr']:.2f} dB", flush=True)
        if "ss16_psnr" in sc.extra:
            print(f"    (vs the closed form: 16x16 supersampled bilinear {sc.extra['ss16_psnr']:.2f} dB, "
                  f"ideal checker over the parallelogram footprint {sc.extra['parallelogram_psnr']:.2f} dB)")
        for x in r:
            fl = f"{x['flip']:.4f}" if x["flip"] is not None else "  n/a "
            print(f"    {x['method']:20s} {x['psnr']:7.2f} dB  FLIP {fl}  fwd {x['fwd_ms']:8.2f} ms  "
                  f"fwd+bwd {x['fwdbwd_ms']:8.2f} ms", flush=True)
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["scene", "method", "psnr", "flip", "fwd_ms", "fwdbwd_ms"])
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else (f"{v:.4f}" if isinstance(v, float) else v)) for k, v in r.items()})
    plot_chart(rows, methods, out / "speed_vs_accuracy.png")
    grid_names = [n for n in ("plane-checker-15", "plane-spot-5", "sphere-25x", "spot-5") if n in images]
    grid_scenes = [s for s in scenes if s.name in grid_names] or scenes[:3]
    plot_error_grid(grid_scenes, images, methods, out / "error_grid.png")
    total = time.perf_counter() - t_start
    meta = (f"{args.res}x{args.res} images, {len(scenes)} scenes, medians of {args.repeats} shuffled round-robin rounds, "
            f"{torch.get_num_threads()} thread(s), torch {torch.__version__}, {platform.machine()}, "
            f"{os.cpu_count()} CPUs (shared: timings are noisy); FLIP: "
            f"{'flip-evaluator (LDR, 67 ppd)' if _flip is not None else 'not installed'}; total run {total:.0f} s.")
    md = summary_markdown(rows, methods, meta)
    ss16 = [f"{s.name} {s.extra['ss16_psnr']:.1f} / {s.extra['parallelogram_psnr']:.1f} dB"
            for s in scenes if "ss16_psnr" in s.extra]
    if ss16:
        md += ("\n\nAgainst the checker's closed form, the 16x16 supersampled bilinear render of the texel "
               "image (the reference of the other scenes) / the ideal checker over the parallelogram "
               "footprint that the filters assume: " + ", ".join(ss16) + ".")
    (out / "summary.md").write_text(md + "\n")
    print()
    print(md)
    if args.docs:
        img_dir = ROOT / "docs" / "images"
        img_dir.mkdir(parents=True, exist_ok=True)
        shutil.copy(out / "speed_vs_accuracy.png", img_dir / "speed_vs_accuracy.png")
        shutil.copy(out / "error_grid.png", img_dir / "error_grid.png")
        doc = ROOT / "docs" / "speed_vs_accuracy.md"
        head, rest = doc.read_text().split(_DOC_START + "\n", 1)
        doc.write_text(head + _DOC_START + "\n" + md + "\n" + _DOC_END + rest.split(_DOC_END, 1)[1])
    print(f"\nwritten to {out} in {total:.0f} s")
    return rows


if __name__ == "__main__":
    main()

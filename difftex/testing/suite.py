"""The scene suite of the speed-vs-accuracy study, shared with bench_auto, stability and the filter tests.

Scenes (every image ``res`` x ``res``):

* ``plane-checker-P`` / ``plane-spot-P``: the ground plane of
  :func:`~difftex.testing.scenes.grazing_plane` seen ``P`` degrees below the
  horizon, textured with an exact 512^2 checkerboard (reference: its closed
  form, :func:`~difftex.testing.references.checker_pixel_box_mean`) or the
  spot texture, ``repeat``;
* ``sphere-Mx``: a unit icosphere rasterized and mapped by
  :func:`difftex.mapping.spherical_uv` (analytic derivatives) at the
  distance where its front point is minified ``M`` texels a pixel;
* ``spot-D``: the spot mesh and texture at distance ``D``.

Other references are 16 x 16 supersampled bilinear
(:func:`~difftex.testing.references.supersampled`); mesh scenes are scored
on the pixels every supersampling rate covers fully.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor

import difftex
from difftex import camera
from difftex.metrics import psnr

from .meshes import icosphere, spot_mesh, spot_texture
from .references import checker_footprint_mean, checker_pixel_box_mean, supersampled
from .scenes import checker_noise_texture, checker_texture, grazing_plane

PITCHES = (90.0, 60.0, 30.0, 15.0, 5.0)
SPHERE_MINIFICATION = (0.5, 5.0, 25.0, 100.0)
SPOT_VIEWS = ((1.6, (1.0, 0.4, 1.0)), (5.0, (-1.0, 0.3, 0.6)), (14.0, (0.3, 0.8, -1.0)))
CHECKER = dict(size=512, checks=32, lo=0.1, hi=0.9)


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
        ss16 = supersampled(tex, grazing_plane(res, pitch, 1.0, fov_deg=fov, ss=16)[0], 16, wrap)
        par = checker_footprint_mean(*grazing_plane(res, pitch, 1.0, fov_deg=fov, dtype=torch.float64),
                                     CHECKER["checks"], CHECKER["lo"], CHECKER["hi"]).float()
        extra = {"ss16_psnr": psnr(ss16, ref), "parallelogram_psnr": psnr(par.expand_as(ref), ref)}
    else:
        tex = spot_texture()
        ref = supersampled(tex, grazing_plane(res, pitch, 1.0, fov_deg=fov, ss=16)[0], 16, wrap)
        kind = "16x16 supersampled bilinear"
        extra = {}
    mask = torch.ones(1, 1, res, res, dtype=torch.bool)
    return Scene(f"plane-{texture_kind}-{pitch:g}", tex, wrap, uv, dx, dy, uv_ss, ref, mask, kind, extra)


def sphere_uv(mvp: Tensor, res: int | tuple[int, int], verts: Tensor, faces: Tensor,
              derivatives: str = "analytic") -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rasterize the sphere at ``res`` (R, or (rows, columns)) and map it: (uv, uv_dx, uv_dy, mask [1, 1, R, R]).

    ``derivatives="analytic"`` chains the interpolated position derivatives
    through spherical_uv's Jacobian (continuous across the atan2 seam);
    ``"finite"`` takes forward differences of uv between neighbouring pixels,
    the naive alternative that jumps by a whole texture at the seam
    (experiments/studies/stability.py shows the difference).
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
    ref = supersampled(tex, uv_ss.pop(16), 16, wrap)
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
    mesh = spot_mesh()
    tex = spot_texture()
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
    ref = supersampled(tex, uv_ss.pop(16), 16, wrap)
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

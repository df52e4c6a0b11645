"""Gallery: every texture technique of the seed notes rendered with difftex, in one labelled PNG.

Rows (each tile ``--tile`` pixels square, rasterized with ``difftex.rasterize``, attributes and their
screen-space derivatives from ``difftex.interpolate``, every texture read with a mip filter of
``difftex.sample`` / ``difftex.envmap``):

1-3. the mappings of the seed notes (planar, cylindrical, spherical, box, normal-vector projection and the
     mesh's own uv) on a sphere, a cylinder (``trimesh.creation.cylinder``) and spot, textured with a checker
     tinted by u (red) and v (green) so that the orientation, seams and distortion show.  The planar /
     cylindrical / spherical / box / normal uv are computed per pixel with analytic derivatives (no seam
     line); "own uv" is the mesh's per-vertex uv interpolated across triangles: the sphere's is the
     spherical map at its vertices (seam split), the cylinder has none, so its per-vertex cylindrical uv (seam
     turned to the camera) is smeared across the seam triangles, which is what the per-pixel mappings avoid.
4.   spot with its texture: "replace" (the texel colour) and "modulate" (texture x Blinn-Phong with two
     lights), the Blinn-Phong shading alone, the solid textures marble and wood (``difftex.noise``,
     evaluated at each pixel's object-space point), and the marble baked into a 2D texture (``difftex.bake``).
5.   a sphere under one procedural height map (bumps, ``--bumps`` periods around): smooth (no map),
     bump-mapped (``difftex.bump``: slope of the trilinear-filtered height), normal-mapped (a tangent-space
     normal map derived from the same height by central differences), displacement-mapped (vertices moved by
     ``difftex.displace``, normals recomputed), and a mirror sphere in the Venice-sunset HDR: the view vector
     reflected about the normal, with its derivatives, looked up in a cube map (``equirect_to_cube``,
     trilinear) and in the latitude-longitude map itself (anisotropic); the background is the map seen
     along each pixel's ray.

    python -m experiments.gallery [--tile 160] [--out docs/images/gallery.png]

:func:`main` returns a summary (per-tile images and the numbers the test checks).
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Callable, NamedTuple, Optional

import numpy as np
import torch
from torch import Tensor

import difftex
from difftex import camera
from difftex.geometry.mesh import unit, vertex_normals
from difftex.io.files import data_path
from difftex.shading import blinn_phong, bump, combine, displace, normal_map, tangent_frames
from difftex.testing.meshes import spot_mesh, spot_texture
from difftex.testing.scenes import checker_texture

COLS = 6
BACKGROUND = 0.94
FOV = 36.0
# Two lights (key and fill) as directions towards them, z-up world; and the shading's constants.
LIGHTS = torch.tensor([[0.5, -0.6, 0.7], [-0.8, -0.3, 0.2]])
LIGHT_COLORS = torch.tensor([[0.85], [0.3]])
AMBIENT = 0.25
# The z-up scenes' camera: front-right, a little above (the spherical seam, on -x, stays behind).
EYE = (2.1, -2.5, 1.35)
# The mirror sphere's camera: y up as the environment map, looking along -z (the panorama's centre).
ENV_EYE = (0.0, 0.35, 3.3)
ENV_FOV = 40.0
ENV_EXPOSURE = 0.6
MAX_ANISO = 8


class View(NamedTuple):
    """One rasterized view: fragments, the camera position and the mask [1, H, W]."""

    frags: difftex.Fragments
    eye: Tensor
    mask: Tensor


# ---------------------------------------------------------------- meshes

def latlong_sphere(segments: int = 96, rings: int = 48) -> difftex.Mesh:
    """A unit sphere (z up) whose own uv is the spherical map of its vertices, split at the -x seam.

    Positions are shared (one vertex per pole); uv are face-varying, ``(i / segments, j / rings)`` on the
    grid, so the seam column u = 0 / 1 and the poles have one uv per adjacent face. Faces are
    counter-clockwise seen from outside.
    """
    i = torch.arange(segments + 1, dtype=torch.float64)
    j = torch.arange(rings + 1, dtype=torch.float64)
    uu, vv = torch.meshgrid(i / segments, j / rings, indexing="xy")  # [rings + 1, segments + 1]
    uv = torch.stack([uu, vv], -1).reshape(-1, 2)
    # difftex.spherical_uv: u = (phi + pi) / 2pi, v = theta / pi from +z.
    phi, theta = 2 * math.pi * i / segments - math.pi, math.pi * j / rings
    ring_pos = [torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)]
    for t in theta[1:-1]:
        ring_pos.append(torch.stack([torch.sin(t) * torch.cos(phi[:-1]), torch.sin(t) * torch.sin(phi[:-1]),
                                     torch.cos(t).expand(segments)], -1))
    ring_pos.append(torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64))
    pos = torch.cat(ring_pos)

    def p_index(ci: int, cj: int) -> int:
        if cj == 0:
            return 0
        if cj == rings:
            return pos.shape[0] - 1
        return 1 + (cj - 1) * segments + ci % segments

    faces, uv_faces = [], []
    for cj in range(rings):
        for ci in range(segments):
            corners = [(ci, cj), (ci + 1, cj), (ci + 1, cj + 1), (ci, cj + 1)]
            tris = [(0, 2, 1), (0, 3, 2)]
            if cj == 0:
                tris = [(0, 3, 2)]
            elif cj == rings - 1:
                tris = [(0, 2, 1)]
            for tri in tris:
                c = [corners[k] for k in tri]
                faces.append([p_index(*x) for x in c])
                uv_faces.append([x[1] * (segments + 1) + x[0] for x in c])
    faces_t, uv_faces_t = torch.tensor(faces), torch.tensor(uv_faces)
    faces_t, uv_faces_t = _outward(pos, faces_t, uv_faces_t)
    return difftex.Mesh(pos.float(), faces_t, uv.float(), uv_faces_t, unit(pos).float(), faces_t)


def _outward(pos: Tensor, faces: Tensor, *others: Tensor) -> tuple[Tensor, ...]:
    """Faces (and index lists that go with them) reordered so that each winds counter-clockwise seen from
    outside a star-shaped mesh around the origin (its normal points away from the origin)."""
    p = pos[faces]
    fn = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flip = (fn * p.mean(1)).sum(-1) < 0
    swap = lambda f: torch.where(flip[:, None], f[:, [0, 2, 1]], f)
    return (swap(faces),) + tuple(swap(o) for o in others)


def cylinder() -> difftex.Mesh:
    """trimesh's cylinder (z axis, radius 0.65, height 1.6) split at its rims so the caps keep flat normals;
    its "own uv" is the cylindrical map evaluated at the vertices (trimesh gives it none), with the seam turned
    towards the camera: the triangles across it interpolate u from ~1 back to ~0, a squeezed copy of the whole
    texture, which is what the per-pixel mappings (analytic derivatives, no vertex uv) avoid."""
    import trimesh

    tm = trimesh.creation.cylinder(radius=0.65, height=1.6, sections=64).smooth_shaded
    pos = torch.tensor(tm.vertices, dtype=torch.float32)
    faces = torch.tensor(tm.faces, dtype=torch.int64)
    normals = torch.tensor(np.array(tm.vertex_normals), dtype=torch.float32)
    uv = difftex.cylindrical_uv(pos, (0.0, 0.0, 0.0), (0.0, 0.0, 0.8), ref=(-EYE[0], -EYE[1], 0.0))
    return difftex.Mesh(pos, faces, uv, faces, normals, faces)


def spot_upright() -> difftex.Mesh:
    """spot centred and turned z-up facing -y, the cameras' side ((x, y, z) -> (-x, z, y), a rotation),
    with vertex normals."""
    m = spot_mesh()
    p = m.positions - torch.tensor([0.0, 0.1, 0.19])
    p = torch.stack([-p[:, 0], p[:, 2], p[:, 1]], -1)
    return difftex.Mesh(p, m.faces, m.uv, m.uv_faces, vertex_normals(p, m.faces), m.faces)


# ---------------------------------------------------------------- rendering helpers

def view(mesh_pos: Tensor, faces: Tensor, res: int, eye=EYE, up=(0.0, 0.0, 1.0), fov: float = FOV) -> View:
    """Rasterize ``mesh_pos`` [V, 3] from ``eye`` (looking at the origin) into res x res pixels."""
    eye_t = torch.tensor(eye, dtype=torch.float32)
    mvp = camera.perspective(fov, 1.0, 0.1, 20.0, degrees=True) @ camera.look_at(eye_t, (0.0, 0.0, 0.0), up)
    frags = difftex.rasterize(camera.transform(mesh_pos, mvp).unsqueeze(0), faces, (res, res), cull_backfaces=True)
    return View(frags, eye_t, frags.mask)


def lit(v: View, normals: Tensor, points: Tensor, kd, ks: float = 0.15) -> Tensor:
    """Blinn-Phong under :data:`LIGHTS` plus ambient: [1, H, W, 3] (or [..., 1] for a scalar kd)."""
    return blinn_phong(normals, v.eye - points, LIGHTS, kd, ks=ks, shininess=40.0, ambient=AMBIENT,
                       light_colors=LIGHT_COLORS)


def to_image(colour: Tensor, mask: Tensor, background: float = BACKGROUND) -> np.ndarray:
    """[1, H, W, C] channels-last colour over a grey background -> [H, W, 3] numpy in [0, 1]."""
    colour = colour.expand(*colour.shape[:-1], 3)
    img = torch.where(mask[..., None], colour, torch.full_like(colour, background))
    return img[0].clamp(0, 1).detach().numpy()


def srgb(x: Tensor) -> Tensor:
    """Linear light in [0, 1] -> sRGB-encoded (the display curve)."""
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)


def tonemap(x: Tensor) -> Tensor:
    """HDR radiance -> display: exposure, Reinhard's x / (1 + x), sRGB."""
    x = x * ENV_EXPOSURE
    return srgb(x / (1 + x))


def tinted_checker(size: int = 240, checks: int = 15) -> Tensor:
    """The test checker, tinted red along u and green along v, so orientation and seams show: [1, 3, S, S].

    An odd number of checks puts v = 0.5 (where normal projection maps a cylinder's whole side) mid-check.
    """
    board = checker_texture(size, checks, lo=0.25, hi=1.0)
    ramp = torch.linspace(0.15, 1.0, size)
    tint = torch.stack([ramp.view(1, -1).expand(size, size), ramp.view(-1, 1).expand(size, size),
                        torch.full((size, size), 0.55)])
    return board * tint.unsqueeze(0)


def read(tex, uv: Tensor, uv_dx: Tensor, uv_dy: Tensor, wrap="repeat") -> Tensor:
    """The anisotropic lookup every 2D tile uses, channels-last [1, H, W, C]."""
    return difftex.sample(tex, uv, filter="anisotropic", max_aniso=MAX_ANISO, wrap=wrap,
                          uv_dx=uv_dx, uv_dy=uv_dy).movedim(1, -1)


# ---------------------------------------------------------------- rows 1-3: the mappings

MAPPINGS = ("planar", "cylindrical", "spherical", "box", "normal", "own uv")


def mapping_tile(mesh: difftex.Mesh, mapping: str, tex, res: int, cyl_axis: float) -> np.ndarray:
    v = view(mesh.positions, mesh.faces, res)
    p, p_dx, p_dy = difftex.interpolate(mesh.positions, mesh.faces, v.frags, derivatives=True)
    n, n_dx, n_dy = difftex.interpolate(mesh.normals, mesh.faces, v.frags, derivatives=True,
                                        attr_faces=mesh.normal_faces)
    wrap = "repeat"
    if mapping == "planar":
        # Projected along y (towards the camera's front-left): upright on the xz plane, streaked along y.
        uv, du, dv = difftex.planar_uv(p, (-1.0, 0.0, 1.0), (0.5, 0.0, 0.0), (0.0, 0.0, -0.5),
                                       points_dx=p_dx, points_dy=p_dy)
    elif mapping == "cylindrical":
        uv, du, dv = difftex.cylindrical_uv(p, (0.0, 0.0, 0.0), (0.0, 0.0, cyl_axis), points_dx=p_dx, points_dy=p_dy)
    elif mapping == "spherical":
        uv, du, dv = difftex.spherical_uv(p, points_dx=p_dx, points_dy=p_dy)
    elif mapping == "box":
        uv, du, dv = difftex.box_uv(p, n, size=2.0, points_dx=p_dx, points_dy=p_dy)
    elif mapping == "normal":
        uv, du, dv = difftex.normal_uv(n, normals_dx=n_dx, normals_dy=n_dy)
    else:
        uv, du, dv = difftex.interpolate(mesh.uv, mesh.faces, v.frags, derivatives=True, attr_faces=mesh.uv_faces)
        wrap = "clamp"
    colour = read(tex, uv, du, dv, wrap=wrap)
    return to_image(lit(v, n, p, colour), v.mask)


# ---------------------------------------------------------------- row 4: spot, texture modes and solid textures

def spot_tile(kind: str, spot: difftex.Mesh, tex, res: int, bake_size: int) -> np.ndarray:
    v = view(spot.positions, spot.faces, res, eye=(1.4, -2.9, 1.0))
    p = difftex.interpolate(spot.positions, spot.faces, v.frags)
    n = difftex.interpolate(spot.normals, spot.faces, v.frags)
    uv, du, dv = difftex.interpolate(spot.uv, spot.faces, v.frags, derivatives=True, attr_faces=spot.uv_faces)
    white = lit(v, n, p, 1.0, ks=0.35)
    if kind in ("replace", "modulate"):
        return to_image(combine(read(tex, uv, du, dv, wrap="clamp"), white, kind), v.mask)
    if kind == "shading":
        return to_image(white, v.mask)
    # Solid textures read the object-space point (in spot's own y-up frame: the grain follows its body).
    q = torch.stack([-p[..., 0], p[..., 2], p[..., 1]], -1)
    if kind == "marble":
        return to_image(lit(v, n, p, difftex.noise.marble(q * 1.6), ks=0.35), v.mask)
    if kind == "wood":
        return to_image(lit(v, n, p, difftex.noise.wood(q), ks=0.2), v.mask)
    if kind == "baked":
        baked = difftex.bake(spot, lambda pts, nrm: difftex.noise.marble(
            torch.stack([-pts[..., 0], pts[..., 2], pts[..., 1]], -1) * 1.6), bake_size)
        colour = read(baked.unsqueeze(0), uv, du, dv, wrap="clamp")
        return to_image(lit(v, n, p, colour, ks=0.35), v.mask)
    raise ValueError(kind)


# ---------------------------------------------------------------- row 5: height maps and the mirror sphere

def height_map(bumps: int, width: int = 512) -> Tensor:
    """[1, 1, W / 2, W] bumps on the sphere's own uv: sin(bumps u 2pi) sin(bumps v pi), periodic in u (no seam)
    and 0 at the poles, so displaced seam / pole copies of a vertex stay together."""
    u = (torch.arange(width) + 0.5) / width
    v = (torch.arange(width // 2) + 0.5) / (width // 2)
    return (torch.sin(2 * math.pi * bumps * u).view(1, -1) * torch.sin(math.pi * bumps * v).view(-1, 1))[None, None]


def normal_map_from_height(height: Tensor, scale: float) -> Tensor:
    """Tangent-space normal map [1, 3, H, W] (``0.5 n + 0.5``, green along +v) of ``scale * height`` by central
    differences in uv units: n = normalize(-scale dh/du, -scale dh/dv, 1), the normal :func:`difftex.bump` gives."""
    H, W = height.shape[-2:]
    h = height[0, 0]
    dh_du = (torch.roll(h, -1, 1) - torch.roll(h, 1, 1)) * (W / 2)  # periodic in u
    hp = torch.cat([h[:1], h, h[-1:]], 0)  # clamped in v
    dh_dv = (hp[2:] - hp[:-2]) * (H / 2)
    dh_dv[0] *= 2
    dh_dv[-1] *= 2
    n = unit(torch.stack([-scale * dh_du, -scale * dh_dv, torch.ones_like(h)], -1))
    return (0.5 * n + 0.5).permute(2, 0, 1).unsqueeze(0)


def height_tile(kind: str, sphere: difftex.Mesh, height: Tensor, res: int, bump_scale: float,
                disp_scale: float) -> np.ndarray:
    mesh = sphere
    if kind == "displacement":
        # One uv per position vertex (any of its corners': the height is periodic in u and 0 at the poles).
        pos_uv = torch.zeros(sphere.positions.shape[0], 2)
        pos_uv[sphere.faces.reshape(-1)] = sphere.uv[sphere.uv_faces.reshape(-1)]
        moved = displace(sphere.positions, sphere.normals, height, pos_uv, disp_scale, filter="bicubic")[0]
        n_moved = vertex_normals(moved, sphere.faces)
        mesh = difftex.Mesh(moved, sphere.faces, sphere.uv, sphere.uv_faces, n_moved, sphere.faces)
    v = view(mesh.positions, mesh.faces, res)
    p = difftex.interpolate(mesh.positions, mesh.faces, v.frags)
    n = difftex.interpolate(mesh.normals, mesh.faces, v.frags, attr_faces=mesh.normal_faces)
    albedo = torch.tensor([0.75, 0.72, 0.68])
    if kind in ("bump", "normal map"):
        uv, du, dv = difftex.interpolate(mesh.uv, mesh.faces, v.frags, derivatives=True, attr_faces=mesh.uv_faces)
        frames = tangent_frames(mesh.positions, mesh.faces, mesh.uv, mesh.normals, mesh.uv_faces,
                                normal_faces=mesh.normal_faces).at(v.frags, mesh.faces)
        if kind == "bump":
            n = bump(height, uv, frames, bump_scale, filter="trilinear", uv_dx=du, uv_dy=dv)
        else:
            nmap = normal_map_from_height(height, bump_scale)
            n = normal_map(nmap, uv, frames, filter="trilinear", uv_dx=du, uv_dy=dv)
    return to_image(lit(v, n, p, albedo, ks=0.4), v.mask)


def env_rays(res: int) -> tuple[Tensor, Tensor, Tensor]:
    """World directions [1, H, W, 3] of the mirror-sphere camera's pixel rays and their d/d(column, row)."""
    view_m = camera.look_at(torch.tensor(ENV_EYE), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    rot = view_m[:3, :3].T  # camera -> world
    t = math.tan(math.radians(ENV_FOV) / 2)
    c = (torch.arange(res) + 0.5) / res * 2 - 1
    x, y = c.view(1, -1).expand(res, res), -c.view(-1, 1).expand(res, res)
    d_cam = torch.stack([x * t, y * t, -torch.ones_like(x)], -1)
    dx = rot @ torch.tensor([2 * t / res, 0.0, 0.0])
    dy = rot @ torch.tensor([0.0, -2 * t / res, 0.0])
    return (d_cam @ rot.T).unsqueeze(0), dx.expand(1, res, res, 3), dy.expand(1, res, res, 3)


def mirror(sphere: difftex.Mesh, res: int) -> tuple[View, Tensor, Tensor, Tensor]:
    """The mirror sphere's view and its reflected view vectors with their screen-space derivatives.

    r = d - 2 (n.d) n with d = p - eye (not normalised: the lookups only use the direction) and n the
    normalised interpolated normal; the derivatives follow by the product rule from interpolate's.
    """
    v = view(sphere.positions, sphere.faces, res, eye=ENV_EYE, up=(0.0, 1.0, 0.0), fov=ENV_FOV)
    p, p_dx, p_dy = difftex.interpolate(sphere.positions, sphere.faces, v.frags, derivatives=True)
    m, m_dx, m_dy = difftex.interpolate(sphere.normals, sphere.faces, v.frags, derivatives=True,
                                        attr_faces=sphere.normal_faces)
    length = m.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    n = m / length
    dot = lambda a, b: (a * b).sum(-1, keepdim=True)
    d = p - v.eye
    r = d - 2 * dot(n, d) * n

    def deriv(dd: Tensor, dm: Tensor) -> Tensor:
        dn = (dm - n * dot(n, dm)) / length
        return dd - 2 * ((dot(dn, d) + dot(n, dd)) * n + dot(n, d) * dn)

    return v, r, deriv(p_dx, m_dx), deriv(p_dy, m_dy)


def env_tile(kind: str, sphere: difftex.Mesh, env: Tensor, cube, res: int) -> tuple[np.ndarray, Tensor, Tensor]:
    """The mirror sphere over the environment; returns the image and the sphere's linear colour [1, H, W, 3]
    and mask [1, H, W] (for the test's check)."""
    v, r, r_dx, r_dy = mirror(sphere, res)
    rays, ray_dx, ray_dy = env_rays(res)
    back = difftex.envmap.equirect(env, rays, filter="trilinear", dirs_dx=ray_dx, dirs_dy=ray_dy)
    # Background pixels have r = 0 (a zero direction reads 0); they are replaced by the rays' lookup below.
    if kind == "cube":
        refl = difftex.envmap.cubemap(cube, r, filter="trilinear", dirs_dx=r_dx, dirs_dy=r_dy)
    else:
        refl = difftex.envmap.equirect(env, r, filter="anisotropic", dirs_dx=r_dx, dirs_dy=r_dy, max_aniso=MAX_ANISO)
    refl = refl.movedim(1, -1)
    hdr = torch.where(v.mask[..., None], refl, back.movedim(1, -1))
    return tonemap(hdr)[0].detach().numpy(), refl.detach(), v.mask


# ---------------------------------------------------------------- the grid

class Tile(NamedTuple):
    label: str
    render: Callable[[], np.ndarray]


def tiles(res: int, bumps: int, bake_size: int, cube_size: int, segments: int, stats: dict) -> list[Tile]:
    """The gallery's tiles in row-major order; the expensive inputs are built once, lazily."""
    cache: dict[str, object] = {}

    def get(name: str, make: Callable[[], object]):
        if name not in cache:
            cache[name] = make()
        return cache[name]

    checker = lambda: get("checker", lambda: difftex.mipmap(tinted_checker()))
    meshes = {"sphere": (lambda: get("sphere", lambda: latlong_sphere(segments, segments // 2)), 1.0),
              "cylinder": (lambda: get("cylinder", cylinder), 0.8),
              "spot": (lambda: get("spot", spot_upright), 0.8)}
    out: list[Tile] = []
    for name, (mesh, axis) in meshes.items():
        for mapping in MAPPINGS:
            label = f"{name}: {mapping}"
            if mapping == "own uv" and name == "cylinder":
                label = "cylinder: per-vertex cyl. uv\n(none of its own; seam in front)"
            elif mapping == "own uv" and name == "sphere":
                label = "sphere: own uv\n(per vertex, seam split)"
            elif mapping == "own uv":
                label = "spot: own uv (OBJ)"
            out.append(Tile(label, lambda m=mesh, k=mapping, a=axis: mapping_tile(m(), k, checker(), res, a)))
    spot = lambda: get("spot", spot_upright)
    spot_tex = lambda: get("spot_tex", lambda: difftex.mipmap(spot_texture()))
    for kind, label in (("replace", "spot: texture, replace"), ("modulate", "spot: texture x Blinn-Phong\n(modulate)"),
                        ("shading", "spot: Blinn-Phong alone\n(2 lights + ambient)"),
                        ("marble", "spot: marble (solid,\nper pixel)"), ("wood", "spot: wood (solid, per pixel)"),
                        ("baked", f"spot: marble baked\nto {bake_size}$^2$ (bake)")):
        out.append(Tile(label, lambda k=kind: spot_tile(k, spot(), spot_tex(), res, bake_size)))
    sphere = lambda: get("sphere", lambda: latlong_sphere(segments, segments // 2))
    height = lambda: get("height", lambda: height_map(bumps))
    bump_scale, disp_scale = 0.012, 0.05
    for kind, label in (("smooth", "sphere: no map"), ("bump", "bump map (trilinear\nheight slope)"),
                        ("normal map", "normal map (from the\nsame height)"),
                        ("displacement", "displacement map\n(vertices moved)")):
        out.append(Tile(label, lambda k=kind: height_tile(k, sphere(), height(), res, bump_scale, disp_scale)))

    env = lambda: get("env", lambda: difftex.load_texture(data_path("envmap/venice_sunset_1k.hdr")))
    cube = lambda: get("cube", lambda: difftex.envmap.cube_mipmap(
        difftex.envmap.equirect_to_cube(env(), cube_size, filter="trilinear")))

    def env_render(kind: str) -> np.ndarray:
        img, refl, mask = env_tile(kind, sphere(), env(), cube(), res)
        stats[f"mirror_{kind}"] = (refl, mask)
        return img

    out.append(Tile(f"mirror sphere: cube map\n({cube_size}$^2$ faces, trilinear)", lambda: env_render("cube")))
    out.append(Tile("mirror sphere: lat-long\nmap (anisotropic)", lambda: env_render("equirect")))
    return out


def main(argv: Optional[list[str]] = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tile", type=int, default=160, help="tile size in pixels")
    ap.add_argument("--bumps", type=int, default=12, help="height-map bump periods around the sphere")
    ap.add_argument("--bake-size", type=int, default=256, help="size of the baked marble texture")
    ap.add_argument("--cube-size", type=int, default=64, help="face size of the environment cube map")
    ap.add_argument("--segments", type=int, default=96, help="the sphere's segments around (half as many rings)")
    ap.add_argument("--label-px", type=int, default=30, help="height of each tile's label strip in pixels")
    ap.add_argument("--out", type=Path, default=Path("docs/images/gallery.png"))
    args = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from tqdm import tqdm

    t0 = time.perf_counter()
    stats: dict = {}
    todo = tiles(args.tile, args.bumps, args.bake_size, args.cube_size, args.segments, stats)
    images, labels = [], []
    with torch.no_grad():
        for tile in tqdm(todo, desc="gallery", unit="tile"):
            images.append(tile.render())
            labels.append(tile.label)
    t_render = time.perf_counter() - t0

    rows = math.ceil(len(images) / COLS)
    T, L = args.tile, args.label_px
    dpi = 100
    fig = plt.figure(figsize=(COLS * T / dpi, rows * (T + L) / dpi), dpi=dpi)
    for k, (img, label) in enumerate(zip(images, labels)):
        r, c = divmod(k, COLS)
        # Exact pixel placement: tile k occupies columns [c T, (c + 1) T) and rows [r (T + L) + L, (r + 1)(T + L)).
        ax = fig.add_axes((c / COLS, 1 - (r + 1) * (T + L) / (rows * (T + L)), 1 / COLS, T / (rows * (T + L))))
        ax.imshow(img, interpolation="nearest")
        ax.set_axis_off()
        fig.text((c + 0.5) / COLS, 1 - (r * (T + L) + L / 2) / (rows * (T + L)), label, ha="center", va="center",
                 fontsize=max(5.0, 7.0 * T / 160), linespacing=1.0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=dpi)
    plt.close(fig)
    total = time.perf_counter() - t0
    print(f"{len(images)} tiles of {T}px in {t_render:.1f} s (total with the figure {total:.1f} s); wrote {args.out} "
          f"({args.out.stat().st_size / 1024:.0f} KB)")
    return {"images": images, "labels": labels, "rows": rows, "cols": COLS, "tile": T, "label_px": L,
            "seconds": total, **stats}


if __name__ == "__main__":
    main()

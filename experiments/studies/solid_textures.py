"""Solid textures: Perlin fBm, wood and marble on a sphere and on spot, evaluated per pixel or baked into 2D.

Top row: the solid textures of ``difftex.noise`` evaluated at the surface
point of every pixel of an icosphere (fBm, wood, marble) and of spot (wood).
Bottom row: marble on spot per pixel (the truth), the same marble baked into
a ``--size``^2 texture with ``difftex.bake`` and read back with bilinear
``difftex.sample`` at the pixels' uv (PSNR against the per-pixel one in the
title), the baked 2D texture itself, and an ambient-occlusion map baked
with ``difftex.ambient_occlusion`` shown alone (no other shading), seen from below.
Shading of the other panels: Lambert with one light plus ambient, from the
interpolated vertex normals.

    python -m experiments.studies.solid_textures [--size 256] [--res 256] [--out docs/images/solid_textures.png]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import difftex
from difftex.metrics import psnr
from difftex.testing.meshes import icosphere, spot_mesh
from difftex.testing.suite import spot_mvp
from difftex.texture.baking import vertex_normals
from difftex.texture.noise import fbm, marble, wood

LIGHT = torch.tensor([0.4, 0.7, 0.6])


def _view(positions, faces, mvp, res):
    clip = difftex.camera.transform(positions, mvp.unsqueeze(0))
    frags = difftex.rasterize(clip, faces, (res, res), cull_backfaces=True)
    p = difftex.interpolate(positions, faces, frags)
    n = torch.nn.functional.normalize(difftex.interpolate(vertex_normals(positions, faces), faces, frags), dim=-1)
    shade = 0.25 + 0.75 * (n @ (LIGHT / LIGHT.norm())).clamp(min=0)
    return frags, p, shade.unsqueeze(1)  # shade [1, 1, H, W]


def _image(colour, shade, mask, background=1.0):
    """[1, 3, H, W] colour x shade on a grey level ``background`` -> [H, W, 3] numpy."""
    img = torch.where(mask, colour * shade, torch.full_like(colour, background))
    return img[0].permute(1, 2, 0).clamp(0, 1).numpy()


def main(argv=None) -> float:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256, help="baked texture size")
    ap.add_argument("--res", type=int, default=256, help="rendered image size")
    ap.add_argument("--ao-directions", type=int, default=64)
    ap.add_argument("--ao-resolution", type=int, default=256, help="shadow-map size")
    ap.add_argument("--out", type=Path, default=Path("docs/images/solid_textures.png"))
    args = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = time.perf_counter()
    res = args.res
    panels = []
    # Sphere: a camera 3.2 units away on +z, looking at the origin.
    pos, faces = icosphere(4)
    eye = torch.tensor([0.6, 0.8, 3.0])
    mvp = difftex.camera.perspective(40.0, 1.0, 0.1, 10.0, degrees=True) @ difftex.camera.look_at(
        eye, torch.zeros(3), torch.tensor([0.0, 1.0, 0.0]))
    frags, p, shade = _view(pos, faces, mvp, res)
    mask = frags.mask.unsqueeze(1)
    grey = (0.5 + 0.5 * fbm(p * 3, octaves=5) / 0.8).clamp(0, 1).unsqueeze(1).expand(-1, 3, -1, -1)
    panels.append(("fBm noise (5 octaves), solid", _image(grey, shade, mask)))
    panels.append(("wood, solid", _image(wood(p).permute(0, 3, 1, 2), shade, mask)))
    panels.append(("marble, solid", _image(marble(p).permute(0, 3, 1, 2), shade, mask)))

    mesh = spot_mesh()
    frags, p, shade = _view(mesh.positions, mesh.faces, spot_mvp(3.0, (1.0, 0.35, 1.0)), res)
    mask = frags.mask.unsqueeze(1)
    uv = difftex.interpolate(mesh.uv, mesh.faces, frags, attr_faces=mesh.uv_faces)
    panels.append(("wood on spot, solid", _image(wood(p).permute(0, 3, 1, 2), shade, mask)))
    solid = marble(p).permute(0, 3, 1, 2)
    tex = difftex.bake(mesh, lambda q, n: marble(q), args.size)
    baked = difftex.sample(tex.unsqueeze(0), uv, filter="bilinear", wrap="clamp")
    score = psnr(baked, solid, mask=mask.expand_as(solid))
    panels.append(("marble on spot, solid (per pixel)", _image(solid, shade, mask)))
    panels.append((f"marble baked to {args.size}$^2$, bilinear\nPSNR {score:.1f} dB vs solid",
                   _image(baked, shade, mask)))
    panels.append((f"the baked 2D texture ({args.size}$^2$)", tex.permute(1, 2, 0).clamp(0, 1).numpy()))
    t1 = time.perf_counter()
    ao = difftex.ambient_occlusion(mesh, args.size // 2, directions=args.ao_directions,
                                 resolution=args.ao_resolution)
    t_ao = time.perf_counter() - t1
    # Seen from below, where the legs and the belly occlude each other (spot is mostly convex elsewhere).
    frags, _, shade = _view(mesh.positions, mesh.faces, spot_mvp(3.0, (1.0, -0.5, 0.6)), res)
    uv = difftex.interpolate(mesh.uv, mesh.faces, frags, attr_faces=mesh.uv_faces)
    ao_px = difftex.sample(ao.unsqueeze(0), uv, filter="bilinear", wrap="clamp")
    panels.append((f"baked ambient occlusion ({args.size // 2}$^2$, {args.ao_directions}\nshadow maps), unshaded, "
                   "from below", _image(ao_px.expand(-1, 3, -1, -1), torch.ones_like(shade),
                                        frags.mask.unsqueeze(1), background=0.6)))

    fig, axes = plt.subplots(2, 4, figsize=(13, 7))
    for ax, (title, img) in zip(axes.flat, panels):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80)
    print(f"marble baked at {args.size}^2 vs solid: PSNR {score:.2f} dB; ambient occlusion bake {t_ao:.1f} s; "
          f"total {time.perf_counter() - t0:.1f} s; wrote {args.out}")
    return score


if __name__ == "__main__":
    main()

"""Speed of difftex.envmap.cubemap against difftex.sample on a 2D texture of the same texel count, same run.

A 6 x S^2 RGB cube (S = 256) is read at N x N directions (N = 512) of a
pinhole view (110 degree field of view, turned so that it spans three faces
and an edge of each), with the view's exact per-pixel direction derivatives;
the 2D reference is ``difftex.sample`` (wrap "clamp") on a [1, 3, S, 6 S]
texture (the same texels) at N x N uv of a view scaled so that a pixel covers
about as many texels as on the cube (the same mip levels). Bilinear and
trilinear (the issue's target: at most 1.5x), and EWA (reported, no target),
forward and forward + backward (gradients to the texels and the directions /
uv); forward also from prebuilt pyramids (``cube_mipmap`` against
``difftex.mipmap``). On the CPU cubemap's bilinear / trilinear run the native
kernel (``csrc/cube.cpp``) where it is built, as sample does. The two are timed interleaved (difftex.testing.timing,
a pause before every call), so a load spike on a shared machine hits both;
the ratio is the median of the per-round ratios.

Prints a markdown table (median ms, interquartile spread, ratio).

    python -m experiments.bench.bench_cubemap [--size 256] [--res 512] [--repeats 9] [--filters bilinear trilinear ewa]
        [--out docs/bench_cubemap.md]
"""
from __future__ import annotations

import argparse
import math

import torch

import difftex
from difftex.envmap import cube_mipmap, cubemap
from difftex.testing import time_interleaved


def view_dirs(n: int, fov_deg: float = 110.0, yaw: float = 0.6, pitch: float = 0.4):
    """[1, n, n, 3] directions of a pinhole view and their derivatives per column / row."""
    t = math.tan(math.radians(fov_deg) / 2)
    s = ((torch.arange(n) + 0.5) / n * 2 - 1) * t
    y, x = torch.meshgrid(-s, s, indexing="ij")
    d = torch.stack([x, y, -torch.ones_like(x)], -1)
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    rot = (torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
           @ torch.tensor([[1.0, 0, 0], [0, cp, -sp], [0, sp, cp]]))
    dx = (torch.tensor([2 * t / n, 0, 0]) @ rot.T).expand(1, n, n, 3).contiguous()
    dy = (torch.tensor([0, -2 * t / n, 0]) @ rot.T).expand(1, n, n, 3).contiguous()
    return (d @ rot.T).unsqueeze(0).contiguous(), dx, dy


def plane_uv(n: int, texels_per_pixel: float, size: int):
    """[1, n, n, 2] uv of a rotated view of a [size, 6 size] texture, ``texels_per_pixel`` along each axis."""
    s = (torch.arange(n) + 0.5 - n / 2) * texels_per_pixel
    r, c = torch.meshgrid(s, s, indexing="ij")
    a = math.radians(17)
    u = (math.cos(a) * c - math.sin(a) * r) / (6 * size) + 0.5
    v = (math.sin(a) * c + math.cos(a) * r) / size + 0.5
    uv = torch.stack([u, v], -1).unsqueeze(0)
    dx = torch.tensor([math.cos(a) / (6 * size), math.sin(a) / size]) * texels_per_pixel
    dy = torch.tensor([-math.sin(a) / (6 * size), math.cos(a) / size]) * texels_per_pixel
    return uv, dx.expand(1, n, n, 2).contiguous(), dy.expand(1, n, n, 2).contiguous()


def run(size: int, res: int, repeats: int, filters=("bilinear", "trilinear", "ewa")) -> list[str]:
    g = torch.Generator().manual_seed(0)
    cube = torch.rand(1, 6, 3, size, size, generator=g)
    tex = cube[0].permute(1, 2, 0, 3).reshape(1, 3, size, 6 * size).contiguous()
    d, ddx, ddy = view_dirs(res)
    # Texels a pixel at the view's centre: d(face uv) = |d dir| / 2 per unit m_a, times S.
    tpp = float(ddx[0, res // 2, res // 2].norm()) / 2 * size
    uv, udx, udy = plane_uv(res, tpp, size)
    rows = ["| filter | pass | cubemap ms (IQR) | sample ms (IQR) | cubemap / sample |", "|---|---|---|---|---|"]
    for filt in filters:
        for label, grad in (("forward", False), ("forward+backward", True)):
            c, t = cube.clone().requires_grad_(grad), tex.clone().requires_grad_(grad)
            dd, uu = d.clone().requires_grad_(grad), uv.clone().requires_grad_(grad)
            mip = filt != "bilinear"

            def cube_step():
                with torch.set_grad_enabled(grad):
                    out = cubemap(c, dd, filter=filt, **(dict(dirs_dx=ddx, dirs_dy=ddy) if mip else {}))
                    if grad:
                        out.backward(torch.ones_like(out))

            def tex_step():
                with torch.set_grad_enabled(grad):
                    out = difftex.sample(t, uu, filter=filt, wrap="clamp",
                                         **(dict(uv_dx=udx, uv_dy=udy) if mip else {}))
                    if grad:
                        out.backward(torch.ones_like(out))

            fns = [cube_step, tex_step]
            if not grad:
                # The same lookups from prebuilt pyramids (a CubeMipmap keeps its atlases between calls).
                mm, tm = cube_mipmap(cube), difftex.mipmap(tex)

                def cube_pre():
                    cubemap(mm, d, filter=filt, **(dict(dirs_dx=ddx, dirs_dy=ddy) if mip else {}))

                def tex_pre():
                    difftex.sample(tm, uv, filter=filt, wrap="clamp", **(dict(uv_dx=udx, uv_dy=udy) if mip else {}))
                fns += [cube_pre, tex_pre]
            times = time_interleaved(fns, repeats, pause=0.05, shuffle=True)
            for (a, b), what in zip((times[:2], times[2:]) if len(times) > 2 else (times,), ("", ", prebuilt pyramid")):
                rows.append(f"| {filt} | {label}{what} | {a.median:.1f} ({a.spread:.1f}) | {b.median:.1f} "
                            f"({b.spread:.1f}) | {a.ratio_to(b):.2f} |")
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=256, help="cube face size S")
    p.add_argument("--res", type=int, default=512, help="directions per side")
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--filters", nargs="+", default=["bilinear", "trilinear", "ewa"])
    p.add_argument("--out", default=None, help="also write the table to this markdown file")
    args = p.parse_args()
    head = f"torch {torch.__version__}, {torch.get_num_threads()} threads, cube 6 x {args.size}^2, {args.res}^2 dirs"
    print("# " + head)
    rows = run(args.size, args.res, args.repeats, args.filters)
    if args.out:
        with open(args.out, "w") as f:
            f.write(head + "\n\n" + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()

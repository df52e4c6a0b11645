"""Overhead of difftex.nvdiffrast over difftex's own ops (the same work, nvdiffrast's conventions).

The spot cow at 512 x 512 (4 views): ``rasterize``, ``interpolate`` of uv with
derivatives, and ``texture`` with trilinear mipmapping, each forward and
forward + backward, timed interleaved with the difftex call it wraps
(difftex.testing.timing: pauses, per-round ratios, medians and spread). The
target of the issue is at most 1.10x for each.

    python -m experiments.bench.bench_nvdiffrast [--res 512] [--reps 15] [--device cpu]
"""
from __future__ import annotations

import argparse
import math

import torch

import difftex
import difftex.nvdiffrast as dr
from difftex import camera
from difftex.testing.meshes import spot_mesh, spot_texture
from difftex.testing.timing import time_interleaved


def _views(mesh, n: int, device: str) -> torch.Tensor:
    proj = camera.perspective(35.0, 1.0, 0.3, 10.0, degrees=True)
    mats = [proj @ camera.look_at((2.6 * math.sin(a), 0.5, 2.6 * math.cos(a))) for a in
            torch.linspace(0, 2 * math.pi, n + 1)[:-1].tolist()]
    return camera.transform(mesh.positions.float(), torch.stack(mats)).to(device)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    dev, R = args.device, args.res
    mesh = spot_mesh()
    pos = _views(mesh, args.views, dev)
    faces = mesh.faces.to(dev)
    uv_faces = (mesh.uv_faces if mesh.uv_faces is not None else mesh.faces).to(dev)
    uv = mesh.uv.float().to(dev)
    tex = spot_texture().to(dev)
    ctx = dr.RasterizeCudaContext(device=dev)
    tri32, uvi32 = faces.int(), uv_faces.int()
    tex_nhwc = tex.permute(0, 2, 3, 1).contiguous()

    # Per-vertex uv in nvdiffrast's terms: one attribute row per corner (face-varying uv).
    frags = difftex.rasterize(pos, faces, (R, R))
    rast, rast_db = dr.rasterize(ctx, pos, tri32, (R, R))
    uv_px, uv_dx, uv_dy = difftex.interpolate(uv, faces, frags, derivatives=True, attr_faces=uv_faces)
    texc, texd = dr.interpolate(uv, rast, uvi32, rast_db=rast_db, diff_attrs="all")

    def fwd_bwd(f, leaf):
        def run():
            x = leaf.detach().requires_grad_()
            out = f(x)
            (out[0] if isinstance(out, tuple) else out).float().square().mean().backward()
        return run

    cases = {
        "rasterize": (lambda: difftex.rasterize(pos, faces, (R, R)), lambda: dr.rasterize(ctx, pos, tri32, (R, R))),
        "interpolate": (lambda: difftex.interpolate(uv, faces, frags, derivatives=True, attr_faces=uv_faces),
                        lambda: dr.interpolate(uv, rast, uvi32, rast_db=rast_db, diff_attrs="all")),
        "texture": (lambda: difftex.sample(tex, uv_px, filter="trilinear", uv_dx=uv_dx, uv_dy=uv_dy),
                    lambda: dr.texture(tex_nhwc, texc, texd, filter_mode="linear-mipmap-linear")),
    }
    grads = {
        # The loss on what both return differentiably: nvdiffrast's (u, v), difftex's first two barycentrics.
        "rasterize": (fwd_bwd(lambda p: difftex.rasterize(p, faces, (R, R)).bary[..., :2], pos),
                      fwd_bwd(lambda p: dr.rasterize(ctx, p, tri32, (R, R))[0][..., :2], pos)),
        "interpolate": (fwd_bwd(lambda a: difftex.interpolate(a, faces, frags, derivatives=True,
                                                              attr_faces=uv_faces), uv),
                        fwd_bwd(lambda a: dr.interpolate(a, rast, uvi32, rast_db=rast_db, diff_attrs="all"), uv)),
        "texture": (fwd_bwd(lambda t: difftex.sample(t, uv_px, filter="trilinear", uv_dx=uv_dx, uv_dy=uv_dy), tex),
                    fwd_bwd(lambda t: dr.texture(t, texc, texd, filter_mode="linear-mipmap-linear"), tex_nhwc)),
    }
    print(f"difftex.nvdiffrast overhead, spot, {args.views} views at {R}x{R}, {dev}, {args.reps} rounds, "
          f"{torch.get_num_threads()} threads")
    print(f"{'op':<12} {'pass':<8} {'difftex ms':>11} {'compat ms':>10} {'ratio':>6} {'IQR ms':>14}")
    for name in cases:
        for label, (a, b) in (("fwd", cases[name]), ("fwd+bwd", grads[name])):
            ta, tb = time_interleaved([a, b], args.reps, pause=0.02, shuffle=True, device=dev)
            print(f"{name:<12} {label:<8} {ta.median:11.2f} {tb.median:10.2f} {tb.ratio_to(ta):6.2f} "
                  f"{ta.spread:6.2f} / {tb.spread:5.2f}")


if __name__ == "__main__":
    main()

"""Triangle ids and barycentrics of difftex.rasterize against a float64 ray cast (issues 16 and 40).

For each scene (icosphere(8), 1,310,720 triangles, at 512^2 by default, and
spot at 512^2) and each implementation (the native kernel, the torch path),
float32 clip-space positions are rasterized and compared with
``difftex.testing.raycast.ray_cast`` of the same positions in float64. Every
disagreement is classified: both hit and the two triangles' planes are within
1e-6 in NDC depth at the pixel centre (a tie: a shared edge decided the
other way), one misses within the snap's reach (2**-16 px) of the other's
edge, or neither (a wrong triangle: what the float32 depth test produced).

Barycentrics (issue 40): where the ids agree, the per-pixel error
max_i |bary_i - exact_i| against ``difftex.testing.raycast.exact_bary`` (float64,
the same pixel centres, the same float32 / float64 positions), as median /
99.9 % / max, for float32 and float64 positions on both implementations.
Mitsuba 3's float32 ray caster is printed beside them where ``mitsuba`` is
installed (``ray_intersect_preliminary``, llvm_ad_rgb variant); else the
figures issue 40 measured for it are printed as the reference.

    python -m experiments.studies.raster_accuracy [--sub 8] [--res 512] [--views 1]
"""
from __future__ import annotations

import argparse

from typing import Optional

import torch

import difftex
from difftex import camera
from difftex.geometry.raster import SUBPIXEL_BITS
from difftex.testing import SPOT_MESH, icosphere
from difftex.testing.raycast import edge_distance, exact_bary, plane_depth, ray_cast

# Issue 40's figures for Mitsuba 3 (float32, llvm variant) at 512^2, (median, 99.9 %, max) of the barycentric error.
MITSUBA_ISSUE40 = {"spot": (1.7e-6, 3.6e-5, 6.3e-4), "icosphere(8)": (1.1e-5, 4.0e-4, 6.5e-3)}


def _spot():
    import trimesh

    m = trimesh.load(str(SPOT_MESH), process=False, force="mesh")
    return torch.tensor(m.vertices, dtype=torch.float64), torch.tensor(m.faces, dtype=torch.int64)


def _camera(V: torch.Tensor, view: int) -> torch.Tensor:
    center = (V.min(0).values + V.max(0).values) / 2
    radius = float((V - center).norm(dim=-1).max())
    a = 0.7 + 1.3 * view
    eye = center + radius * torch.tensor([2.6 * torch.sin(torch.tensor(a)), 0.9, 2.6 * torch.cos(torch.tensor(a))],
                                         dtype=torch.float64)
    mvp = camera.perspective(45.0, 1.0, 0.1 * radius, 10 * radius, degrees=True, dtype=torch.float64) @ \
        camera.look_at(eye, center, dtype=torch.float64)
    return mvp


def bary_stats(err: torch.Tensor) -> tuple[float, float, float]:
    """(median, 99.9 % quantile, max) of a 1-D error tensor (zeros where empty)."""
    if err.numel() == 0:
        return 0.0, 0.0, 0.0
    e = err.sort().values
    return float(e[(len(e) - 1) // 2]), float(e[min(len(e) - 1, int(0.999 * len(e)))]), float(e[-1])


def bary_errors(V: torch.Tensor, F: torch.Tensor, res: int, view: int) -> dict:
    """{(impl, dtype name): (median, 99.9 %, max, pixels compared)} of max_i |bary_i - exact_i| where ids agree."""
    mvp = _camera(V, view)
    out = {}
    for dtype in (torch.float32, torch.float64):
        pos = camera.transform(V, mvp).to(dtype)
        ref, _ = ray_cast(pos, F, (res, res))
        for impl in ("native", "reference"):
            with difftex.backend(impl):
                fr = difftex.rasterize(pos, F, (res, res))
            ids = fr.tri_id[0]
            ok = (ids == ref) & (ids >= 0)
            ex = exact_bary(pos, F, torch.where(ok, ids, -1), (res, res))
            err = (fr.bary[0].double() - ex).abs().amax(-1)[ok]
            out[impl, str(dtype).split(".")[1]] = (*bary_stats(err), int(ok.sum()))
    return out


def mitsuba_bary_errors(V: torch.Tensor, F: torch.Tensor, res: int, view: int) -> Optional[tuple]:
    """Mitsuba 3's float32 barycentric error as :func:`bary_errors` measures it, or None without mitsuba."""
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError:
        return None
    mi.set_variant("llvm_ad_rgb")
    mvp = _camera(V, view)
    pos = camera.transform(V, mvp).float()
    ref, _ = ray_cast(pos, F, (res, res))
    # The scene in NDC (x, y, z / w): orthographic rays along +z through the pixel centres hit the projected
    # triangles; their (u, v) are screen-space barycentrics, made perspective-correct with 1 / w.
    ndc = (pos[:, :3] / pos[:, 3:]).double()
    mesh = mi.Mesh("m", len(V), len(F))
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.ravel(mi.Point3f(*(ndc[:, k].float().numpy() for k in range(3))))
    params["faces"] = dr.ravel(mi.Vector3u(*(F[:, k].to(torch.int32).numpy() for k in range(3))))
    params.update()
    scene = mi.load_dict({"type": "scene", "m": mesh})
    r, c = torch.meshgrid(torch.arange(res), torch.arange(res), indexing="ij")
    x = ((c.reshape(-1).double() + 0.5) / res * 2 - 1).float().numpy()
    y = (1 - (r.reshape(-1).double() + 0.5) / res * 2).float().numpy()
    ray = mi.Ray3f(mi.Point3f(x, y, -2.0 + 0 * x), mi.Vector3f(0, 0, 1))
    pi = scene.ray_intersect_preliminary(ray, coherent=True)
    ids = torch.tensor(pi.prim_index.numpy().astype("int64")).view(res, res)
    hit = torch.tensor(pi.is_valid().numpy()).view(res, res)
    u = torch.tensor(pi.prim_uv.x.numpy()).double().view(res, res)
    v = torch.tensor(pi.prim_uv.y.numpy()).double().view(res, res)
    ok = hit & (ids == ref) & (ref >= 0)
    ids = torch.where(ok, ids, -1)
    ex = exact_bary(pos, F, ids, (res, res))
    w = pos[:, 3].double()[F[ids.clamp(min=0)]]  # [H, W, 3]
    lam = torch.stack((1 - u - v, u, v), -1) / w
    got = lam / lam.sum(-1, keepdim=True)
    err = (got - ex).abs().amax(-1)[ok]
    return (*bary_stats(err), int(ok.sum()))


def measure(V: torch.Tensor, F: torch.Tensor, res: int, view: int) -> dict:
    mvp = _camera(V, view)
    pos = camera.transform(V, mvp).float()
    ref, _ = ray_cast(pos, F, (res, res))
    out = {"pixels": res * res, "covered": int((ref >= 0).sum())}
    for impl in ("native", "reference"):
        with difftex.backend(impl):
            ids = difftex.rasterize(pos, F, (res, res)).tri_id[0]
        bad = torch.nonzero(ids != ref)
        r, c = bad[:, 0], bad[:, 1]
        x, y = ids[r, c], ref[r, c]
        both = (x >= 0) & (y >= 0)
        dz = (plane_depth(pos, F, x[both], r[both], c[both], (res, res))
              - plane_depth(pos, F, y[both], r[both], c[both], (res, res))).abs()
        one = ~both
        hit = torch.where(x[one] >= 0, x[one], y[one])
        de = edge_distance(pos, F, hit, r[one], c[one], (res, res))
        out[impl] = {
            "agree": 1 - len(bad) / (res * res),
            "disagree": len(bad),
            "tie": int((dz <= 1e-6).sum()),
            "max_dz": float(dz.max()) if len(dz) else 0.0,
            "edge": int((de <= 2.0 ** -SUBPIXEL_BITS).sum()),
            "max_edge_px": float(de.max()) if len(de) else 0.0,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sub", type=int, default=8, help="icosphere subdivisions")
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--bary-only", action="store_true", help="skip the triangle-id classification")
    args = ap.parse_args()
    for name, (V, F) in (("icosphere(%d)" % args.sub, icosphere(args.sub, dtype=torch.float64)), ("spot", _spot())):
        for v in range(args.views):
            errs = bary_errors(V, F, args.res, v)
            for (impl, dt), (med, q, mx, n) in errs.items():
                print(f"{name:>14} {args.res}^2 view {v} {impl:>9} {dt}: |bary - exact| median {med:.1e}  "
                      f"99.9% {q:.1e}  max {mx:.1e}  ({n:,} px where ids agree)", flush=True)
            mit = mitsuba_bary_errors(V, F, args.res, v)
            if mit is not None:
                print(f"{name:>14} {args.res}^2 view {v} {'mitsuba':>9} float32: |bary - exact| median {mit[0]:.1e}  "
                      f"99.9% {mit[1]:.1e}  max {mit[2]:.1e}  ({mit[3]:,} px)", flush=True)
            elif name in MITSUBA_ISSUE40 and args.res == 512:
                med, q, mx = MITSUBA_ISSUE40[name]
                print(f"{name:>14} {args.res}^2 {'mitsuba':>9} float32: |bary - exact| median {med:.1e}  99.9% {q:.1e}  "
                      f"max {mx:.1e}  (issue 40's figures, its own camera; mitsuba is not installed here)", flush=True)
            if args.bary_only:
                continue
            m = measure(V, F, args.res, v)
            for impl in ("native", "reference"):
                r = m[impl]
                print(f"{name:>14} {len(F):>9,} tris {args.res}^2 view {v} {impl:>9}: {r['agree']:.5%} agree "
                      f"({r['disagree']} px: {r['tie']} depth ties (max |dz| {r['max_dz']:.1e}), {r['edge']} "
                      f"within 2^-{SUBPIXEL_BITS} px of an edge (max {r['max_edge_px']:.1e} px)); "
                      f"{m['covered']:,} px covered", flush=True)


if __name__ == "__main__":
    main()

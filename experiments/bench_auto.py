"""filter="auto" against anisotropic 16 and trilinear: PSNR, time and taps on several scenes.

Scenes (reference: 16 x 16 supersampled bilinear on level 0, box filtered,
compared over pixels whose 16 x 16 sub-pixels are all covered):

* grazing plane (``difftex.scenes.grazing_plane``), 256 x 256, 1024^2
  checker + noise, repeat, at pitches 10, 20 and 40 degrees;
* a unit sphere with spherical uv (per-pixel ``spherical_uv`` of the
  interpolated surface point, so no seam), the same texture, 128 x 128 at
  distances 2, 4, 8, 16 (fov 40);
* spot (data/spot, its 1024^2 texture, clamp), 128 x 128, four views at
  distances 2.5 to 12.

Times are medians of forward passes with 1 thread, the three filters run
alternately (interleaved) so they see the same machine load; each pass
builds the pyramid from the texture (part of the cost, as in training).
"Taps" counts trilinear taps (anisotropic / auto) or pixels (trilinear).

Prints a markdown table and writes it to docs/auto_filter.md.

    python experiments/bench_auto.py [--repeats 7] [--tolerance 0.1] [--out docs/auto_filter.md]
"""
from __future__ import annotations

import argparse
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import difftex  # noqa: E402
from difftex import camera  # noqa: E402
from difftex.filters.anisotropic import tap_count  # noqa: E402
from difftex.filters.auto import auto_tap_count  # noqa: E402
from difftex.lod import ellipse, footprint  # noqa: E402
from difftex.scenes import checker_noise_texture, grazing_plane  # noqa: E402

SS = 16

NOTES = """
## How auto chooses (difftex/filters/auto.py)

Per pixel, with the footprint's axes from `difftex.lod.ellipse` (level-0 texels, times `2^lod_bias`):
`N_a = min(ceil(major / max(minor, 1/2)), max_aniso)` and `N = ceil(N_a / (1 + tolerance))` trilinear taps
(`N = N_a` where the axis ratio exceeds max_aniso: those taps are already wider than the minor axis), run
through the anisotropic filter's own code (`anisotropic_points(..., taps=N)`). Pixels whose major axis is
under half a texel get one tap at level 0 (bilinear), round footprints one tap (trilinear), long ones 2-16.
`tolerance` (default 0.1) is how much wider (as a fraction) a tap's prefilter may be than anisotropic's;
with 0 auto equals anisotropic wherever the minor axis is at least half a texel.

## Findings

* Within 0.5 dB of anisotropic 16 on every scene above and on the 17 scenes of
  experiments/speed_vs_accuracy.py (worst there -0.33 dB, the 5-degree spot plane), never more taps.
  On these scenes that leaves little to save: anisotropic's taps are nearly all needed for its accuracy,
  so auto takes 0-3 % fewer taps and its time is anisotropic's within this machine's noise. It saves where
  footprints are magnified below half a texel (one read instead of anisotropic's two) or round.
* What the first version gave away: with tolerance 0.25 it took 7-10 % fewer taps on grazing planes but
  fell 2.1 dB under anisotropic 16 on the closed-form checker plane at 5 degrees (1.2 dB on the spot
  plane); with a one-texel spacing floor it read plain bilinear on a sphere magnified 2x, 5.3 dB under
  anisotropic, whose two level-0 taps there act as supersampling inside the pixel. Below half a texel the
  gap between one and two level-0 taps stays 5-8 dB, but both errors are under one 8-bit level (52-72 dB).
* Making nearly-round footprints (axis ratio 1-1.25) one trilinear tap, as a first version did, costs
  3-5 dB on spot's texture: anisotropic's two taps there sit a full level finer than trilinear's one, and
  trilinear's level (box pyramid + bilinear) is already blurrier than the pixel's box footprint. So the
  tolerance scales the tap count relative to anisotropic's, and the one-tap case is only reached where
  `N_a / (1 + tolerance) <= 1`.
* Larger tolerances trade fast: 0.5 loses 1-1.7 dB on spot and 1.2-1.5 dB on the plane; 1.0 loses 3-9 dB.
* "Brilinear" taps (snapping each tap's level to an integer within a band, one bilinear read instead of
  two) were tried and dropped: -0.2 to -1.2 dB for at most ~10 % time on these scenes.
* A plain texture tensor given to `filter="auto"` builds only the pyramid levels the footprints read
  (`difftex.levels_needed`), with identical values.
"""


def _masked_psnr(x: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> float:
    err = ((x - ref) ** 2).double()[mask.expand_as(x)]
    mse = err.mean().item()
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def plane_scene(tex: torch.Tensor, pitch: float, res: int = 256):
    uv, dx, dy = grazing_plane(res, pitch, 1.0)
    fine = grazing_plane(res, pitch, 1.0, ss=SS)[0]
    ref = F.avg_pool2d(difftex.sample(tex, fine, wrap="repeat"), SS)
    mask = torch.isfinite(ref).all(1, keepdim=True)
    return dict(uv=uv, uv_dx=dx, uv_dy=dy, ref=ref, mask=mask, wrap="repeat")


def _raster_uv(positions, faces, mvp, res, uv_fn):
    pos = camera.transform(positions, mvp.unsqueeze(0))
    frags = difftex.rasterize(pos, faces, (res, res))
    return frags, uv_fn(frags)


def _mesh_scene(positions, faces, mvp, res, tex, wrap, uv_of):
    """uv_of(frags, derivatives) -> uv or (uv, dx, dy); reference from a 16x finer raster."""
    frags = difftex.rasterize(camera.transform(positions, mvp.unsqueeze(0)), faces, (res, res))
    uv, dx, dy = uv_of(frags, True)
    fine = difftex.rasterize(camera.transform(positions, mvp.unsqueeze(0)), faces, (res * SS, res * SS))
    fuv = uv_of(fine, False)
    ref = F.avg_pool2d(difftex.sample(tex, fuv, wrap=wrap), SS)
    mask = F.avg_pool2d(fine.mask.unsqueeze(1).double(), SS) == 1
    return dict(uv=uv, uv_dx=dx, uv_dy=dy, ref=ref, mask=mask, wrap=wrap)


def sphere_scene(tex: torch.Tensor, dist: float, res: int = 128):
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=5)
    positions = torch.tensor(m.vertices, dtype=torch.float32)
    faces = torch.tensor(m.faces, dtype=torch.int64)
    eye = torch.tensor([dist * 0.6, dist * 0.3, dist * 0.74])
    eye = eye / eye.norm() * dist
    mvp = camera.perspective(40.0, 1.0, 0.1, 100.0, degrees=True) @ camera.look_at(
        eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))

    def uv_of(frags, derivs):
        if derivs:
            p, pdx, pdy = difftex.interpolate(positions, faces, frags, derivatives=True)
            return difftex.spherical_uv(p, points_dx=pdx, points_dy=pdy)
        return difftex.spherical_uv(difftex.interpolate(positions, faces, frags))

    return _mesh_scene(positions, faces, mvp, res, tex, "repeat", uv_of)


def spot_scene(mesh, tex: torch.Tensor, view: int, res: int = 128):
    dirs = [(0.8, 0.3, 1.0), (-1.0, 0.5, 0.2), (0.1, 1.0, -0.6), (1.0, -0.2, -1.0)]
    dists = [2.5, 4.0, 7.0, 12.0]
    d = torch.tensor(dirs[view])
    at = torch.tensor([0.0, 0.1, 0.2])
    eye = at + d / d.norm() * dists[view]
    mvp = camera.perspective(40.0, 1.0, 0.1, 100.0, degrees=True) @ camera.look_at(eye, at, torch.tensor([0.0, 1.0, 0.0]))

    def uv_of(frags, derivs):
        return difftex.interpolate(mesh.uv, mesh.faces, frags, derivatives=derivs, attr_faces=mesh.uv_faces)

    return _mesh_scene(mesh.positions, mesh.faces, mvp, res, tex, "clamp", uv_of), dists[view]


def taps(scene, H: int, W: int, filter: str, tolerance: float) -> int:
    dx, dy = scene["uv_dx"].reshape(-1, 2), scene["uv_dy"].reshape(-1, 2)
    if filter == "trilinear":
        return dx.shape[0]
    fp = footprint(dx, dy, H, W)
    ell = ellipse(fp)
    n = tap_count(ell, fp, 16) if filter == "anisotropic" else auto_tap_count(ell, fp, 0.0, 16, tolerance)
    return int(n.sum())


def run(scene, tex, filters, repeats: int):
    """Medians (ms) of interleaved forward passes, and the outputs."""
    outs, times = {}, {name: [] for name, _ in filters}
    for r in range(repeats + 1):
        for name, kw in filters:
            t0 = time.perf_counter()
            out = difftex.sample(tex, scene["uv"], uv_dx=scene["uv_dx"], uv_dy=scene["uv_dy"], wrap=scene["wrap"],
                                 **kw)
            if r:
                times[name].append((time.perf_counter() - t0) * 1e3)
            outs[name] = out
    return outs, {k: statistics.median(v) for k, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--tolerance", type=float, default=None, help="auto's tolerance (default: sample's)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "auto_filter.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    from difftex.sample import DEFAULT_TOLERANCE
    tol = DEFAULT_TOLERANCE if args.tolerance is None else args.tolerance
    auto_kw = {"filter": "auto"} if args.tolerance is None else {"filter": "auto", "tolerance": tol}
    filters = [("trilinear", {"filter": "trilinear"}), ("anisotropic 16", {"filter": "anisotropic", "max_aniso": 16}),
               ("auto", auto_kw)]
    checker = checker_noise_texture(1024)
    mesh = difftex.load_mesh(ROOT / "data" / "spot" / "spot_triangulated.obj")
    spot_tex = difftex.load_texture(ROOT / "data" / "spot" / "spot_texture.png")
    scenes = [(f"grazing plane, pitch {p}", checker, lambda p=p: plane_scene(checker, p)) for p in (10, 20, 40)]
    scenes += [(f"sphere, distance {d}", checker, lambda d=d: sphere_scene(checker, d)) for d in (2, 4, 8, 16)]
    scenes += [(f"spot, view {v}", spot_tex, lambda v=v: spot_scene(mesh, spot_tex, v)) for v in range(4)]
    rows = []
    for name, tex, make in scenes:
        scene = make()
        if isinstance(scene, tuple):
            scene, dist = scene
            name = f"{name} (distance {dist})"
        outs, times = run(scene, tex, filters, args.repeats)
        H, W = tex.shape[-2:]
        row = {"scene": name, "pixels": int(scene["mask"].sum())}
        for f, _ in filters:
            key = "anisotropic" if f.startswith("aniso") else f
            row[f] = (_masked_psnr(outs[f], scene["ref"], scene["mask"]), times[f], taps(scene, H, W, key, tol))
        rows.append(row)
        print(name, {k: (round(v[0], 2), round(v[1], 1), v[2]) if isinstance(v, tuple) else v
                     for k, v in row.items() if k != "scene"}, flush=True)
    lines = [
        "# filter=\"auto\" vs anisotropic 16 vs trilinear",
        "",
        f"Generated by `experiments/bench_auto.py` (auto tolerance {tol}). PSNR in dB against a 16x16 supersampled "
        "bilinear reference over fully covered pixels; forward time in ms (median of "
        f"{args.repeats}, the three filters interleaved, 1 thread, pyramid built inside the timed call; "
        f"torch {torch.__version__}, {platform.machine()}, shared 2-core machine, so +-20% noise); "
        "taps = trilinear taps (trilinear: one per pixel).",
        "",
        "| scene | trilinear dB / ms / taps | aniso 16 dB / ms / taps | auto dB / ms / taps | auto - aniso16 dB |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        cells = [f"{r[f][0]:.2f} / {r[f][1]:.1f} / {r[f][2]}" for f, _ in filters]
        lines.append(f"| {r['scene']} | " + " | ".join(cells) + f" | {r['auto'][0] - r['anisotropic 16'][0]:+.2f} |")
    text = "\n".join(lines) + "\n" + NOTES
    print(text)
    Path(args.out).write_text(text)


if __name__ == "__main__":
    main()

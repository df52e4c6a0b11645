"""Filtering after shading (issue 41 point 5): a normal-mapped plane under a tight Blinn-Phong lobe, minified.

A texture filter averages what it reads; shading is not linear in a normal, so the shaded average of
filtered normals is not the average of shaded normals: filtering a bumpy normal map before shading flattens
it and loses the glints a tight specular lobe makes of the bumps (Pharr, Wronski, Salvi, Fajardo, "Filtering
After Shading With Stochastic Texture Filtering", 2024). Stochastic filtering reads one texel-tap drawn from
the filter's weights; shading each draw and averaging the shaded draws estimates the filter applied *after*
shading, without bias, at the cost of noise that falls as 1 / sqrt(draws).

Scenes: a 512^2 normal map of random bumps (a height field of band-limited noise, 24-96 cycles across the
texture, its normals encoded in [0, 1]) on a plane seen straight on at 4, 8, 16 and 32 texels a pixel, and on
the grazing plane of ``difftex.testing.grazing_plane`` (1-100 texels a pixel, anisotropic). The shading is
Blinn-Phong in the plane's tangent frame: kd 0.2, ks 1, shininess 400, light and view fixed, the half vector
4 degrees off the flat normal (a light near the viewer). The bumps' own normals mostly miss so tight a lobe
(the supersampled plane's mean radiance is 0.23); filtered normal maps are flatter and catch it everywhere
(0.44-0.58 at 4-32 texels a pixel, anisotropic-16): the specular aliasing of Toksvig (2005) and Olano & Baker
(2010), which filtering after shading does not have. The reference shades 16 x 16
bilinear level-0 lookups a pixel and averages them (a box filter over the pixel, after shading).

Methods, each timed (forward, interleaved rounds, median) and scored (RMSE against the reference):

* before: ``normal_map``'s way: the encoded normal map filtered (trilinear, anisotropic-16, EWA), decoded,
  renormalised, shaded once;
* after, stochastic filter: ``sample(..., stochastic=1, generator=g)`` k times (k = 1 .. 32; anisotropic-16 and
  EWA), each draw decoded and shaded, the k shaded values averaged. The draws read the mip levels, which are
  themselves the normal map filtered before shading: averaging after shading undoes only the filter's own
  blend (of levels, probes, texels), not the pyramid's prefiltering, so this barely moves under minification;
* after, level-0 footprint draws: k points drawn uniformly from each pixel's footprint (``uv + a uv_dx + b
  uv_dy``, a, b uniform in [-1/2, 1/2): filter importance sampling of the box pixel filter), each read by a
  bilinear tap of level 0 and shaded, averaged: what a renderer with k samples a pixel does, unbiased for the
  reference, with noise falling as 1 / sqrt(k).

The figure puts, on the grazing plane, the reference beside filtering before shading (anisotropic-16) and
after it at about the same wall time; the chart plots error against time for every method and scene.

    python -m experiments.studies.filter_after_shading [--res 128] [--out docs/images/filter_after_shading.png]
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
import torch.nn.functional as F

import difftex
from difftex.testing import grazing_plane, time_interleaved

DRAWS = (1, 2, 4, 8, 16, 32)  # level-0 footprint draws
FILTER_DRAWS = (1, 4, 16)  # the stochastic filters' draws (their torch path is slower)


def height_field(size: int = 512, seed: int = 0) -> torch.Tensor:
    """[size, size] float64 random band-limited height field (24-96 cycles across), in texels, slopes ~0.35."""
    g = torch.Generator().manual_seed(seed)
    f = torch.fft.fftfreq(size, d=1.0 / size)
    fy, fx = torch.meshgrid(f, f, indexing="ij")
    r = torch.sqrt(fx ** 2 + fy ** 2)
    band = ((r >= 24) & (r <= 96)).double()
    spec = torch.complex(torch.randn(size, size, generator=g, dtype=torch.float64),
                         torch.randn(size, size, generator=g, dtype=torch.float64)) * band
    h = torch.fft.ifft2(spec).real
    # Slopes of about 0.35 (20 degrees): bumps a tight lobe resolves, normals a filter flattens.
    return h / h.std() * 0.35 / (2 * math.pi * 60 / size)


def bump_normal_map(size: int = 512, seed: int = 0) -> torch.Tensor:
    """[1, 3, size, size] tangent-space normal map (encoded in [0, 1]) of ``height_field``: its central
    differences."""
    h = height_field(size, seed)
    hx = (torch.roll(h, -1, 1) - torch.roll(h, 1, 1)) / 2
    hy = (torch.roll(h, -1, 0) - torch.roll(h, 1, 0)) / 2
    n = torch.stack([-hx, -hy, torch.ones_like(h)], 0)
    n = n / n.norm(dim=0, keepdim=True)
    return ((n + 1) / 2).float()[None]


def bump_height_map(size: int = 512, seed: int = 0) -> torch.Tensor:
    """[1, 1, size, size] the same height field in uv units (a texel is 1 / size), for ``difftex.bump``."""
    return (height_field(size, seed) / size).float()[None, None]


def blinn(n: torch.Tensor, light: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
    """[B, 1, H, W] Blinn-Phong radiance of unit tangent-space normals [B, H, W, 3] (frame = identity)."""
    return difftex.blinn_phong(n, view, light, kd=0.2, ks=1.0, shininess=400.0).movedim(-1, 1)


def normal_map_normals(tex, uv: torch.Tensor, **kw) -> torch.Tensor:
    """Unit normals [B, H, W, 3] of an encoded normal map read by ``difftex.sample(tex, uv, **kw)``."""
    return F.normalize(2 * difftex.sample(tex, uv, **kw).movedim(1, -1) - 1, dim=-1, eps=1e-12)


def bump_normals(tex, uv: torch.Tensor, **kw) -> torch.Tensor:
    """Unit normals [B, H, W, 3] of a height map (uv units) by bump mapping: ``normalize(-dh/du, -dh/dv, 1)`` with
    the slope of the read ``difftex.sample(tex, uv, **kw)`` (for a stochastic read, the slope of the drawn
    estimate: unbiased for the filter's slope, docs/stochastic.md)."""
    with torch.enable_grad():
        pts = uv.detach().requires_grad_(True)
        h = difftex.sample(tex, pts, **kw)
        (slope,) = torch.autograd.grad(h, pts, torch.ones_like(h))
    return F.normalize(torch.cat([-slope, torch.ones_like(slope[..., :1])], -1), dim=-1)


MAPS = {"normal": (bump_normal_map, normal_map_normals), "bump": (bump_height_map, bump_normals)}


def frontal_plane(res: int, texels_per_pixel: float, size: int, ss: int = 1):
    """uv, uv_dx, uv_dy ([1, res * ss, res * ss, 2]) of a plane seen straight on at ``texels_per_pixel``."""
    n = res * ss
    t = (torch.arange(n, dtype=torch.float64) + 0.5) / ss * texels_per_pixel / size + 0.123
    v, u = torch.meshgrid(t, t, indexing="ij")
    uv = torch.stack([u, v], -1)[None].float()
    dx = torch.zeros_like(uv)
    dx[..., 0] = texels_per_pixel / size
    dy = torch.zeros_like(uv)
    dy[..., 1] = texels_per_pixel / size
    return uv, dx, dy


def reference(normals, tex: torch.Tensor, uv_ss: torch.Tensor, ss: int, light, view,
              chunk_rows: int = 8) -> torch.Tensor:
    """Box average over ss x ss sub-pixel samples of the shaded bilinear level-0 normal: shading, then filtering."""
    rows = []
    with torch.no_grad():
        for chunk in torch.split(uv_ss, chunk_rows * ss, dim=1):
            rows.append(F.avg_pool2d(blinn(normals(tex, chunk, filter="bilinear"), light, view), ss))
    return torch.cat(rows, 2)


def footprint_draws(uv: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """One point a pixel drawn uniformly from the pixel's square footprint: ``uv + a dx + b dy``, a, b uniform in
    [-1/2, 1/2) (filter importance sampling of the box pixel filter, the reference's own)."""
    ab = torch.rand(uv.shape[:-1] + (2,), generator=g, dtype=uv.dtype) - 0.5
    return uv + ab[..., :1] * dx + ab[..., 1:] * dy


def methods(normals, mip, uv, dx, dy, light, view):
    """{name: (callable giving the [1, 1, H, W] image, draws)}; ``normals`` reads unit normals (``MAPS``)."""
    kw = dict(uv_dx=dx, uv_dy=dy, max_aniso=16)
    out = {}
    for f in ("trilinear", "anisotropic", "ewa"):
        out[f"before: {f}"] = ((lambda f=f: blinn(normals(mip, uv, filter=f, **kw), light, view)), 0)

    def average(k: int, draw) -> torch.Tensor:
        g = torch.Generator().manual_seed(k)
        return sum(blinn(draw(g), light, view) for _ in range(k)) / k

    for f in ("anisotropic", "ewa"):
        for k in FILTER_DRAWS:
            out[f"after: stochastic {f} x{k}"] = (
                lambda f=f, k=k: average(k, lambda g: normals(mip, uv, filter=f, stochastic=1, generator=g, **kw)), k)
    for k in DRAWS:
        out[f"after: level-0 footprint x{k}"] = (
            lambda k=k: average(k, lambda g: normals(mip[0], footprint_draws(uv, dx, dy, g), filter="bilinear")), k)
    return out


def rmse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.sqrt(((a - b) ** 2).mean()))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--ss", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--map", default="normal", choices=list(MAPS),
                    help="normal: an encoded normal map; bump: the same bumps as a height map (difftex.bump's way)")
    ap.add_argument("--out", default="results/filter_after_shading/filter_after_shading.png",
                    help="figure (docs/images/filter_after_shading.png is the README's); the chart beside it")
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    make, normals = MAPS[args.map]
    tex = make()
    mip = difftex.mipmap(tex)
    size = tex.shape[-1]
    h = F.normalize(torch.tensor([math.sin(math.radians(4)), 0.0, math.cos(math.radians(4))]), dim=0)
    view = torch.tensor([0.0, 0.0, 1.0])
    light = F.normalize(2 * torch.dot(h, view) * h - view, dim=0)  # the mirror of view about h
    scenes = {f"frontal {s}x": (frontal_plane(args.res, s, size), frontal_plane(args.res, s, size, args.ss)[0])
              for s in (4, 8, 16, 32)}
    uv, dx, dy = grazing_plane(args.res, tile=0.25)
    scenes["grazing"] = ((uv, dx, dy), grazing_plane(args.res, tile=0.25, ss=args.ss)[0])

    rows, images = [], {}
    for name, ((uv, dx, dy), uv_ss) in scenes.items():
        ref = reference(normals, mip[0], uv_ss, args.ss, light, view)
        ms = methods(normals, mip, uv, dx, dy, light, view)
        with torch.no_grad():
            times = time_interleaved([fn for fn, _ in ms.values()], repeats=args.repeats, warmup=1)
            for (m, (fn, k)), t in zip(ms.items(), times):
                img = fn()
                rows.append({"scene": name, "method": m, "draws": k, "ms": t.median, "rmse": rmse(img, ref)})
                if name == "grazing":
                    images[m] = img
        images["reference"] = ref if name == "grazing" else images.get("reference")
        print(f"{name}: reference mean {float(ref.mean()):.4f}", flush=True)

    print("| scene | method | ms | RMSE |\n|---|---|---:|---:|")
    for r in rows:
        print(f"| {r['scene']} | {r['method']} | {r['ms']:.1f} | {r['rmse']:.4f} |")
    # At equal wall time: per scene, the best result after shading within 10 % of anisotropic-16's time (at
    # 128^2 the shading itself is most of every method's time; the timer's noise is a few percent).
    print("\n| scene | before: anisotropic RMSE (ms) | after, no slower: best RMSE (method, ms) | lower error |")
    print("|---|---|---|---|")
    for name in scenes:
        sc = [r for r in rows if r["scene"] == name]
        base = next(r for r in sc if r["method"] == "before: anisotropic")
        cand = [r for r in sc if r["draws"] and r["ms"] <= 1.1 * base["ms"]]
        best = min(cand, key=lambda r: r["rmse"]) if cand else None
        print(f"| {name} | {base['rmse']:.4f} ({base['ms']:.1f}) | "
              + (f"{best['rmse']:.4f} ({best['method']}, {best['ms']:.1f})" if best else "none that fast")
              + f" | {'after' if best and best['rmse'] < base['rmse'] else 'before'} |")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    g = [r for r in rows if r["scene"] == "grazing"]
    base = next(r for r in g if r["method"] == "before: anisotropic")
    cand = [r for r in g if r["draws"] and r["ms"] <= 1.1 * base["ms"]] or [min((r for r in g if r["draws"]),
                                                                         key=lambda r: r["ms"])]
    best = min(cand, key=lambda r: r["rmse"])
    panels = [("16x16 supersampled reference", images["reference"]),
              (f"before shading: anisotropic-16 ({base['ms']:.0f} ms)", images["before: anisotropic"]),
              (f"after shading: {best['method'].split(': ')[1]} ({best['ms']:.0f} ms)", images[best["method"]])]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 4.4))
    vmax = 1.0  # one scale for all three: filtering first shows as too much highlight
    for ax, (title, img) in zip(axes, panels):
        ax.imshow(img[0, 0].clamp(0, vmax).numpy(), cmap="gray", vmin=0, vmax=vmax)
        ax.set_title(f"{title}\nRMSE {rmse(img, images['reference']):.4f}", fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, name in enumerate(scenes):
        sc = [r for r in rows if r["scene"] == name]
        c = f"C{i}"
        for f, ls in (("stochastic anisotropic", ":"), ("stochastic ewa", "--"), ("level-0 footprint", "-")):
            pts = [r for r in sc if r["method"].startswith(f"after: {f}")]
            ax.plot([r["ms"] for r in pts], [r["rmse"] for r in pts], ls, color=c, marker=".",
                    label=f"{name}: after, {f}" if i == 0 else (name if f == "level-0 footprint" else None))
        for r in sc:
            if r["method"].startswith("before"):
                ax.scatter([r["ms"]], [r["rmse"]], color=c, marker={"before: trilinear": "v",
                           "before: anisotropic": "s", "before: ewa": "D"}[r["method"]], zorder=3)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward ms (log)")
    ax.set_ylabel("RMSE against the reference (log)")
    ax.set_title("before shading (markers: v trilinear, s anisotropic, D ewa) vs after (lines: draws 1-32)",
                 fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    chart = out.with_name(out.stem + "_chart.png")
    fig.savefig(chart, dpi=110)
    print(f"wrote {out} and {chart}")


if __name__ == "__main__":
    main()

"""Ripmap and summed-area table against trilinear and anisotropic: footprint angle and elongation.

The seed notes' answer to anisotropy: "use ripmaps and summed-area tables.
Can look up axis-aligned rectangular zones; diagonal footprints still a
problem". Measured on ``--points``^2 random uv of a checker-plus-noise
texture (``--tex``^2 texels, repeat), every point with the same footprint:

* angle: a footprint of 16 x 2 texels (8:1) rotated from 0 to 90 degrees;
  reference: 16 x 16 supersampled bilinear over the pixel's parallelogram
  (:func:`difftex.testing.supersampled`);
* elongation: axis-aligned footprints of r x 1 texels along u, r = 1 to
  512; reference: the exact mean of the bilinear texture over the box
  (:func:`experiments.studies.stability.box_mean_bilinear`), which no
  supersampling reaches at r = 512. Also the forward + backward time of
  each filter (gradients to texture and uv), timed interleaved
  (:func:`difftex.testing.time_interleaved`).

Writes ``--out`` (default results/box_filters): box_filters.png and
box_filters.md; ``--docs`` copies the chart to docs/images/box_filters.png.

    python -m experiments.studies.box_filters [--points 64] [--tex 256] [--repeats 5] [--threads 1]
"""
from __future__ import annotations

import argparse
import math
import platform
import shutil
import time
from pathlib import Path
from typing import Optional

import torch

import difftex
from difftex.metrics import psnr
from difftex.testing import checker_noise_texture, supersampled, time_interleaved
from experiments.studies.stability import box_mean_bilinear

ROOT = Path(__file__).resolve().parents[2]
METHODS = (("trilinear", {}), ("anisotropic-16", {"max_aniso": 16}), ("ripmap", {}), ("sat", {}))
ANGLES = (0.0, 7.5, 15.0, 22.5, 30.0, 37.5, 45.0, 52.5, 60.0, 67.5, 75.0, 82.5, 90.0)
RATIOS = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512)


def _filter(name: str) -> str:
    return name.split("-")[0]


def footprint_points(n: int, size: int, J: list[list[float]], seed: int = 0):
    """uv [1, n, n, 2] random, and uv_dx / uv_dy of the texel Jacobian J (columns: per pixel column / row)."""
    uv = torch.rand(1, n, n, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    dx = torch.tensor([J[0][0], J[1][0]], dtype=torch.float64) / size
    dy = torch.tensor([J[0][1], J[1][1]], dtype=torch.float64) / size
    return uv, dx.expand(1, n, n, 2).contiguous(), dy.expand(1, n, n, 2).contiguous()


def parallelogram_reference(tex, uv, dx, dy, ss: int = 16):
    """ss x ss bilinear samples over each point's parallelogram ``uv + a dx + b dy``, box-averaged."""
    n = uv.shape[1]
    a = (torch.arange(ss, dtype=torch.float64) + 0.5) / ss - 0.5
    A, B = torch.meshgrid(a, a, indexing="xy")
    sub = uv[0, :, :, None, None, :] + A[..., None] * dx[0, :1, :1, None] + B[..., None] * dy[0, :1, :1, None]
    return supersampled(tex, sub.permute(0, 2, 1, 3, 4).reshape(1, n * ss, n * ss, 2), ss)


def rotated(major: float, minor: float, degrees: float) -> list[list[float]]:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return [[c * major, -s * minor], [s * major, c * minor]]


def sweep_angle(tex, n: int, angles=ANGLES) -> list[dict]:
    size = tex.shape[-1]
    rows = []
    for deg in angles:
        uv, dx, dy = footprint_points(n, size, rotated(16, 2, deg))
        ref = parallelogram_reference(tex.double(), uv, dx, dy)
        for name, kw in METHODS:
            out = difftex.sample(tex, uv.float(), filter=_filter(name), uv_dx=dx.float(), uv_dy=dy.float(), **kw)
            rows.append(dict(sweep="angle", x=deg, method=name, psnr=psnr(out.double(), ref)))
    return rows


def sweep_ratio(tex, n: int, repeats: int, ratios=RATIOS) -> list[dict]:
    size = tex.shape[-1]
    rows = []
    for r in ratios:
        uv, dx, dy = footprint_points(n, size, [[float(r), 0.0], [0.0, 1.0]])
        ref = box_mean_bilinear(tex, uv.reshape(-1, 2), (dx[..., 0] / 2).reshape(-1),
                                (dy[..., 1] / 2).reshape(-1)).view(1, -1, n, n)
        t = tex.clone().requires_grad_(True)
        u = uv.float().requires_grad_(True)
        fns, outs = [], {}
        for name, kw in METHODS:
            call = lambda f=_filter(name), kw=kw: difftex.sample(t, u, filter=f, uv_dx=dx.float(), uv_dy=dy.float(),
                                                                 **kw)
            with torch.no_grad():
                outs[name] = call()

            def fwd_bwd(call=call):
                t.grad = u.grad = None
                call().sum().backward()
            fns.append(fwd_bwd)
        times = time_interleaved(fns, repeats, shuffle=True)
        for (name, _), tm in zip(METHODS, times):
            rows.append(dict(sweep="ratio", x=r, method=name, psnr=psnr(outs[name].double(), ref), ms=tm.median))
    return rows


def plot(rows: list[dict], path: Path, meta: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(17, 5))
    for name, _ in METHODS:
        a = [r for r in rows if r["sweep"] == "angle" and r["method"] == name]
        axes[0].plot([r["x"] for r in a], [r["psnr"] for r in a], "o-", label=name, ms=4)
        b = [r for r in rows if r["sweep"] == "ratio" and r["method"] == name]
        axes[1].plot([r["x"] for r in b], [r["psnr"] for r in b], "o-", label=name, ms=4)
        axes[2].plot([r["x"] for r in b], [r["ms"] for r in b], "o-", label=name, ms=4)
    axes[0].set(xlabel="footprint angle to the u axis (deg), 16 x 2 texels", ylabel="PSNR vs 16x16 supersampled (dB)",
                title="diagonal footprints: the box is too big")
    axes[1].set(xlabel="axis-aligned footprint r x 1 texels", ylabel="PSNR vs exact box mean (dB)", xscale="log",
                title="elongation along u")
    axes[2].set(xlabel="axis-aligned footprint r x 1 texels", ylabel="forward + backward (ms)", xscale="log",
                yscale="log", title="cost")
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=9)
    fig.suptitle("ripmap and summed-area table (sat) against trilinear and anisotropic: " + meta, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def table(rows: list[dict]) -> str:
    names = [m for m, _ in METHODS]
    lines = ["| angle (deg) | " + " | ".join(names) + " |", "| ---: |" + " ---: |" * len(names)]
    for x in dict.fromkeys(r["x"] for r in rows if r["sweep"] == "angle"):
        cell = {r["method"]: r for r in rows if r["sweep"] == "angle" and r["x"] == x}
        lines.append(f"| {x:g} | " + " | ".join(f"{cell[m]['psnr']:.1f}" for m in names) + " |")
    lines += ["", "| r x 1 texels | " + " | ".join(f"{m} dB / ms" for m in names) + " |",
              "| ---: |" + " ---: |" * len(names)]
    for x in dict.fromkeys(r["x"] for r in rows if r["sweep"] == "ratio"):
        cell = {r["method"]: r for r in rows if r["sweep"] == "ratio" and r["x"] == x}
        lines.append(f"| {x:g} | " + " | ".join(f"{cell[m]['psnr']:.1f} / {cell[m]['ms']:.1f}" for m in names) + " |")
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=64, help="points per side (all share one footprint)")
    ap.add_argument("--tex", type=int, default=256, help="texture size (square)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="results/box_filters")
    ap.add_argument("--docs", action="store_true", help="also copy the chart to docs/images/box_filters.png")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    tex = checker_noise_texture(args.tex)
    rows = sweep_angle(tex, args.points) + sweep_ratio(tex, args.points, args.repeats)
    meta = (f"{args.points}^2 points, {args.tex}^2 texture, float32, {torch.get_num_threads()} thread(s), "
            f"medians of {args.repeats} rounds, {platform.machine()}")
    md = meta + "\n\n" + table(rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "box_filters.md").write_text(md + "\n")
    plot(rows, out / "box_filters.png", meta)
    print(md)
    if args.docs:
        (ROOT / "docs" / "images").mkdir(parents=True, exist_ok=True)
        shutil.copy(out / "box_filters.png", ROOT / "docs" / "images" / "box_filters.png")
    print(f"\nwritten to {out} in {time.perf_counter() - t0:.0f} s")
    return rows


if __name__ == "__main__":
    main()

"""Speed against accuracy of every difftex filter and its peers, on planes, a sphere and the spot cow.

Scenes (:mod:`difftex.testing.suite`, shared with bench_auto, stability and
the tests; every image ``--res`` x ``--res``, 128 by default):

* ``plane-checker-P`` / ``plane-spot-P``: the ground plane of
  :func:`difftex.testing.grazing_plane` seen ``P`` degrees below the horizon
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
checker over the pixel's exact footprint (:func:`difftex.testing.checker_pixel_box_mean`,
built on :func:`difftex.testing.checker_footprint_mean`, the exact mean over a
parallelogram ``uv + a uv_dx + b uv_dy``, ``a, b in [-1/2, 1/2]``).  Mesh scenes are
scored on the pixels that every supersampling rate covers fully (silhouette
anti-aliasing is not what is measured).

Methods: difftex nearest / bilinear / bicubic (level 0), trilinear,
anisotropic (max_aniso 2, 4, 8, 16), EWA, and "auto", "ripmap" and "sat"
where the installed difftex has them; stochastic trilinear, anisotropic 8
and EWA (``<filter>-sto<k>``, ``sample(..., stochastic=k)``) with one draw
a pixel and the means of 4 and 16 (``--no-stochastic`` leaves them out); peers: ``F.grid_sample`` bilinear at one sample a pixel and
at 2x2, 4x4 and 8x8 supersampled uv (box-averaged), and kornia's
``remap(normalized_coordinates=True, align_corners=False)``.  The peers have
no repeat mode: along a repeating axis the texture is padded by one texel
(circular) and uv folded into [0, 1), clamp is their "border" padding
(:func:`difftex.testing.pad_and_grid`); that is exact and part of their
timed work.

Timing: only the texture lookup (uv and derivatives given; the supersampled
peers get their n^2 uv for free, so their cost in a real renderer, n^2
rasterization and interpolation, is not counted).  Forward under no_grad and
forward + backward of ``sum()`` with gradients to the texture and uv (the
mip filters build the pyramid inside the timed region).  Methods are run
round-robin (:func:`difftex.testing.time_interleaved`, forward and
forward + backward as separate entries), ``--repeats`` rounds a scene in a
new random order each round (so that no method always follows one that
evicts the caches), with a pause before every timed call, and the medians
reported, so that the load drift of a shared machine hits every method alike;
``--threads 1`` by default for the same reason.

Outputs in ``--out`` (default results/speed_vs_accuracy): results.csv
(scene, method, psnr, flip, fwd_ms, fwdbwd_ms), speed_vs_accuracy.png (PSNR
against fwd+bwd time, log axis, Pareto fronts), error_grid.png (per-pixel
error images) and summary.md; ``--docs`` also writes docs/speed_vs_accuracy.md
and copies the PNGs to docs/images/.  FLIP (``pip install flip-evaluator``)
is used where it imports, else the column is empty.

    python -m experiments.studies.speed_vs_accuracy [--res 128] [--repeats 5] [--threads 1] [--docs]
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import platform
import shutil
import statistics
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

import difftex
from difftex.metrics import psnr
from difftex.testing import Scene, build_scenes, grid_sample_lookup, kornia_lookup, time_interleaved
from difftex.texture import options as _sample_mod

ROOT = Path(__file__).resolve().parents[2]

try:  # optional perceptual metric; never a dependency of the package
    import flip_evaluator as _flip
except Exception:  # pragma: no cover - depends on the environment
    _flip = None


# --------------------------------------------------------------------------
# methods
# --------------------------------------------------------------------------


# Stochastic texture filtering (issue 41 point 3): each of these filters with k draws a pixel, k = 1 (the
# PSNR of one draw: what a renderer that filters after shading sees per frame) and the means of 4 and 16.
STOCHASTIC = ("trilinear", "anisotropic-8", "ewa")
DRAWS = (1, 4, 16)
# The draws' generator: seeded once a run, so that a run's images repeat.
_GENERATOR = torch.Generator().manual_seed(0)


def method_names(ss_rates=(2, 4, 8), stochastic: bool = True) -> list[str]:
    """Every method of the experiment; "auto", "ripmap" and "sat" only where difftex.sample has them, the
    stochastic ones ("<filter>-sto<k>") where it has ``stochastic`` and ``stochastic`` is set."""
    names = ["nearest", "bilinear", "bicubic", "trilinear"]
    names += [f"anisotropic-{a}" for a in (2, 4, 8, 16)]
    names += ["ewa"]
    if "auto" in getattr(_sample_mod, "FILTERS", ()):
        names.append("auto")
    names += [f for f in ("ripmap", "sat") if f in getattr(_sample_mod, "FILTERS", ())]
    if stochastic and hasattr(_sample_mod, "check_stochastic"):
        names += [f"{f}-sto{k}" for f in STOCHASTIC for k in DRAWS]
    names += ["grid_sample"] + [f"grid_sample-ss{n}x{n}" for n in ss_rates] + ["kornia"]
    return names


def make_method(name: str, scene: Scene, tex: Tensor, uv: Tensor, uv_ss: dict[int, Tensor]) -> Callable[[], Tensor]:
    """A closure that renders ``scene`` with ``name`` from the leaf tensors given (for gradients)."""
    w = scene.wrap
    dx, dy = scene.uv_dx, scene.uv_dy
    if "-sto" in name:
        base, k = name.rsplit("-sto", 1)
        f, _, a = base.partition("-")
        kw = dict(max_aniso=int(a)) if a else {}
        return lambda: difftex.sample(tex, uv, filter=f, wrap=w, uv_dx=dx, uv_dy=dy, stochastic=int(k),
                                      generator=_GENERATOR, **kw)
    if name in ("nearest", "bilinear", "bicubic"):
        return lambda: difftex.sample(tex, uv, filter=name, wrap=w)
    if name in ("trilinear", "ewa", "auto", "ripmap", "sat"):
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

    def forward(fn):
        def run():
            with torch.no_grad():
                fn()
        return run

    def forward_backward(fn):
        def run():
            for leaf in leaves:
                leaf.grad = None
            fn().sum().backward()
        return run

    # Shuffled rounds: a method timed right after a heavy one (EWA, 8x8) finds its data
    # evicted from the caches (measured: auto, which followed EWA, read up to 1.37x
    # anisotropic-16's forward on the small scenes, against 1.02x when timed alone).
    timed = time_interleaved([forward(fns[m]) for m in methods] + [forward_backward(fns[m]) for m in methods],
                             repeats, shuffle=True)
    fwd, fwdbwd = timed[:len(methods)], timed[len(methods):]
    for i, m in enumerate(methods):
        img = images[m]
        rows.append(dict(scene=scene.name, method=m, psnr=psnr(img, scene.reference, mask=scene.mask),
                         flip=flip_error(img, scene.reference, scene.mask),
                         fwd_ms=fwd[i].median, fwdbwd_ms=fwdbwd[i].median))
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
    lines += ["", *auto_target_lines(rows)]
    return "\n".join(lines)


# The difftex filters a per-pixel choice could draw on (issue 19, part 3).
CHOICES = ("bilinear", "trilinear", "anisotropic-2", "anisotropic-4", "anisotropic-8", "anisotropic-16", "ripmap",
           "sat")


def auto_target_lines(rows: list[dict], ref: str = "anisotropic-16", within: float = 0.5) -> list[str]:
    """Issue 19's target for "auto" (within ``within`` dB of ``ref`` on every scene, at most 0.7x its fwd+bwd
    time in the mean over scenes) against two bounds from the same run: trilinear's time (one tap a pixel,
    the cheapest mip filter), and per scene the cheapest single filter of CHOICES within ``within`` dB of
    ``ref`` (a whole-scene oracle). Empty where the run lacks ``ref`` or "auto"."""
    by = {(r["scene"], r["method"]): r for r in rows}
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    if not all((s, ref) in by and (s, "auto") in by for s in scenes):
        return []
    out = [f"Issue 19's target for auto: within {within} dB of {ref} on every scene, at most 0.7x its fwd+bwd "
           f"time in the mean over scenes. Per scene, fwd+bwd time / {ref}'s (dB against {ref}):", "",
           "| scene | auto | trilinear | cheapest filter within " + f"{within} dB |", "| --- | ---: | ---: | --- |"]
    ratios: dict[str, list[float]] = {"auto": [], "trilinear": [], "oracle": []}
    for s in scenes:
        base = by[(s, ref)]
        rel = lambda m: (by[(s, m)]["fwdbwd_ms"] / base["fwdbwd_ms"], by[(s, m)]["psnr"] - base["psnr"])  # noqa: E731
        ok = [m for m in CHOICES if (s, m) in by and rel(m)[1] >= -within]
        best = min(ok, key=lambda m: rel(m)[0])
        cells = []
        for key, m in (("auto", "auto"), ("trilinear", "trilinear"), ("oracle", best)):
            t, d = rel(m)
            ratios[key].append(t)
            cells.append(f"{m} {t:.2f} ({d:+.1f})" if key == "oracle" else f"{t:.2f} ({d:+.1f})")
        out.append(f"| {s} | " + " | ".join(cells) + " |")
    out.append("| mean | " + " | ".join(f"{statistics.mean(ratios[k]):.2f}" for k in ("auto", "trilinear", "oracle"))
               + " |")
    return out


# The part of docs/speed_vs_accuracy.md that --docs rewrites; the prose around it is kept.
_DOC_START = "<!-- generated by experiments/studies/speed_vs_accuracy.py --docs: start -->"
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
    ap.add_argument("--stochastic", action=argparse.BooleanOptionalAction, default=True,
                    help="the stochastic filters (<filter>-sto<k>: k draws a pixel)")
    ap.add_argument("--only", default="", help="comma-separated methods to run (default: all)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    t_start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    methods = method_names(stochastic=args.stochastic)
    if args.only:
        methods = [m for m in methods if m in args.only.split(",")]
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

"""Minification benchmark: speed and accuracy of the mip filters on the grazing-plane scene.

Scene (the issue's): 256 x 256 image of a ground plane, camera 1 unit up,
looking 20 degrees down (``difftex.testing.grazing_plane``); 1024 x 1024 x 3
checkerboard-plus-noise texture, repeat. Accuracy is PSNR against a 16 x 16
supersampled bilinear render (box filtered). Speed is the median over
repeats of the forward pass and of forward + backward (gradients to the
texture and the uv), next to ``F.grid_sample`` bilinear in the same run; the
mip filters build the pyramid from the texture inside the timed region (its
cost is part of every training step).

Prints a markdown table and writes it to docs/bench_minify.md.

    python -m experiments.bench.bench_minify [--threads 1] [--repeats 9] [--out docs/bench_minify.md]
"""
from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

import torch
import torch.nn.functional as F

import difftex
from difftex.metrics import psnr
from difftex.testing import checker_noise_texture, grazing_plane, grid_sample_lookup, supersampled, time_interleaved

ROOT = Path(__file__).resolve().parents[2]


def _timed_pair(fn, base, repeats: int) -> tuple[float, float, float]:
    """Median ms of ``fn()`` and of ``base()``, timed alternately, and the median of their per-round ratios.

    Alternating keeps both under the same machine load, which on a shared
    CPU drifts by 2-3x within a minute; the ratio is the steadier figure.
    """
    tb, ts = time_interleaved([base, fn], repeats)
    return ts.median, tb.median, ts.ratio_to(tb)


def _no_grad(fn) -> None:
    with torch.no_grad():
        fn()


def _backward(fn, clear) -> None:
    clear()
    fn().sum().backward()


def _torch_path(fn):
    """``fn`` run with difftex's native CPU kernel switched off (as ``DIFFTEX_NATIVE=0`` does)."""
    def run():
        with difftex.backend("grid_sample"):
            return fn()
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1: steadiest on a "
                    "shared 2-core machine; 0 keeps torch's default)")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--tex", type=int, default=1024)
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench_minify.md"))
    args = ap.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    tex0 = checker_noise_texture(args.tex)
    uv0, dx, dy = grazing_plane(args.res, 20.0, 1.0)
    ref = supersampled(tex0, grazing_plane(args.res, 20.0, 1.0, ss=16)[0], 16, "repeat")

    tex = tex0.clone().requires_grad_(True)
    uv = uv0.clone().requires_grad_(True)
    # grid_sample's grid, folded into [0, 1) beforehand (not timed): the
    # cheapest form of a bilinear lookup, the baseline of the ratios.
    grid = (2 * (uv0 - torch.floor(uv0)) - 1).requires_grad_(True)

    def gs():
        return F.grid_sample(tex, grid, mode="bilinear", padding_mode="border", align_corners=False)

    def ss_uv(n):
        return grazing_plane(args.res, 20.0, 1.0, ss=n)[0].requires_grad_(True)

    uv4, uv8 = ss_uv(4), ss_uv(8)

    rows = []  # (name, output fn)
    rows.append(("grid_sample bilinear", gs))
    rows.append(("grid_sample bilinear, 4x4 supersampled",
                 lambda: F.avg_pool2d(grid_sample_lookup(tex, uv4, "repeat"), 4)))
    rows.append(("grid_sample bilinear, 8x8 supersampled",
                 lambda: F.avg_pool2d(grid_sample_lookup(tex, uv8, "repeat"), 8)))
    rows.append(("difftex bilinear", lambda: difftex.sample(tex, uv, filter="bilinear")))
    for name, kw in (("nearest-mip", {}), ("trilinear", {}), ("anisotropic", {"max_aniso": 2}),
                     ("anisotropic", {"max_aniso": 4}),
                     ("anisotropic", {"max_aniso": 16}), ("ewa", {"max_aniso": 4}), ("ewa", {"max_aniso": 16})):
        label = f"difftex {name}" + (f", max_aniso {kw['max_aniso']}" if kw else "")
        rows.append((label, lambda name=name, kw=kw: difftex.sample(tex, uv, filter=name, uv_dx=dx, uv_dy=dy, **kw)))

    # The same filters with the native CPU kernel off (difftex.backend): the torch path.
    for name, kw in (("trilinear", {}), ("anisotropic", {"max_aniso": 2})):
        label = f"difftex {name}" + (f", max_aniso {kw['max_aniso']}" if kw else "") + ", torch path (no native kernel)"
        rows.append((label, _torch_path(lambda name=name, kw=kw: difftex.sample(tex, uv, filter=name, uv_dx=dx,
                                                                                uv_dy=dy, **kw))))

    mm = difftex.mipmap(tex0).levels
    levels = [lv.clone().requires_grad_(True) for lv in mm]
    rows.insert(6, ("difftex trilinear, prebuilt Mipmap (gradient to its levels)",
                    lambda: difftex.sample(difftex.Mipmap(levels), uv, filter="trilinear", uv_dx=dx, uv_dy=dy)))

    def clear():
        tex.grad = uv.grad = grid.grad = None
        for lv in levels:
            lv.grad = None

    def gs_fwd():
        _no_grad(gs)

    def gs_fwd_bwd():
        _backward(gs, clear)

    results = []
    for label, fn in rows:
        with torch.no_grad():
            out = fn()
        score = psnr(grid_sample_lookup(tex0, uv0, "repeat") if label == "grid_sample bilinear" else out, ref)
        reps = args.repeats if "ewa" not in label and "8x8" not in label else max(3, args.repeats // 3)

        def fwd():
            _no_grad(fn)

        def fwd_bwd():
            _backward(fn, clear)

        f_ms, fb_ms, f_ratio = _timed_pair(fwd, gs_fwd, reps)
        b_ms, bb_ms, b_ratio = _timed_pair(fwd_bwd, gs_fwd_bwd, reps)
        results.append((label, score, f_ms, b_ms, f_ratio, b_ratio, fb_ms, bb_ms))
        print(f"{label:60s} {score:6.2f} dB  fwd {f_ms:8.2f} ms ({f_ratio:5.1f}x)  fwd+bwd {b_ms:8.2f} ms "
              f"({b_ratio:5.1f}x)   [grid_sample alongside: {fb_ms:.2f} / {bb_ms:.2f} ms]", flush=True)

    lines = [
        f"Grazing-plane scene: {args.res}x{args.res} image, camera 1 unit above the plane, 20 deg down, "
        f"{args.tex}x{args.tex}x3 checker+noise texture, repeat. PSNR against 16x16 supersampled bilinear. "
        f"Medians of {args.repeats} runs (EWA and 8x8: {max(3, args.repeats // 3)}), "
        f"{torch.get_num_threads()} thread(s), torch {torch.__version__}, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} CPUs. Forward+backward: gradients to texture and uv (mip filters: the pyramid is "
        "built from the texture inside the timed region, except the prebuilt-Mipmap row; the mip filters run "
        "difftex's native CPU kernel except in the torch-path rows). Each row is timed "
        "alternately with grid_sample bilinear (no supersampling, uv folded into [0, 1) beforehand); the "
        "ratio is the median of the per-pair ratios, and the last columns give grid_sample's own medians "
        "during that row, which show the machine's load drift.",
        "",
        "| filter | PSNR (dB) | fwd (ms) | fwd+bwd (ms) | fwd ratio | fwd+bwd ratio | grid_sample fwd / fwd+bwd (ms) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for label, score, f_ms, b_ms, f_ratio, b_ratio, fb_ms, bb_ms in results:
        lines.append(f"| {label} | {score:.2f} | {f_ms:.2f} | {b_ms:.2f} | {f_ratio:.1f}x | {b_ratio:.1f}x | "
                     f"{fb_ms:.2f} / {bb_ms:.2f} |")
    # The two targets, each timed alternately against its own peer
    # (rows measured minutes apart see different machine loads).
    named = dict(rows)
    aniso2 = named["difftex anisotropic, max_aniso 2"]
    ss4 = named["grid_sample bilinear, 4x4 supersampled"]
    trilinear = named["difftex trilinear"]
    lines += ["", "Head to head, each pair timed alternately (medians of the per-pair ratios):", ""]
    for label, fn, peer_label, peer in (
            ("trilinear", trilinear, "grid_sample bilinear", gs),
            ("trilinear, torch path", named["difftex trilinear, torch path (no native kernel)"],
             "grid_sample bilinear", gs),
            ("anisotropic max_aniso 2", aniso2, "grid_sample 4x4 supersampled", ss4),
            ("anisotropic max_aniso 2, torch path",
             named["difftex anisotropic, max_aniso 2, torch path (no native kernel)"], "grid_sample 4x4 supersampled",
             ss4)):
        ratios = []
        for wrap in (lambda f: (lambda: _no_grad(f)), lambda f: (lambda: _backward(f, clear))):
            ratios.append(_timed_pair(wrap(fn), wrap(peer), args.repeats)[2])
        lines.append(f"* {label} / {peer_label}: forward {ratios[0]:.2f}x, forward+backward {ratios[1]:.2f}x")
    table = "\n".join(lines)
    print()
    print(table)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("# Minification benchmark\n\n" + table + "\n")
    print(f"\nwritten to {out}")


if __name__ == "__main__":
    main()

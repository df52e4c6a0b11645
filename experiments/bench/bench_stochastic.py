"""Stochastic filtering's cost against deterministic trilinear: forward + backward, one draw a pixel.

``python -m experiments.bench.bench_stochastic [--res 256] [--tex 512] [--repeats 15] [--suite-res 128]``

Two parts, gradients to the texture and uv in both:

* the grazing plane (``difftex.testing.scenes.grazing_plane``, 20 degrees)
  over a checker-noise texture, every function timed interleaved in rounds
  (``difftex.testing.timing.time_interleaved``, after a pause), medians and
  the per-round ratio to trilinear;
* the scenes of the speed-against-accuracy chart (``difftex.testing.suite``,
  ``--suite-res`` pixels a side), each timed in the steady state of a loop
  (``difftex.testing.time_blocks``: blocks of back-to-back calls, interleaved
  block by block), the per-call ratio to trilinear on that scene, and the
  mean of those ratios over the scenes: issue 41's measure, one draw a
  pixel for at most 1.1x trilinear's forward+backward.

``--suite-res 0`` skips the second part.
"""
from __future__ import annotations

import argparse
import statistics

import torch

from difftex import sample
from difftex.testing import build_scenes, time_blocks
from difftex.testing.scenes import checker_noise_texture, grazing_plane
from difftex.testing.timing import time_interleaved


def _case(tex0, uv0, dx, dy, wrap, filter: str, k: int, g: torch.Generator):
    def fn():
        tex = tex0.clone().requires_grad_()
        uv = uv0.clone().requires_grad_()
        out = sample(tex, uv, filter=filter, wrap=wrap, uv_dx=dx, uv_dy=dy, max_aniso=8, stochastic=k,
                     generator=g)
        out.sum().backward()
    return fn


def plane_table(args) -> None:
    tex0 = checker_noise_texture(args.tex)
    uv0, dx, dy = grazing_plane(args.res, pitch_deg=20.0)
    g = torch.Generator().manual_seed(0)
    cases = [("trilinear", 0), ("trilinear", 1), ("anisotropic", 0), ("anisotropic", 1), ("bicubic", 0),
             ("bicubic", 1)]
    if args.res <= 128:
        cases += [("ewa", 0), ("ewa", 1)]
    timings = time_interleaved([_case(tex0, uv0, dx, dy, "repeat", f, k, g) for f, k in cases],
                               repeats=args.repeats, shuffle=True)
    base = timings[0]
    print(f"{args.res}^2 pixels, {args.tex}^2 texture, {torch.get_num_threads()} threads, fwd+bwd ms")
    print("| filter | stochastic | median ms | IQR ms | x trilinear (per-round median) |")
    print("| --- | --- | --- | --- | --- |")
    for (f, k), t in zip(cases, timings):
        print(f"| {f} | {k} | {t.median:.2f} | {t.spread:.2f} | {t.ratio_to(base):.2f} |")


def suite_table(args) -> None:
    """Per scene of the chart: one draw of each stochastic filter against deterministic trilinear, steady state."""
    scenes = build_scenes(args.suite_res, ss_rates=())
    g = torch.Generator().manual_seed(0)
    cases = [("trilinear", 0), ("trilinear", 1), ("anisotropic", 1)] + [(f, 1) for f in args.extra]
    ratios: dict[tuple, list[float]] = {c: [] for c in cases}
    print(f"\nsuite scenes, {args.suite_res}^2 pixels, {torch.get_num_threads()} threads, fwd+bwd, steady state "
          f"(time_blocks, {args.blocks} blocks)")
    print("| scene | trilinear ms | " + " | ".join(f"{f} x1 / trilinear" for f, _ in cases[1:]) + " |")
    print("| --- | --- | " + " | ".join("---" for _ in cases[1:]) + " |")
    for sc in scenes:
        fns = [_case(sc.texture, sc.uv, sc.uv_dx, sc.uv_dy, sc.wrap, f, k, g) for f, k in cases]
        t = time_blocks(fns, blocks=args.blocks)
        row = []
        for c, tc in zip(cases, t):
            r = tc.ratio_to(t[0])
            ratios[c].append(r)
            if c != cases[0]:
                row.append(f"{r:.2f}")
        print(f"| {sc.name} | {t[0].median:.2f} | " + " | ".join(row) + " |")
    print("| **mean of the ratios** | | " + " | ".join(f"**{statistics.mean(ratios[c]):.3f}**"
                                                    for c in cases[1:]) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--tex", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--suite-res", type=int, default=128, help="pixels a side of the suite scenes (0: skip)")
    ap.add_argument("--blocks", type=int, default=6, help="time_blocks rounds per suite scene")
    ap.add_argument("--extra", nargs="*", default=[], help="more stochastic filters for the suite (ewa, bicubic)")
    ap.add_argument("--plane", action=argparse.BooleanOptionalAction, default=True, help="the grazing-plane table")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave torch's default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.plane:
        plane_table(args)
    if args.suite_res:
        suite_table(args)


if __name__ == "__main__":
    main()

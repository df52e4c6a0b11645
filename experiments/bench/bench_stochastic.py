"""Stochastic filtering's cost against deterministic trilinear: forward + backward, one draw a pixel.

``python -m experiments.bench.bench_stochastic [--res 256] [--tex 512] [--repeats 15]``

A grazing plane (``difftex.testing.scenes.grazing_plane``, 20 degrees) over
a checker-noise texture, gradients to the texture and uv; every function
timed interleaved in rounds (``difftex.testing.timing``), medians and the
per-round ratio to trilinear. Issue 41 asks one draw a pixel for at most
1.1x trilinear's forward+backward.
"""
from __future__ import annotations

import argparse

import torch

from difftex import sample
from difftex.testing.scenes import checker_noise_texture, grazing_plane
from difftex.testing.timing import time_interleaved


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--tex", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave torch's default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    tex0 = checker_noise_texture(args.tex)
    uv0, dx, dy = grazing_plane(args.res, pitch_deg=20.0)
    g = torch.Generator().manual_seed(0)

    def case(filter: str, k: int):
        def fn():
            tex = tex0.clone().requires_grad_()
            uv = uv0.clone().requires_grad_()
            out = sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy, max_aniso=8, stochastic=k, generator=g)
            out.sum().backward()
        return fn

    cases = [("trilinear", 0), ("trilinear", 1), ("anisotropic", 0), ("anisotropic", 1), ("bicubic", 0),
             ("bicubic", 1)]
    if args.res <= 128:
        cases += [("ewa", 0), ("ewa", 1)]
    timings = time_interleaved([case(f, k) for f, k in cases], repeats=args.repeats, shuffle=True)
    base = timings[0]
    print(f"{args.res}^2 pixels, {args.tex}^2 texture, {torch.get_num_threads()} threads, fwd+bwd ms")
    print("| filter | stochastic | median ms | IQR ms | x trilinear (per-round median) |")
    print("| --- | --- | --- | --- | --- |")
    for (f, k), t in zip(cases, timings):
        print(f"| {f} | {k} | {t.median:.2f} | {t.spread:.2f} | {t.ratio_to(base):.2f} |")


if __name__ == "__main__":
    main()

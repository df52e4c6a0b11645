"""Fitting a texture through stochastic filtering: do unbiased one-tap gradients fit as well, per second?

``python -m experiments.studies.stochastic_fit [--steps 150] [--res 96] [--tex 128]``

Targets: the deterministic anisotropic filter (max_aniso 8) of a checker-noise
texture on two closed-form planes (20 and 50 degrees, ``grazing_plane``).
From a grey texture, Adam fits the texture to them with the render made by
each variant: the deterministic anisotropic filter, its stochastic mode
with 1 and 4 draws a pixel (fresh draws every step, seeded), the
"decorrelated" pair (below), and deterministic trilinear (one tap pair a pixel, the cost a stochastic draw
aims at, but the wrong filter for these targets). Reported: the PSNR of the
deterministic anisotropic re-render of the fitted texture against the
targets (what a fit is for), and the seconds of the fit, on the shared
2-core CPU (noisy: compare within one run). The learning rate follows a
cosine decay to 0, which lets a noisy gradient settle.

The stochastic render is unbiased, but a squared error of it is not: the
expected loss is ``(E img - t)^2 + Var(img)``, and the variance term pulls
the fit towards textures that vary less inside each footprint. The
"decorrelated" variant removes it with two independent draws: the gradient
of ``2 (img_a - t) . img_b``, img_a drawn without a graph, is unbiased for
the gradient of ``(E img - t)^2``, the deterministic loss.
"""
from __future__ import annotations

import argparse
import time

import torch

from difftex import sample
from difftex.metrics import psnr
from difftex.testing.scenes import checker_noise_texture, grazing_plane


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--tex", type=int, default=128)
    ap.add_argument("--lr", type=float, default=0.05)
    args = ap.parse_args()
    truth = checker_noise_texture(args.tex, checks=8)
    views = [grazing_plane(args.res, pitch_deg=p, fov_deg=30.0) for p in (20.0, 50.0)]

    def render(tex, filter: str, k: int = 0, g: torch.Generator | None = None):
        return [sample(tex, uv, filter=filter, uv_dx=dx, uv_dy=dy, max_aniso=8, stochastic=k, generator=g)
                for uv, dx, dy in views]

    with torch.no_grad():
        targets = render(truth, "anisotropic")
    variants = [("anisotropic", 0), ("anisotropic", 1), ("anisotropic", 4), ("anisotropic", "1+1 decorrelated"),
                ("trilinear", 0)]
    print(f"{args.steps} Adam steps (lr {args.lr}), {args.tex}^2 texture, two {args.res}^2 views, "
          f"{torch.get_num_threads()} threads")
    print("| render in the fit | draws | re-render PSNR dB (deterministic anisotropic) | fit s |")
    print("| --- | --- | --- | --- |")
    for filter, k in variants:
        tex = torch.full_like(truth, 0.5).requires_grad_()
        opt = torch.optim.Adam([tex], lr=args.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.steps)
        g = torch.Generator().manual_seed(0)
        t0 = time.perf_counter()
        for _ in range(args.steps):
            opt.zero_grad(set_to_none=True)
            if isinstance(k, str):  # two independent draws: residual from one, gradient through the other
                with torch.no_grad():
                    res = [a - t for a, t in zip(render(tex, filter, 1, g), targets)]
                loss = sum((2 * r * b).mean() for r, b in zip(res, render(tex, filter, 1, g)))
            else:
                loss = sum(((img - t) ** 2).mean() for img, t in zip(render(tex, filter, k, g), targets))
            loss.backward()
            opt.step()
            sched.step()
        seconds = time.perf_counter() - t0
        with torch.no_grad():
            out = render(tex.clamp(0, 1), "anisotropic")
            score = sum(float(psnr(o, t)) for o, t in zip(out, targets)) / len(out)
        print(f"| {filter} | {k or 'deterministic'} | {score:.2f} | {seconds:.1f} |")


if __name__ == "__main__":
    main()

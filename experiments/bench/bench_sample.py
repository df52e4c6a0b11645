"""Speed of difftex.sample against torch.nn.functional.grid_sample, measured in the same run.

For a 1024x1024 RGB texture sampled at 512x512 points, batch 1 and 8, forward
and forward+backward (gradients to texture and uv), prints the median ms of
ours and of grid_sample with the same filter and the ratio ours / grid_sample
as a markdown table. The uv is a rotated, scaled view of the texture (the
coherent access pattern of a render); ``--uv random`` gives the worst case.

    python -m experiments.bench.bench_sample [--device cuda] [--uv random] [--out docs/bench_sample.md]
"""
from __future__ import annotations

import argparse
import math

import torch

import difftex
from difftex.testing import grid_sample_lookup, time_interleaved

GS = {"nearest": "nearest", "bilinear": "bilinear", "bicubic": "bicubic"}


def make_uv(B: int, res: int, pattern: str, device: str, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if pattern == "random":
        return torch.rand(B, res, res, 2, generator=g).to(device)
    s = (torch.arange(res, dtype=torch.float32) + 0.5) / res - 0.5
    yy, xx = torch.meshgrid(s, s, indexing="ij")
    uvs = []
    for b in range(B):
        a = math.radians(17 + 11 * b)
        scale = 1.3
        u = scale * (math.cos(a) * xx - math.sin(a) * yy) + 0.5 + 0.01 * b
        v = scale * (math.sin(a) * xx + math.cos(a) * yy) + 0.5
        uvs.append(torch.stack((u, v), -1))
    return torch.stack(uvs).to(device)


def run(device: str, pattern: str, reps: int, filters, batches) -> list[str]:
    rows = ["| filter | B | pass | ours ms | grid_sample ms | ours / grid_sample |", "|---|---|---|---|---|---|"]
    for B in batches:
        tex = torch.rand(1, 3, 1024, 1024, device=device)
        uv = make_uv(B, 512, pattern, device)
        for filt in filters:
            ours = lambda t, u: difftex.sample(t, u, filter=filt, wrap="clamp")
            peer = lambda t, u: grid_sample_lookup(t, u, "clamp", mode=GS[filt])
            for label, grad in (("forward", False), ("forward+backward", True)):
                def step_of(f):
                    t = tex.clone().requires_grad_(grad)
                    u = uv.clone().requires_grad_(grad)

                    def step():
                        out = f(t, u)
                        if grad:
                            out.backward(torch.ones_like(out))
                    return step
                with torch.set_grad_enabled(grad):
                    a, b = (t.median for t in time_interleaved([step_of(ours), step_of(peer)], reps, device=device))
                rows.append(f"| {filt} | {B} | {label} | {a:.1f} | {b:.1f} | {a / b:.2f} |")
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--uv", default="view", choices=["view", "random"])
    p.add_argument("--reps", type=int, default=9)
    p.add_argument("--filters", nargs="+", default=list(GS))
    p.add_argument("--batches", nargs="+", type=int, default=[1, 8])
    p.add_argument("--out", default=None, help="also write the table to this markdown file")
    args = p.parse_args()
    print(f"# torch {torch.__version__}, device {args.device}, threads {torch.get_num_threads()}, uv {args.uv}")
    rows = run(args.device, args.uv, args.reps, args.filters, args.batches)
    if args.out:
        with open(args.out, "w") as f:
            f.write(f"device {args.device}, torch {torch.__version__}, {torch.get_num_threads()} threads, "
                    f"uv pattern {args.uv}\n\n" + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()

"""Fitting at scale: steps per second for 1 and N processes, and peak memory per process by texture size.

Speed: the demo fit (``experiments.fit.fit_texture``) at a small size, once with one plain process and once
per ``--procs`` entry under ``torchrun --standalone`` (gloo on the CPU), each process given
``--threads // P`` intra-op threads so that every run uses the same cores; the same seed and global batch,
so the runs do the same work and end at the same texture. Reads ``steps_per_second`` (the fit loop only)
from each run's metrics.json.

Memory: a capture of spot at ``--mem-res``^2 (2 views, written with ``--make-capture``) is fitted for one step
with a ``N x N`` RGB texture (trilinear, batch 1, no DataLoader workers), one fresh process per size, and its
peak RSS (``resource.getrusage``) is read back; the arithmetic beside it counts what lives across steps (the
texture, its gradient, Adam's two moments: 4 x 12 bytes per texel) and the all-reduce payload per step (the
float32 texture gradient, 12 bytes per texel; a ring all-reduce sends and receives 2 (P - 1) / P of it per
process).

    python -m experiments.bench.bench_fit_scale [--procs 2] [--iters 30] [--res 64] [--memory 1024 4096 8192]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MIB = 1 << 20


def _run(cmd: list[str], threads: int) -> None:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONPATH=str(ROOT))
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stderr[-3000:]}")


def speed(procs: list[int], iters: int, res: int, views: int, batch: int, threads: int, tmp: Path) -> list[dict]:
    rows = []
    for p in [1] + procs:
        out = tmp / f"speed{p}"
        fit = ["-m", "experiments.fit.fit_texture", "--iters", str(iters), "--res", str(res), "--views", str(views),
               "--batch", str(batch), "--eval-views", "2", "--no-progress", "--out", str(out)]
        launcher = ([sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={p}"]
                    if p > 1 else [sys.executable])
        _run(launcher + fit, max(1, threads // p))
        m = json.loads((out / "metrics.json").read_text())
        rows.append({"processes": p, "threads_each": max(1, threads // p), "steps_per_second": m["steps_per_second"],
                     "texture_psnr": m["texture_psnr"], "allreduce_MiB": m["allreduce_bytes_per_step"] / MIB})
    return rows


def memory(sizes: list[int], res: int, threads: int, tmp: Path) -> list[dict]:
    cap = tmp / "capture"
    _run([sys.executable, "-m", "experiments.fit.fit_texture", "--make-capture", str(cap), "--res", str(res),
          "--views", "2"], threads)
    rows = []
    for n in sizes:
        out = tmp / f"mem{n}"
        _run([sys.executable, "-m", "experiments.fit.fit_texture", "--capture", str(cap), "--mesh",
              str(ROOT / "data" / "spot" / "spot_triangulated.obj"), "--tex-size", str(n), "--iters", "1",
              "--batch", "1", "--workers", "0", "--no-progress", "--out", str(out)], threads)
        m = json.loads((out / "metrics.json").read_text())
        texel = n * n * 3 * 4
        rows.append({"texture": n, "peak_rss_MiB": m["peak_rss_bytes"] / MIB, "state_MiB": 4 * texel / MIB,
                     "allreduce_MiB": texel / MIB})
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--procs", type=int, nargs="*", default=[2])
    p.add_argument("--iters", type=int, default=30)
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--views", type=int, default=16)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--memory", type=int, nargs="*", default=[], metavar="N", help="texture sizes to measure")
    p.add_argument("--mem-res", type=int, default=256)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if args.procs:  # `--procs` with no numbers: memory only
            print(f"| processes | threads each | steps/s | texture PSNR (dB) | all-reduce MiB/step |\n|---|---|---|---|---|")
            for r in speed(args.procs, args.iters, args.res, args.views, args.batch, args.threads, tmp):
                print(f"| {r['processes']} | {r['threads_each']} | {r['steps_per_second']:.2f} | "
                      f"{r['texture_psnr']:.3f} | {r['allreduce_MiB']:.0f} |", flush=True)
        if args.memory:
            print(f"\n| texture | peak RSS (MiB) | texture + grad + Adam (MiB) | all-reduce MiB/step |\n|---|---|---|---|")
            for r in memory(args.memory, args.mem_res, args.threads, tmp):
                print(f"| {r['texture']}^2 | {r['peak_rss_MiB']:.0f} | {r['state_MiB']:.0f} | "
                      f"{r['allreduce_MiB']:.0f} |", flush=True)


if __name__ == "__main__":
    main()

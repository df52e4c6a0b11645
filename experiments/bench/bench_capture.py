"""The demo fit against the same views fitted back from disk: wall time and texture PSNR, interleaved.

Writes the demo's training views as a capture (``fit_texture --make-capture``, same ``--res`` / ``--views`` /
``--seed``), then runs, ``--repeats`` times and in alternating order so that a change in the machine's load falls
on both, one fresh process each of:

- ``demo``: ``python -m experiments.fit.fit_texture`` (views rendered in memory, rasterized once);
- ``capture``: ``--capture DIR --mesh spot --reference-texture spot`` with default settings (frames cached in
  memory when they fit ``--cache-mb``, the default);
- ``uncached`` (with ``--uncached``): the same with ``--cache-mb 0`` (images streamed through ``--workers``
  DataLoader workers, every step's views rasterized anew).

Every run has the same iterations, batch, seed and a texture of the demo's size (spot's 1024^2). Wall is the
whole process (start-up, setup, fit, evaluation, writing the outputs), measured here; the fit loop alone is the
run's ``fit_seconds``; CPU is the process's user + system time (``getrusage``), which another load on a shared
machine moves less than the wall time. Prints each run, then per mode the median and range (min..max) and the
ratio to the demo of the same repeat.

    python -m experiments.bench.bench_capture [--repeats 3] [--iters 300] [--uncached]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MESH = ROOT / "data" / "spot" / "spot_triangulated.obj"
TEXTURE = ROOT / "data" / "spot" / "spot_texture.png"


def _run(args: list[str], out: Path) -> dict:
    """One fit in a fresh process; its metrics plus the measured wall and CPU time."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "experiments.fit.fit_texture", *args, "--no-progress", "--out", str(out)],
                       cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    if r.returncode:
        raise RuntimeError(f"fit_texture {' '.join(args)} failed:\n{r.stderr[-3000:]}")
    return dict(json.loads((out / "metrics.json").read_text()), wall=wall, cpu=cpu)


def _spread(xs: list[float]) -> str:
    return f"{statistics.median(xs):.2f} ({min(xs):.2f}..{max(xs):.2f})"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--iters", type=int, default=300)
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--views", type=int, default=48)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--uncached", action="store_true", help="also time --capture with --cache-mb 0")
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error("--repeats: expected at least 1")
    from PIL import Image

    with Image.open(TEXTURE) as im:
        tex_size = im.size[0]  # the demo fits a texture of spot's size
    common = ["--iters", str(args.iters), "--batch", str(args.batch), "--seed", str(args.seed)]
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cap = tmp / "capture"
        subprocess.run([sys.executable, "-m", "experiments.fit.fit_texture", "--make-capture", str(cap), "--res",
                        str(args.res), "--views", str(args.views), "--seed", str(args.seed)], cwd=ROOT, check=True,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True)
        capture = ["--capture", str(cap), "--mesh", str(MESH), "--tex-size", str(tex_size),
                   "--reference-texture", str(TEXTURE), *common]
        modes = {"demo": ["--res", str(args.res), "--views", str(args.views), *common], "capture": capture}
        if args.uncached:
            modes["uncached"] = capture + ["--cache-mb", "0"]
        runs: dict[str, list[dict]] = {m: [] for m in modes}
        print(f"| repeat | mode | wall (s) | CPU (s) | fit loop (s) | texture PSNR (dB) | cached | cache MiB |\n"
              f"|---|---|---|---|---|---|---|---|", flush=True)
        for rep in range(args.repeats):
            order = list(modes) if rep % 2 == 0 else list(modes)[::-1]
            for mode in order:
                m = _run(modes[mode], tmp / f"{mode}{rep}")
                runs[mode].append(m)
                print(f"| {rep} | {mode} | {m['wall']:.2f} | {m['cpu']:.2f} | {m['fit_seconds']:.2f} | "
                      f"{m['texture_psnr']:.3f} | "
                      f"{m.get('cached', '-')} | {m.get('cache_bytes', 0) / 2 ** 20:.1f} |", flush=True)
    print(f"\n{args.repeats} repeats, median (min..max); ratio = mode / demo of the same repeat\n"
          f"| mode | wall (s) | wall ratio | CPU (s) | CPU ratio | fit loop (s) | fit-loop ratio | texture PSNR (dB) "
          f"| PSNR - demo (dB) |\n|---|---|---|---|---|---|---|---|---|")
    demo = runs["demo"]
    for mode, rs in runs.items():
        cols = []
        for key in ("wall", "cpu", "fit_seconds"):
            cols += [_spread([r[key] for r in rs]), _spread([r[key] / q[key] for r, q in zip(rs, demo)])]
        dpsnr = [r["texture_psnr"] - q["texture_psnr"] for r, q in zip(rs, demo)]
        print(f"| {mode} | {' | '.join(cols)} | {statistics.median(r['texture_psnr'] for r in rs):.3f} | "
              f"{max(dpsnr, key=abs):+.3f} |")


if __name__ == "__main__":
    main()

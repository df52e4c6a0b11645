"""Speed and peak memory of difftex.rasterize / interpolate.

Scenes: the spot cow (5,856 triangles) at 256, 512 and 1024 pixels square;
icospheres of 1,280 to 1,310,720 triangles at 512x512; the issue's target
case, a ~100k-triangle sphere at 1024x1024. For each it prints the median ms
of

- ``raster``: ``rasterize(pos, faces, (H, W))`` alone,
- ``fwd``: rasterize + ``interpolate(uv, ..., derivatives=True)`` (what a
  textured render needs before sampling),
- ``fwd+bwd``: that plus ``backward()`` of a loss on uv, uv_dx, uv_dy to
  the clip-space positions and the uv,

and the peak memory of one fwd+bwd: on CPU the growth of the peak resident
set size during the first fwd+bwd of a fresh subprocess (the kernel's
high-water mark is reset just before the call, so loading and other scenes
do not count), ``torch.cuda.max_memory_allocated`` on CUDA.

    python -m experiments.bench.bench_raster [--device cuda] [--reps 5] [--out docs/bench_raster.md]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

SCENES = [
    ("spot", 5856, 256),
    ("spot", 5856, 512),
    ("spot", 5856, 1024),
    ("icosphere", 3, 512),
    ("icosphere", 4, 512),
    ("icosphere", 5, 512),
    ("icosphere", 6, 512),
    ("icosphere", 7, 512),
    ("icosphere", 8, 512),
    ("uvsphere", 160, 1024),
    ("icosphere", 6, 1024),
    ("icosphere", 7, 1024),
]


def _mesh(kind: str, param: int):
    import torch
    import trimesh

    from difftex.testing import SPOT_MESH, icosphere

    uv = None
    if kind == "icosphere":
        V, F = icosphere(param)
    else:
        if kind == "spot":
            m = trimesh.load(str(SPOT_MESH), process=False, force="mesh")
            uv = torch.tensor(m.visual.uv, dtype=torch.float32)
        else:  # uv sphere with 2 * param * param triangles (about)
            m = trimesh.creation.uv_sphere(count=[param, param])
        V = torch.tensor(m.vertices, dtype=torch.float32)
        F = torch.tensor(m.faces, dtype=torch.int64)
    if uv is None:  # spherical uv: any smooth attribute would do
        n = V / V.norm(dim=-1, keepdim=True)
        uv = torch.stack((torch.atan2(n[:, 0], n[:, 2]) / (2 * math.pi) + 0.5, torch.acos(n[:, 1].clamp(-1, 1)) / math.pi), -1)
    return V, F, uv


def _rss_kb(field: str) -> int:
    for line in open("/proc/self/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return -1


def run_one(kind: str, param: int, res: int, device: str, reps: int) -> dict:
    import torch

    import difftex
    from difftex import camera
    from difftex.testing import time_interleaved

    V, F, uv = _mesh(kind, param)
    center = (V.min(0).values + V.max(0).values) / 2
    radius = float((V - center).norm(dim=-1).max())
    eye = center + radius * torch.tensor([1.2, 0.8, 2.3])
    mvp = camera.perspective(45.0, 1.0, 0.1 * radius, 10 * radius, degrees=True) @ camera.look_at(eye, center)
    pos = camera.transform(V, mvp).to(device)
    F, uv = F.to(device), uv.to(device)

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    def raster():
        return difftex.rasterize(pos, F, (res, res))

    def fwd():
        fr = difftex.rasterize(pos, F, (res, res))
        return difftex.interpolate(uv, F, fr, derivatives=True)

    p = pos.clone().requires_grad_(True)
    u = uv.clone().requires_grad_(True)

    def fwdbwd():
        fr = difftex.rasterize(p, F, (res, res))
        val, dx, dy = difftex.interpolate(u, F, fr, derivatives=True)
        (val.square().sum() + dx.abs().sum() + dy.abs().sum()).backward()
        p.grad = None
        u.grad = None

    # Peak memory of the first fwd+bwd, before anything else ran: freed
    # memory the allocator keeps would otherwise hide the peak.
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
        fwdbwd()
        sync()
        peak_mb = (torch.cuda.max_memory_allocated() - base) / 2**20
    else:
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # reset VmHWM to the current RSS
            before = _rss_kb("VmRSS")
            fwdbwd()
            peak_mb = (_rss_kb("VmHWM") - before) / 1024
        except OSError:
            peak_mb = float("nan")

    timings = time_interleaved([raster, fwd, fwdbwd], reps, device=device)
    med = [t.median for t in timings]
    best = [t.min for t in timings]

    fr = raster()
    covered = float((fr.tri_id >= 0).float().mean())
    return {
        "scene": kind,
        "param": param,
        "tris": int(F.shape[0]),
        "res": res,
        "raster_ms": med[0],
        "fwd_ms": med[1],
        "fwdbwd_ms": med[2],
        "raster_min": best[0],
        "fwd_min": best[1],
        "fwdbwd_min": best[2],
        "peak_mb": peak_mb,
        "covered": covered,
        "threads": torch.get_num_threads(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", default=None, help="write the markdown table here")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: kind,param,res
    args = ap.parse_args()

    if args.one:
        kind, param, res = args.one.split(",")
        print(json.dumps(run_one(kind, int(param), int(res), args.device, args.reps)))
        return

    import torch

    rows = []
    for kind, param, res in SCENES:
        out = subprocess.run(
            # As a module from the repository root, like this process (the package imports need it).
            [sys.executable, "-m", "experiments.bench.bench_raster", "--device", args.device, "--reps", str(args.reps),
             "--one", f"{kind},{param},{res}"],
            capture_output=True, text=True, env=dict(os.environ), cwd=ROOT,
        )
        if out.returncode != 0:
            print(out.stderr, file=sys.stderr)
            raise SystemExit(f"{kind} {param} {res} failed")
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(r)
        name = "spot" if kind == "spot" else f"{kind} {param}"
        print(f"{name:>14} {r['tris']:>9,} tris {res:>5}^2  raster {r['raster_ms']:8.1f} ms  fwd {r['fwd_ms']:8.1f} ms  "
              f"fwd+bwd {r['fwdbwd_ms']:8.1f} ms  peak {r['peak_mb']:7.0f} MB  covered {r['covered']:.0%}", flush=True)

    dev = args.device
    if dev == "cpu":
        import platform

        dev_desc = f"CPU ({os.cpu_count()} cores, torch {torch.__version__}, {rows[0]['threads']} threads, {platform.machine()})"
    else:
        dev_desc = torch.cuda.get_device_name()
    lines = [
        f"Device: {dev_desc}; float32; median (min) of {args.reps} runs, ms.",
        "",
        "| scene | triangles | image | rasterize | + interpolate (uv + derivatives) | fwd+bwd | peak MB (fwd+bwd) | pixels covered |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        name = "spot" if r["scene"] == "spot" else (f"icosphere({r['param']})" if r["scene"] == "icosphere" else "uv sphere")
        lines.append(
            f"| {name} | {r['tris']:,} | {r['res']}x{r['res']} | {r['raster_ms']:.1f} ({r['raster_min']:.1f}) | "
            f"{r['fwd_ms']:.1f} ({r['fwd_min']:.1f}) | {r['fwdbwd_ms']:.1f} ({r['fwdbwd_min']:.1f}) | "
            f"{r['peak_mb']:.0f} | {r['covered']:.0%} |"
        )
    lines += [
        "",
        "Columns: `rasterize` alone; `+ interpolate` adds `interpolate(uv, faces, frags, derivatives=True)` "
        "(uv, uv_dx, uv_dy); `fwd+bwd` adds the backward of a loss on all three to the clip-space positions "
        "and the uv. Peak MB: growth of the process's peak memory during the first fwd+bwd of a fresh "
        "process (CPU: resident set high-water mark; CUDA: max_memory_allocated). Camera: 45 degree "
        "perspective looking at the mesh from a fixed oblique direction; no backface culling. "
        "Regenerate with `python -m experiments.bench.bench_raster --out docs/bench_raster.md`.",
    ]
    table = "\n".join(lines)
    print()
    print(table)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(table + "\n")


if __name__ == "__main__":
    main()

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

With ``--peers`` it times instead, on the CPU, ``rasterize`` (native kernel,
also with ``derivatives=False``, and the torch path), ``depth_peel`` of 4
layers, and the peers: Mitsuba 3 (``llvm_ad_rgb``;
``scene.ray_intersect_preliminary`` of one ray through every pixel centre,
the rays built once as Dr.Jit arrays) with its BVH prebuilt, both with
``coherent=True`` (how Mitsuba's own integrators trace camera rays: packet
traversal, 1.4-2.6x faster on these scenes) and with the call's default
``coherent=False``, and with the BVH rebuilt every call (vertex positions
set again and ``params.update()``: a deforming mesh; coherent rays). The
native kernel is compared with the faster prebuilt variant. Each scene runs
once per thread count of ``--threads`` (default 1 and 2: torch's and Dr.Jit's
pools both set to it). It also prints the output bandwidth rasterize achieves:
the bytes of its dense outputs (tri_id int64, bary, depth and, unless
``derivatives=False``, bary_dx, bary_dy) over its median time (the compact
copies for interpolate are written on top and not counted); Mitsuba's
(t, prim_uv, prim_index: 16 bytes a ray) likewise. Scenes: spot at 512^2 and
1024^2, icosphere(8) at 512^2 (``--small``: spot and icosphere(4) at 128^2,
a check that it runs). The main comparison is the steady state of the speed
issues (difftex.testing.time_blocks): ``--blocks`` rounds, each a block of 8
back-to-back calls of every function (shuffled order, a pause before each
block, the first 2 calls untimed: a render or training loop's time, every
library's threads awake); depth_peel against rasterize in blocks of their
own (what ran before decides how many page faults a call pays). Ratios are
the median and quartiles [q1-q3] of the per-call ratios. The first call
after a pause (difftex.testing.time_interleaved, ``--reps`` rounds; the
torch path is timed only there) is a second table. The peers need the
optional ``peers`` extra (``pip install difftex[peers]``); without it they
are skipped with a message. About 2-3 minutes on 2 cores.

    python -m experiments.bench.bench_raster --peers [--small] [--blocks 6] [--reps 9] [--threads 1,2] [--out docs/bench_raster_peers.md]
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


PEER_SCENES = [("spot", 5856, 512), ("spot", 5856, 1024), ("icosphere", 8, 512)]
PEER_SCENES_SMALL = [("spot", 5856, 128), ("icosphere", 4, 128)]


def _view(V):
    """The benchmark camera (as run_one's) and its clip-space float32 positions."""
    import torch

    from difftex import camera

    center = (V.min(0).values + V.max(0).values) / 2
    radius = float((V - center).norm(dim=-1).max())
    eye = center + radius * torch.tensor([1.2, 0.8, 2.3])
    mvp = camera.perspective(45.0, 1.0, 0.1 * radius, 10 * radius, degrees=True) @ camera.look_at(eye, center)
    return mvp, camera.transform(V, mvp)


def _mitsuba_peers(V, F, mvp, res: int):
    """{name: fn} of the Mitsuba ray casts and a function giving its triangle ids, or a message why not."""
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:
        return None, f"Mitsuba 3 / Dr.Jit not installed ({exc}); pip install difftex[peers]"
    import numpy as np
    import torch

    mi.set_variant("llvm_ad_rgb")
    mesh = mi.Mesh("mesh", vertex_count=V.shape[0], face_count=F.shape[0], has_vertex_normals=False,
                   has_vertex_texcoords=False)
    mp = mi.traverse(mesh)
    verts = mi.Float(V.double().numpy().astype(np.float32).ravel())
    mp["vertex_positions"] = verts
    mp["faces"] = mi.UInt32(F.numpy().astype(np.uint32).ravel())
    mp.update()
    scene = mi.load_dict({"type": "scene", "mesh": mesh})
    sp = mi.traverse(scene)
    key = [k for k in sp.keys() if k.endswith("vertex_positions")][0]
    # One ray through every pixel centre (row-major, row 0 at the top), from
    # the near plane to the far plane, as difftex samples them.
    inv = torch.linalg.inv(mvp.double())
    xs = (torch.arange(res, dtype=torch.float64) + 0.5) / res * 2 - 1
    y, x = torch.meshgrid(-xs, xs, indexing="ij")
    ends = []
    for z in (-1.0, 1.0):
        p = torch.stack((x, y, torch.full_like(x, z), torch.ones_like(x)), -1).reshape(-1, 4) @ inv.T
        ends.append(p[:, :3] / p[:, 3:])
    d = ends[1] - ends[0]
    o = mi.Point3f(*[mi.Float(ends[0][:, i].numpy().astype(np.float32)) for i in range(3)])
    dv = mi.Vector3f(*[mi.Float(d[:, i].numpy().astype(np.float32)) for i in range(3)])
    dr.eval(o, dv)

    def cast(coherent: bool = True):
        si = scene.ray_intersect_preliminary(mi.Ray3f(o, dv), coherent=coherent)
        dr.eval(si.t, si.prim_uv, si.prim_index)
        dr.sync_thread()
        return si

    def cast_incoherent():
        return cast(coherent=False)

    # Two evaluated vertex buffers, 1e-6 apart, set in turn: a deforming mesh.
    # (Setting the same buffer again is no change, and update() then keeps
    # the old BVH.)
    moved = [verts, verts + 1e-6]
    dr.eval(moved[1])
    turn = [0]

    def cast_rebuilt():
        turn[0] ^= 1
        sp[key] = moved[turn[0]]
        sp.update()  # rebuilds the BVH (Embree on llvm) before the cast
        return cast()

    def ids():
        si = cast()
        hit = np.asarray(si.t) < float("inf")
        out = np.where(hit, np.asarray(si.prim_index).astype(np.int64), -1)
        return torch.from_numpy(out.reshape(res, res))

    info = f"Mitsuba {mi.__version__} llvm_ad_rgb, Dr.Jit {dr.__version__}"
    return {"mitsuba coherent (prebuilt BVH)": cast, "mitsuba incoherent (prebuilt BVH)": cast_incoherent,
            "mitsuba coherent (BVH rebuilt)": cast_rebuilt, "_ids": ids, "_info": info}, None


def _out_bytes(fr) -> int:
    """Bytes of the dense outputs of a Fragments (the derivatives where present)."""
    return sum(t.numel() * t.element_size() for t in (fr.tri_id, fr.bary, fr.depth, fr.bary_dx, fr.bary_dy)
               if t is not None)


def _ratio(a, b) -> dict:
    """Median and quartiles of the per-call ratios a / b (the k-th timed call of each, same harness call)."""
    import statistics

    r = [x / y for x, y in zip(a.times_ms, b.times_ms)]
    q = statistics.quantiles(r, n=4, method="inclusive") if len(r) > 1 else [r[0]] * 3
    return {"median": statistics.median(r), "q1": q[0], "q3": q[2]}


def run_peers(kind: str, param: int, res: int, reps: int, pause: float, threads: int = 0, blocks: int = 6) -> dict:
    import torch

    import difftex
    from difftex.testing import time_blocks, time_interleaved

    if threads:
        torch.set_num_threads(threads)
        try:
            import drjit as dr

            dr.set_thread_count(threads)
        except ImportError:
            pass
    V, F, _ = _mesh(kind, param)
    mvp, pos = _view(V)
    H = W = res

    def native():
        with difftex.backend("auto"):
            return difftex.rasterize(pos, F, (H, W))

    def native_lean():
        with difftex.backend("auto"):
            return difftex.rasterize(pos, F, (H, W), derivatives=False)

    def torch_path():
        with difftex.backend("reference"):
            return difftex.rasterize(pos, F, (H, W))

    def peel4():
        with difftex.backend("auto"):
            return difftex.depth_peel(pos, F, (H, W), 4)

    fns = {"rasterize (native)": native, "rasterize (native, no derivs)": native_lean}
    peers, why = _mitsuba_peers(V, F, mvp, res)
    out: dict = {"scene": kind, "param": param, "tris": int(F.shape[0]), "res": res,
                 "threads": torch.get_num_threads(), "skipped": why, "blocks": blocks}
    if peers is not None:
        ids = native().tri_id[0]
        out["mitsuba_id_agreement"] = float((peers.pop("_ids")() == ids).double().mean())
        out["peer_info"] = peers.pop("_info")
        fns.update(peers)
    names = list(fns)
    # The main comparison: steady state (blocks of back-to-back calls, interleaved block by block).
    t = time_blocks([fns[n] for n in names], blocks, calls=8, skip=2, pause=pause)
    # Depth peeling against one layer in blocks of their own: both allocate their dense outputs afresh (about
    # 40 MB a layer at 1024^2), and after Mitsuba's allocations the allocator has often handed that memory
    # back to the system, so a call pays its page faults again.
    peel_t, one_t = time_blocks([peel4, native], blocks, calls=8, skip=2, pause=pause)
    by = dict(zip(names, t))
    by["depth_peel 4 (native)"] = peel_t
    out["times"] = {n: {"median": x.median, "iqr": x.spread, "min": x.min} for n, x in by.items()}
    ratios = {"depth_peel 4 / rasterize": _ratio(peel_t, one_t),
              "no derivs / native": _ratio(by["rasterize (native, no derivs)"], by["rasterize (native)"])}
    full_b, lean_b = _out_bytes(native()), _out_bytes(native_lean())
    out["bandwidth_gbs"] = {"rasterize (native)": full_b / by["rasterize (native)"].median / 1e6,
                            "rasterize (native, no derivs)": lean_b / by["rasterize (native, no derivs)"].median / 1e6}
    out["out_bytes"] = {"rasterize (native)": full_b, "rasterize (native, no derivs)": lean_b}
    if peers is not None:
        coh, inc = by["mitsuba coherent (prebuilt BVH)"], by["mitsuba incoherent (prebuilt BVH)"]
        out["mitsuba_faster"] = "coherent" if coh.median <= inc.median else "incoherent"
        ratios["incoherent / coherent (mitsuba)"] = _ratio(inc, coh)
        ratios["native / mitsuba coherent"] = _ratio(by["rasterize (native)"], coh)
        ratios["no derivs / mitsuba coherent"] = _ratio(by["rasterize (native, no derivs)"], coh)
        ratios["native / mitsuba rebuilt"] = _ratio(by["rasterize (native)"], by["mitsuba coherent (BVH rebuilt)"])
        out["bandwidth_gbs"]["mitsuba coherent (prebuilt BVH)"] = 16 * H * W / coh.median / 1e6
    out["ratios"] = ratios
    # The first call after a pause (time_interleaved: other libraries' threads asleep, caches cold), apart;
    # the torch path only here (one call of it takes as long as a block of the others).
    first = {"rasterize (native)": native, "rasterize (native, no derivs)": native_lean,
             "rasterize (torch)": torch_path}
    if peers is not None:
        first["mitsuba coherent (prebuilt BVH)"] = peers["mitsuba coherent (prebuilt BVH)"]
    fnames = list(first)
    ft = dict(zip(fnames, time_interleaved([first[n] for n in fnames], reps, pause=pause, shuffle=True)))
    out["first_call"] = {n: {"median": x.median, "iqr": x.spread} for n, x in ft.items()}
    fr = {"torch path / native": _ratio(ft["rasterize (torch)"], ft["rasterize (native)"])}
    if peers is not None:
        fr["native / mitsuba coherent"] = _ratio(ft["rasterize (native)"], ft["mitsuba coherent (prebuilt BVH)"])
        fr["no derivs / mitsuba coherent"] = _ratio(ft["rasterize (native, no derivs)"],
                                                    ft["mitsuba coherent (prebuilt BVH)"])
    out["first_call_ratios"] = fr
    return out


def _run_scene(flags: list[str]) -> dict:
    """One scene in a fresh process (its own peak memory, no other library's threads): its JSON result line."""
    # As a module from the repository root, like this process (the package imports need it).
    proc = subprocess.run([sys.executable, "-m", "experiments.bench.bench_raster", *flags],
                          capture_output=True, text=True, env=dict(os.environ), cwd=ROOT)
    if proc.returncode != 0:
        print(proc.stderr, file=sys.stderr)
        raise SystemExit(f"{' '.join(flags[-2:])} failed")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _rq(x: dict) -> str:
    return f"{x['median']:.2f} [{x['q1']:.2f}-{x['q3']:.2f}]"


def peers_main(args) -> None:
    rows = []
    thread_counts = [int(t) for t in args.threads.split(",")]
    for kind, param, res in (PEER_SCENES_SMALL if args.small else PEER_SCENES):
        for nt in thread_counts:
            r = _run_scene(["--reps", str(args.reps), "--pause", str(args.pause), "--threads", str(nt),
                            "--blocks", str(args.blocks), "--peer-one", f"{kind},{param},{res}"])
            rows.append(r)
            if r["skipped"]:
                print(f"peers skipped: {r['skipped']}")
            name = "spot" if kind == "spot" else f"icosphere({param})"
            print(f"{name} {r['tris']:,} tris {res}^2, {r['threads']} thread(s), steady state:")
            for n, x in r["times"].items():
                print(f"  {n:>34}: {x['median']:8.2f} ms (IQR {x['iqr']:.2f}, min {x['min']:.2f})")
            for n, x in r["ratios"].items():
                print(f"  {n:>34}: {_rq(x)}x")
            for n, x in r["bandwidth_gbs"].items():
                nb = r["out_bytes"].get(n)
                print(f"  {n:>34}: {x:.2f} GB/s of output" + (f" ({nb / 2**20:.1f} MiB a call)" if nb else
                                                                 " (t, prim_uv, prim_index: 16 B a ray)"))
            print("  first call after a pause:")
            for n, x in r["first_call"].items():
                print(f"  {n:>34}: {x['median']:8.2f} ms (IQR {x['iqr']:.2f})")
            for n, x in r["first_call_ratios"].items():
                print(f"  {n:>34}: {_rq(x)}x")
            if "mitsuba_id_agreement" in r:
                print(f"  triangle ids equal to Mitsuba's on {r['mitsuba_id_agreement']:.4%} of pixels")
            if "mitsuba_faster" in r:
                print(f"  Mitsuba's faster prebuilt variant: {r['mitsuba_faster']}")
    import platform

    def cell(t, n):
        return f"{t[n]['median']:.2f} ({t[n]['iqr']:.2f})" if n in t else "-"

    def ratio(q, n):
        return _rq(q[n]) if n in q else "-"

    def name_of(r):
        return "spot" if r["scene"] == "spot" else f"icosphere({r['param']})"

    lines = [f"CPU ({os.cpu_count()} cores, {platform.machine()}); {rows[0].get('peer_info', 'peers skipped')}; "
             f"float32. Steady state (difftex.testing.time_blocks): {args.blocks} rounds, each a block of 8 "
             f"back-to-back calls of every function in a shuffled order after a {args.pause * 1e3:.0f} ms pause, "
             "the first 2 calls of a block untimed; median (IQR) ms over the timed calls; ratios: median "
             "[q1-q3] of the per-call ratios (k-th timed call against k-th); depth_peel against rasterize in "
             "blocks of their own; GB/s: rasterize's dense outputs (tri_id, bary, depth, bary_dx, bary_dy) over "
             "its median time.",
             "", "| scene | image | threads | rasterize native ms | no derivs ms | depth_peel 4 ms | "
             "Mitsuba coherent ms | Mitsuba incoherent ms | Mitsuba rebuilt ms | native / coherent | "
             "no derivs / coherent | native / rebuilt | native GB/s | peel 4 / 1 |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        t, q = r["times"], r["ratios"]
        lines.append(f"| {name_of(r)} ({r['tris']:,}) | {r['res']}^2 | {r['threads']} | "
                     f"{cell(t, 'rasterize (native)')} | {cell(t, 'rasterize (native, no derivs)')} | "
                     f"{cell(t, 'depth_peel 4 (native)')} | {cell(t, 'mitsuba coherent (prebuilt BVH)')} | "
                     f"{cell(t, 'mitsuba incoherent (prebuilt BVH)')} | {cell(t, 'mitsuba coherent (BVH rebuilt)')} | "
                     f"{ratio(q, 'native / mitsuba coherent')} | {ratio(q, 'no derivs / mitsuba coherent')} | "
                     f"{ratio(q, 'native / mitsuba rebuilt')} | "
                     f"{r['bandwidth_gbs']['rasterize (native)']:.2f} | {ratio(q, 'depth_peel 4 / rasterize')} |")
    lines += ["", f"First call after a {args.pause * 1e3:.0f} ms pause (difftex.testing.time_interleaved, "
              f"{args.reps} shuffled rounds; other libraries' threads asleep, caches cold): median (IQR) ms, "
              "ratios median [q1-q3] of per-round ratios.", "",
              "| scene | image | threads | rasterize native ms | no derivs ms | torch path ms | Mitsuba coherent ms | "
              "native / coherent | no derivs / coherent | torch path / native |",
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        t, q = r["first_call"], r["first_call_ratios"]
        lines.append(f"| {name_of(r)} ({r['tris']:,}) | {r['res']}^2 | {r['threads']} | "
                     f"{cell(t, 'rasterize (native)')} | {cell(t, 'rasterize (native, no derivs)')} | "
                     f"{cell(t, 'rasterize (torch)')} | {cell(t, 'mitsuba coherent (prebuilt BVH)')} | "
                     f"{ratio(q, 'native / mitsuba coherent')} | {ratio(q, 'no derivs / mitsuba coherent')} | "
                     f"{ratio(q, 'torch path / native')} |")
    table = "\n".join(lines)
    print()
    print(table)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(table + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", default=None, help="write the markdown table here")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: kind,param,res
    ap.add_argument("--peers", action="store_true", help="time against Mitsuba 3 (see above)")
    ap.add_argument("--small", action="store_true", help="with --peers: small scenes only (a check that it runs)")
    ap.add_argument("--pause", type=float, default=0.05, help="with --peers: seconds slept before each timed call")
    ap.add_argument("--threads", default="1,2", help="with --peers: thread counts, comma-separated (torch and Dr.Jit)")
    ap.add_argument("--blocks", type=int, default=6, help="with --peers: steady-state rounds (blocks of 8 calls)")
    ap.add_argument("--peer-one", default=None, help=argparse.SUPPRESS)  # internal: kind,param,res
    args = ap.parse_args()

    if args.peer_one:
        kind, param, res = args.peer_one.split(",")
        print(json.dumps(run_peers(kind, int(param), int(res), args.reps, args.pause, int(args.threads),
                                   args.blocks)))
        return
    if args.peers:
        if args.device != "cpu":
            raise SystemExit("--peers times the CPU (Mitsuba's llvm variant)")
        peers_main(args)
        return

    if args.one:
        kind, param, res = args.one.split(",")
        print(json.dumps(run_one(kind, int(param), int(res), args.device, args.reps)))
        return

    import torch

    rows = []
    for kind, param, res in SCENES:
        r = _run_scene(["--device", args.device, "--reps", str(args.reps), "--one", f"{kind},{param},{res}"])
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

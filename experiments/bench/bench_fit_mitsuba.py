"""The main job beside the tool a user would otherwise pick: spot's texture fitted with difftex's filters and
with Mitsuba 3 doing the same fit, texture PSNR against wall time, in one run.

The fit is the demo's (experiments/fit/fit_texture.py): 48 views of spot at 128^2 (the views ``--make-capture``
writes: the same cameras, rendered with difftex's EWA filter), 300 steps of 8 views, Adam, texture PSNR over the
texels the views see. What each tool's result comes from:

* **difftex** rasterizes each view once and reads the texture through a mip filter (trilinear, anisotropic,
  EWA): one lookup a pixel that averages the texels under the pixel's footprint, so the gradient of a pixel
  reaches every texel it covers, in one sample.
* **Mitsuba 3** (``llvm_ad_rgb``, the ``peers`` extra) renders the mesh as an area emitter whose radiance is
  the texture (a ``bitmap``, bilinear: Mitsuba has no mip filtering of a differentiable bitmap), with the
  ``prb`` integrator at max depth 1 (the emitted radiance at the first hit, nothing else), a box pixel filter,
  and ``spp`` rays a pixel (4, 16, 64): a minified pixel's footprint is covered by supersampling, so its
  gradient reaches spp texel neighbourhoods of the footprint, and the noise of the estimate falls as
  1 / sqrt(spp). ``mi.ad.Adam`` with its own learning rate (``--mi-lr``, 0.1: tuned for it), the texture
  clamped to [0, 1] after each step as in Mitsuba's tutorials, one ``mi.render`` a view (each its own seed).

Before fitting, the script checks the set-up: Mitsuba renders the true texture through every camera at 64 spp
and the image PSNR against the views difftex rendered must be high (a misaligned camera or a flipped v gives
under 20 dB); it prints the figure.

Dr.Jit 1.5 emits ``llvm.minimum``, which Debian 12's LLVM 15 cannot compile ("LLVM ERROR: Cannot select:
fminimum") in the differentiable integrators: the script points ``DRJIT_LIBLLVM_PATH`` at the newest libLLVM it
finds (``DRJIT_LIBLLVM_PATH`` if set, then a Rust toolchain's, then the system's) and prints which; without
mitsuba / drjit it prints why and runs difftex alone.

    python -m experiments.bench.bench_fit_mitsuba [--iters 300] [--spp 4 16 64] [--out docs/fit_peers.md]

Writes a table (markdown) and a chart (PSNR against wall time, ``--chart``, default docs/images/fit_peers.png).
"""
from __future__ import annotations

import argparse
import glob
import os
import re
import time
from pathlib import Path

import torch

LIBLLVM_GLOBS = [
    os.path.expanduser("~/.rustup/toolchains/*/lib/libLLVM*.so*"),
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
]


def pick_libllvm() -> str | None:
    """The libLLVM Dr.Jit should load: DRJIT_LIBLLVM_PATH if set, else the newest found (major >= 16)."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    best = None
    for pattern in LIBLLVM_GLOBS:
        for path in glob.glob(pattern):
            m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
            if m and int(m.group(1)) >= 16 and (best is None or int(m.group(1)) > best[0]):
                best = (int(m.group(1)), path)
    if best is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = best[1]
        return best[1]
    return None


def load_mitsuba():
    """(mitsuba, drjit, the libLLVM used) with llvm_ad_rgb set, or (None, None, why) where it cannot run."""
    lib = pick_libllvm()
    try:
        import drjit as dr
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
    except Exception as exc:  # not installed, or no usable LLVM
        return None, None, f"mitsuba unavailable ({type(exc).__name__}: {exc}); install the peers extra"
    return mi, dr, lib or "the default libLLVM (none newer than 15 found: the prb integrator may abort)"


def write_ply(path: Path, mesh) -> None:
    """``mesh`` as a binary PLY with one uv a vertex (Mitsuba's meshes carry one): each (position, uv) corner
    pair of the face-varying mesh becomes a vertex. uv is written as difftex holds it (v down the rows,
    DESIGN.md) and the bitmap given in difftex's row order: Mitsuba's PLY loader and bitmap agree with that
    (checked by check_alignment; 1 - v gives 13-28 dB instead of 28-35 dB)."""
    import numpy as np

    pairs = torch.stack([mesh.faces.reshape(-1), mesh.uv_faces.reshape(-1)], 1)
    uniq, inverse = torch.unique(pairs, dim=0, return_inverse=True)
    pos = mesh.positions[uniq[:, 0]].float().numpy()
    uv = mesh.uv[uniq[:, 1]].float().numpy()
    faces = inverse.reshape(-1, 3).numpy().astype(np.int32)
    vert = np.zeros(len(pos), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("u", "<f4"), ("v", "<f4")])
    vert["x"], vert["y"], vert["z"] = pos[:, 0], pos[:, 1], pos[:, 2]
    vert["u"], vert["v"] = uv[:, 0], uv[:, 1]
    face = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, faces
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vert)}\nproperty float x\n"
              "property float y\nproperty float z\nproperty float u\nproperty float v\n"
              f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vert.tobytes())
        f.write(face.tobytes())


def mitsuba_scene(mi, ply: Path, texture: torch.Tensor):
    """The scene: the mesh as an area emitter whose radiance is ``texture`` ([1, 3, H, W], given channels-last
    as Mitsuba holds a bitmap), prb at max depth 1."""
    data = mi.TensorXf(texture[0].permute(1, 2, 0).contiguous().numpy())
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 1},
        "spot": {"type": "ply", "filename": str(ply), "face_normals": True,
                 "emitter": {"type": "area", "radiance": {"type": "bitmap", "data": data, "raw": True,
                                                          "filter_type": "bilinear", "wrap_mode": "repeat"}}},
    })


def mitsuba_sensor(mi, view: torch.Tensor, fov_deg: float, res: int, spp: int):
    """A perspective sensor for difftex's world -> view matrix (OpenGL: the camera looks down -z, x right, y up).

    Mitsuba's camera looks down +z with x to the left of the image, so its to_world is the inverse view with
    x and z negated."""
    c2w = torch.linalg.inv(view.double()) @ torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64))
    return mi.load_dict({
        "type": "perspective", "fov": fov_deg, "fov_axis": "y", "near_clip": 0.1, "far_clip": 100.0,
        "to_world": mi.ScalarTransform4f(c2w.tolist()),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                 "pixel_format": "rgb"},
    })


KEY = "spot.emitter.radiance.data"


def to_torch(x) -> torch.Tensor:
    """A Mitsuba [H, W, C] image or bitmap as a torch [1, C, H, W] float32 tensor."""
    return torch.tensor(x.numpy()).permute(2, 0, 1)[None].float()


def check_alignment(mi, scene, sensors, targets: torch.Tensor, spp: int = 64) -> float:
    """Mean image PSNR of Mitsuba's render of the true texture against difftex's views (the set-up check)."""
    from difftex.metrics import psnr

    return sum(psnr(to_torch(mi.render(scene, sensor=s, spp=spp)), targets[i:i + 1])
               for i, s in enumerate(sensors)) / len(sensors)


def fit_mitsuba(mi, dr, ply: Path, view: torch.Tensor, targets: torch.Tensor, true_tex: torch.Tensor,
                seen: torch.Tensor, *, spp: int, iters: int, batch: int, lr: float, seed: int, res: int,
                fov_deg: float, progress: bool) -> dict:
    """The demo's fit in Mitsuba: the texture of an area emitter, ``iters`` steps of ``batch`` views."""
    from tqdm import tqdm

    from difftex.metrics import psnr

    t0 = time.perf_counter()
    scene = mitsuba_scene(mi, ply, torch.full_like(true_tex, 0.5))
    sensors = [mitsuba_sensor(mi, v, fov_deg, res, spp) for v in view]
    goal = [mi.TensorXf(t.permute(1, 2, 0).contiguous().numpy()) for t in targets]
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=lr)
    opt[KEY] = params[KEY]
    params.update(opt)
    g = torch.Generator().manual_seed(seed + 1)
    order: list[int] = []
    curve: list[tuple[int, float, float]] = []  # (step, wall seconds, texture PSNR)
    every, scoring = max(1, iters // 12), 0.0
    for step in tqdm(range(iters), desc=f"mitsuba spp {spp}", disable=not progress):
        if len(order) < batch:
            order += torch.randperm(len(sensors), generator=g).tolist()
        idx, order = order[:batch], order[batch:]
        for j, i in enumerate(idx):
            img = mi.render(scene, params, sensor=sensors[i], spp=spp, seed=step * batch + j)
            dr.backward(dr.mean(dr.square(img - goal[i])) / batch)
        opt.step()
        opt[KEY] = dr.clip(opt[KEY], 0.0, 1.0)
        params.update(opt)
        if (step + 1) % every == 0 or step + 1 == iters:  # the scoring's time is left out of the wall time
            t = time.perf_counter()
            curve.append((step + 1, t - t0 - scoring, psnr(to_torch(params[KEY]), true_tex, mask=seen)))
            scoring += time.perf_counter() - t
    best = max(curve, key=lambda c: c[2])
    return {"tool": "Mitsuba 3", "setting": f"prb, spp {spp}, lr {lr}", "texture_psnr": curve[-1][2],
            "seconds": curve[-1][1], "best": best, "curve": curve}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iters", type=int, default=300)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--filters", nargs="+", default=["trilinear", "anisotropic", "ewa"])
    ap.add_argument("--spp", nargs="+", type=int, default=[4, 16, 64])
    ap.add_argument("--lr", type=float, default=0.03, help="difftex's Adam learning rate (the demo's)")
    ap.add_argument("--mi-lr", type=float, default=0.1, help="Mitsuba's Adam learning rate")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="also write the table to this markdown file")
    ap.add_argument("--chart", default="docs/images/fit_peers.png", help="PSNR against wall time (PNG)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)

    import difftex
    from difftex.testing.meshes import spot_mesh, spot_texture
    from experiments.fit.fit_texture import fit, random_cameras, render_all, seen_texels

    torch.set_num_threads(min(2, torch.get_num_threads()))
    rows = []
    for f in args.filters:
        m = fit(f, args.iters, args.res, args.views, args.batch, args.lr, args.seed, save=False,
                progress=not args.no_progress)
        rows.append({"tool": "difftex", "setting": f"{f}, lr {args.lr}", "texture_psnr": m["texture_psnr"],
                     "seconds": m["seconds"]})
        print(f"difftex {f}: {m['texture_psnr']:.2f} dB in {m['seconds']:.1f} s", flush=True)

    mi, dr, lib = load_mitsuba()
    if mi is None:
        print(f"# Mitsuba skipped: {lib}")
    else:
        print(f"# Mitsuba {mi.__version__}, Dr.Jit {dr.__version__}, llvm_ad_rgb, libLLVM: {lib}")
        mesh, true_tex = spot_mesh(), spot_texture()
        proj, view = random_cameras(args.views, args.seed)
        target_model = difftex.TexturedMesh(mesh, true_tex, filter="ewa", learn_texture=False)
        targets = render_all(target_model, target_model.rasterize(proj @ view, (args.res, args.res)), args.batch)
        seen = seen_texels(target_model, proj @ view, args.res)
        work = Path(os.environ.get("TMPDIR", "/tmp")) / f"difftex-mitsuba-{os.getpid()}"
        work.mkdir(parents=True, exist_ok=True)
        ply = work / "spot.ply"
        write_ply(ply, mesh)
        fov = 40.0  # random_cameras' default
        sensors = [mitsuba_sensor(mi, v, fov, args.res, 64) for v in view[:8]]
        align = check_alignment(mi, mitsuba_scene(mi, ply, true_tex), sensors, targets[:8])
        print(f"# set-up check: Mitsuba's render of the true texture (64 spp) against difftex's views: "
              f"{align:.1f} dB image PSNR (silhouettes differ: Mitsuba antialiases them, the views do not)")
        for spp in args.spp:
            r = fit_mitsuba(mi, dr, ply, view, targets, true_tex, seen, spp=spp, iters=args.iters,
                            batch=args.batch, lr=args.mi_lr, seed=args.seed, res=args.res, fov_deg=fov,
                            progress=not args.no_progress)
            rows.append(r)
            print(f"Mitsuba spp {spp}: {r['texture_psnr']:.2f} dB in {r['seconds']:.1f} s (best "
                  f"{r['best'][2]:.2f} dB at step {r['best'][0]}, {r['best'][1]:.1f} s)", flush=True)

    lines = [f"# {args.views} views at {args.res}^2, {args.iters} steps of {args.batch} views, torch "
             f"{torch.__version__}, {torch.get_num_threads()} threads; wall time includes set-up "
             "(targets, rasterization or scene load, kernel compilation)",
             "| tool | setting | texture PSNR (dB) | wall time (s) | best PSNR on the way (dB, at step, s) |",
             "|---|---|---:|---:|---|"]
    lines += [f"| {r['tool']} | {r['setting']} | {r['texture_psnr']:.2f} | {r['seconds']:.1f} | "
              + (f"{r['best'][2]:.2f} at {r['best'][0]}, {r['best'][1]:.1f} s" if "best" in r else "") + " |"
              for r in rows]
    table = "\n".join(lines)
    print(table)
    if args.out:
        Path(args.out).write_text(table + "\n")
    if args.chart:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for r in rows:  # Mitsuba's PSNR on the way: a line per spp
            if "curve" in r:
                ax.plot([c[1] for c in r["curve"]], [c[2] for c in r["curve"]], color="tab:orange", alpha=0.4,
                        lw=1)
        for tool, marker in (("difftex", "o"), ("Mitsuba 3", "s")):
            pts = [r for r in rows if r["tool"] == tool]
            if pts:
                ax.scatter([r["seconds"] for r in pts], [r["texture_psnr"] for r in pts], marker=marker,
                           label=tool)
                for r in pts:
                    ax.annotate(r["setting"].split(",")[0] if tool == "difftex" else r["setting"].split(",")[1],
                                (r["seconds"], r["texture_psnr"]), textcoords="offset points", xytext=(4, 4),
                                fontsize=8)
        ax.set_xscale("log")
        ax.set_xlabel("wall time (s, log)")
        ax.set_ylabel("texture PSNR (dB)")
        ax.set_title("spot's texture from 48 views: difftex and Mitsuba 3")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.chart, dpi=120)
        print(f"wrote {args.chart}")


if __name__ == "__main__":
    main()

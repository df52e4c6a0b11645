"""Fit the spot cow's texture to photographs of it, by gradient descent through difftex.

Like nvdiffrast's earth sample: target images are rendered from the true
texture with the most accurate filter (EWA) over random views at a wide
range of distances (2 to 16 units: at the default 128x128 the median
footprint of a view spans 3 to 39 texels of the 1024x1024 texture) and angles; the fitted texture starts
constant grey and Adam updates it so that renders with ``--filter`` match
the targets. Rasterization is done once, since only the texture changes.

Writes to ``--out``: metrics.json ({"filter", "iters", "texture_psnr",
"image_psnr" (on 16 held-out views), "train_image_psnr", "seconds", ...}), views.png (target / fit / error for a few
views), texture.png (fitted | true | seen-texel mask), curves.png (loss and
texture PSNR).

    python -m experiments.fit.fit_texture [--filter trilinear] [--iters 300] [--res 128] [--views 48]

Captures on disk (difftex.io.capture, the transforms.json convention of Blender / instant-ngp / nerfstudio):
``--make-capture DIR`` writes the bundled spot views (the demo's training views, with the coverage as alpha)
as one; ``--capture DIR --mesh MESH [--tex-size 1024]`` fits a texture to a capture. The mesh does not move, so
when every frame's fragments and image fit ``--cache-mb`` (experiments/fit/frame_cache.py) each frame is
rasterized and loaded once and the steps gather from memory, as the demo does; otherwise (``--cache-mb 0``, or a
capture too big) the images stream through a DataLoader (``--workers``) and each step's views are rasterized
anew, so a capture need not fit in memory. Both give the same batches, so the same texture. Frames whose camera
sees nothing of the mesh are skipped with a warning; other bad frames raise unless ``--skip-bad``.

Scale (experiments/fit/runtime.py): ``torchrun --nproc-per-node N -m experiments.fit.fit_texture ...`` splits each
step's global batch over N processes (gloo on the CPU, nccl on CUDA) and averages the gradients with an all-reduce;
rank 0 writes the outputs. ``--checkpoint-every K`` writes ``OUT/checkpoint.pt`` atomically every K steps (and at
the end); ``--resume`` continues from it, ending at the same texture as an uninterrupted run.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Iterator

import warnings

import torch
from tqdm import tqdm

import difftex
from difftex import Fragments, camera
from difftex.metrics import psnr
from difftex.io.capture import CaptureDataset, CaptureWarning, load_capture, save_capture, visible_frames
from difftex.testing import spot_mesh, spot_texture
from experiments.fit import frame_cache, runtime
from experiments.fit.runtime import Dist, StepSampler

FILTERS = ("bilinear", "trilinear", "anisotropic", "ewa", "auto")
# --capture's default budget for the frames held in memory (MiB, per process): the demo's 48 views at 128^2 take
# 18 MiB; 512 holds e.g. 250 frames at 256^2 where the object covers a quarter of each (images and masks 16 B a
# pixel, fragments 44 B a covered pixel), about what a 1024^2 fit itself peaks at.
CACHE_MB = 512.0


def random_cameras(n: int, seed: int, dist_range=(2.0, 16.0), fov_deg: float = 40.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(projection [4, 4], world -> view [n, 4, 4]) of cameras looking at spot from random directions and distances."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    lo, hi = math.log(dist_range[0]), math.log(dist_range[1])
    dist = torch.exp(torch.rand(n, 1, generator=g) * (hi - lo) + lo)
    at = torch.tensor([0.0, 0.1, 0.2])  # centre of spot's bounding box
    eye = at + d * dist
    up = torch.where(d[:, 1:2].abs() > 0.95, torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    proj = camera.perspective(fov_deg, 1.0, 0.1, 100.0, degrees=True)
    return proj, camera.look_at(eye, at.expand(n, 3), up)


def random_views(n: int, seed: int, dist_range=(2.0, 16.0), fov_deg: float = 40.0) -> torch.Tensor:
    """[n, 4, 4] world -> clip matrices looking at spot from random directions and distances."""
    proj, view = random_cameras(n, seed, dist_range, fov_deg)
    return proj @ view


def select(frags: Fragments, idx: torch.Tensor) -> Fragments:
    """The fragments of the views ``idx``."""
    return Fragments(*(getattr(frags, f)[idx] for f in ("tri_id", "bary", "depth", "bary_dx", "bary_dy")))


def seen_texels(model: difftex.TexturedMesh, mvp: torch.Tensor, res: int | tuple[int, int]) -> torch.Tensor:
    """[1, 1, H, W] bool: texels that a bilinear lookup at 4x the resolution (res or (H, W)) touches in some view."""
    size = (4 * res, 4 * res) if isinstance(res, int) else (4 * res[0], 4 * res[1])
    tex = model.texture.detach().clone().requires_grad_()
    probe = difftex.TexturedMesh(difftex.Mesh(model.positions, model.faces, model.uv, model.uv_faces), tex,
                                 filter="bilinear", wrap=model.wrap, learn_texture=False)
    probe.texture.requires_grad_()
    for chunk in torch.split(torch.arange(mvp.shape[0]), 8):
        img, _ = probe(mvp[chunk], size)
        img.sum().backward()
    return (probe.texture.grad.abs().sum(1, keepdim=True) > 0)


def render_all(model, frags: Fragments, batch: int) -> torch.Tensor:
    with torch.no_grad():
        return torch.cat([model(frags=select(frags, idx))[0] for idx in torch.split(torch.arange(frags.tri_id.shape[0]), batch)])


def peak_rss_bytes() -> int | None:
    """This process's peak resident memory so far (resource.getrusage; None where it is unavailable)."""
    try:
        import resource
    except ImportError:  # Windows
        return None
    import sys

    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)  # macOS reports bytes, Linux KiB


def _check_resume(saved: dict, config: dict) -> None:
    diff = {k: (saved.get(k), v) for k, v in config.items() if saved.get(k) != v}
    if diff:
        raise ValueError(f"--resume: the checkpoint was written by a run with other settings "
                         f"(checkpoint, now): {diff}; use the same settings or another --out")


def train(model: difftex.TexturedMesh, batches, sampler: StepSampler, config: dict, d: Dist, *,
          out: Path | None, checkpoint_every: int = 0, resume: bool = False, score=None,
          progress: bool = True, desc: str = "fit") -> dict:
    """Adam on the texture (and uv) over ``config["iters"]`` steps; the loop every mode of this script shares.

    ``batches(share)`` returns ``(images, targets, weight or None)`` for this process's views of a step; the
    loss is the global batch's mean squared error (each process's mean over its equal share, / world),
    gradients are summed over the processes. ``score()`` (rank 0) gives the texture PSNR logged every 10
    steps. With ``checkpoint_every`` > 0, rank 0 writes ``out/checkpoint.pt`` every that many steps and at
    the end; ``resume`` starts from it. Returns ``{"curve", "fit_seconds", "steps", "allreduce_bytes"}``.
    """
    iters, lr = config["iters"], config["lr"]
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, iters, eta_min=lr * 0.05)
    curve = {"iter": [], "loss": [], "texture_psnr": []}
    start = 0
    if resume:
        ck = runtime.load_checkpoint(out) if out is not None else None
        if ck is not None:
            _check_resume(ck["config"], config)
            with torch.no_grad():
                model.texture.copy_(ck["texture"])
                model.uv.copy_(ck["uv"])
            opt.load_state_dict(ck["optimizer"])
            sched.load_state_dict(ck["scheduler"])
            torch.set_rng_state(ck["rng"]["torch"])
            if not torch.equal(ck["rng"]["sampler"], sampler.state_at(ck["step"])):
                raise ValueError("--resume: the checkpoint's sampler state differs from a replay of the seed")
            curve, start = ck["curve"], ck["step"]
    sampler.start = start
    params = [p for p in model.parameters() if p.requires_grad]
    allreduce_bytes = sum(p.numel() * p.element_size() for p in params) if d.world > 1 else 0
    t_fit = time.perf_counter()
    bar = tqdm(range(start, iters), disable=not (progress and d.main), desc=desc)
    for it, share in zip(bar, batches):
        img, target, weight = share
        err = (img - target) ** 2
        loss = torch.mean(err if weight is None else weight * err) / d.world
        opt.zero_grad(set_to_none=True)
        loss.backward()
        runtime.all_reduce_grads(params, d)
        opt.step()
        sched.step()
        with torch.no_grad():
            model.texture.clamp_(0, 1)
        if it % 10 == 0 or it == iters - 1:
            loss_all = runtime.reduce_sum(loss.item(), d)
            if d.main:
                tp = score() if score is not None else float("nan")
                curve["iter"].append(it)
                curve["loss"].append(loss_all)
                curve["texture_psnr"].append(tp)
                bar.set_postfix(loss=f"{loss_all:.2e}", tex_psnr=f"{tp:.2f}")
        if checkpoint_every and ((it + 1) % checkpoint_every == 0 or it == iters - 1):
            if d.main:
                runtime.save_checkpoint(out, {
                    "step": it + 1, "texture": model.texture.detach(), "uv": model.uv.detach(),
                    "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                    "rng": {"torch": torch.get_rng_state(), "sampler": sampler.state_at(it + 1)},
                    "config": config, "curve": curve})
            runtime.barrier(d)
        runtime.maybe_kill_at(it)
    return {"curve": curve, "fit_seconds": time.perf_counter() - t_fit, "steps": iters - start,
            "allreduce_bytes": allreduce_bytes}


def fit(filter: str = "trilinear", iters: int = 300, res: int = 128, views: int = 48, batch: int = 8,
        lr: float = 0.03, seed: int = 0, out: str | Path = "results/fit_texture", target_filter: str = "ewa",
        eval_views: int = 16, progress: bool = True, save: bool = True, *, checkpoint_every: int = 0,
        resume: bool = False, device: str = "cpu", stochastic: int = 0, decorrelate: bool = True) -> dict:
    """Run one fit of the demo (spot's views rendered in memory) and return its metrics (also written to
    ``out``/metrics.json when ``save``; under torchrun only rank 0 writes and returns them, the others
    return {}). ``stochastic`` / ``decorrelate``: the fitted model's stochastic filtering
    (:class:`difftex.TexturedMesh`; 0: the deterministic filter); the targets and the scores stay
    deterministic."""
    d = runtime.setup(device)
    dev = d.device
    torch.manual_seed(seed)
    mesh = spot_mesh()
    true_tex = spot_texture().to(dev)
    mvp = random_views(views, seed).to(dev)
    difftex._native.load()  # the native CPU kernel's first-use build stays out of the timings

    t0 = time.perf_counter()
    target_model = difftex.TexturedMesh(mesh, true_tex, filter=target_filter, learn_texture=False).to(dev)
    frags = target_model.rasterize(mvp, (res, res))
    targets = render_all(target_model, frags, batch)
    if d.main:
        seen = seen_texels(target_model, mvp, res)
        # Held-out views: a filter that only fits the texels its training pixels
        # happen to read (bilinear under minification) shows it here.
        eval_frags = target_model.rasterize(random_views(eval_views, seed + 1000).to(dev), (res, res))
        eval_targets = render_all(target_model, eval_frags, batch)

    init = torch.full_like(true_tex, 0.5)
    model = difftex.TexturedMesh(mesh, init, filter=filter, stochastic=stochastic, decorrelate=decorrelate,
                                 seed=seed).to(dev)
    config = {"mode": "demo", "filter": filter, "iters": iters, "res": res, "views": views, "batch": batch,
              "lr": lr, "seed": seed, "target_filter": target_filter, "stochastic": stochastic,
              "decorrelate": decorrelate}
    sampler = StepSampler(views, batch, seed + 1, iters, d)

    def batches():
        for share in sampler:
            idx = torch.tensor(share, device=dev)
            img, _ = model(frags=select(frags, idx))
            yield img, targets[idx], None

    score = (lambda: psnr(model.texture.detach(), true_tex, mask=seen)) if d.main else None
    run = train(model, batches(), sampler, config, d, out=Path(out), checkpoint_every=checkpoint_every,
                resume=resume, score=score, progress=progress, desc=f"fit {filter}")
    if not d.main:
        return {}
    model.stochastic = 0  # scored with the deterministic filter, as the targets were rendered
    fits = render_all(model, frags, batch)
    metrics = {
        "filter": filter,
        "stochastic": stochastic,
        "decorrelate": decorrelate,
        "iters": iters,
        "texture_psnr": psnr(model.texture.detach(), true_tex, mask=seen),
        "initial_texture_psnr": psnr(init, true_tex, mask=seen),
        "image_psnr": psnr(render_all(model, eval_frags, batch), eval_targets),
        "train_image_psnr": psnr(fits, targets),
        "seconds": time.perf_counter() - t0,
        "fit_seconds": run["fit_seconds"],
        "steps_per_second": run["steps"] / run["fit_seconds"] if run["steps"] else float("nan"),
        "processes": d.world,
        "allreduce_bytes_per_step": run["allreduce_bytes"],
        "peak_rss_bytes": peak_rss_bytes(),
        "res": res, "views": views, "eval_views": eval_views, "batch": batch, "lr": lr, "seed": seed,
        "target_filter": target_filter,
        "seen_texels": int(seen.sum()),
    }
    if save:
        write_outputs(Path(out), metrics, run["curve"], targets, fits, model.texture.detach(), true_tex, seen)
    return metrics


def make_capture(folder: str | Path, res: int = 128, views: int = 48, seed: int = 0, target_filter: str = "ewa",
                 batch: int = 8) -> Path:
    """Write the demo's training views of spot (rendered with ``target_filter``, coverage as alpha) as a
    transforms.json capture in ``folder``; returns the JSON's path. Fit it with
    ``--capture folder --mesh data/spot/spot_triangulated.obj``."""
    proj, view = random_cameras(views, seed)
    model = difftex.TexturedMesh(spot_mesh(), spot_texture(), filter=target_filter, learn_texture=False)
    frags = model.rasterize(proj @ view, (res, res))
    images = render_all(model, frags, batch)
    return save_capture(folder, images, view, proj, masks=frags.mask.unsqueeze(1).to(images.dtype))


def fit_capture(capture: str | Path, mesh: str | Path, filter: str = "trilinear", iters: int = 300,
                batch: int = 8, lr: float = 0.03, seed: int = 0, out: str | Path = "results/fit_capture",
                tex_size: int = 1024, workers: int = 2, skip_bad: bool = False,
                reference_texture: str | Path | None = None, progress: bool = True, save: bool = True, *,
                cache_mb: float = CACHE_MB, checkpoint_every: int = 0, resume: bool = False,
                device: str = "cpu") -> dict:
    """Fit a ``tex_size``^2 RGB texture of ``mesh`` to a transforms.json capture.

    The loss weights each pixel by the image's alpha (the object mask; 1 without one). Frames whose camera
    sees nothing of the mesh are skipped with a CaptureWarning (they would add no gradient, and a camera
    pointing away is common in a real capture); ValueError if no frame sees it (usually a wrong axis
    convention or scale). With ``reference_texture`` (same size), metrics include the texture PSNR over
    the texels the frames see (as the demo counts them).

    ``cache_mb`` (MiB, per process) bounds the frames held in memory: when every frame's fragments and
    image fit it, each frame is rasterized and read once and no DataLoader worker starts; otherwise (0
    turns the cache off) ``workers`` processes stream the images and each step rasterizes its views. The
    two give bit-identical batches, so the same texture; ``cache_mb`` is not part of the settings that
    ``resume`` checks. Returns the metrics (rank 0; {} on the other ranks). Raises ValueError naming
    ``cache_mb`` when it is not a number >= 0.
    """
    if isinstance(cache_mb, bool) or not isinstance(cache_mb, (int, float)) or not 0 <= cache_mb < math.inf:
        raise ValueError(f"cache_mb: expected a finite number of MiB >= 0 (0: no cache), got {cache_mb!r}")
    d = runtime.setup(device)
    dev = d.device
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    cap = load_capture(capture, on_bad="skip" if skip_bad else "raise")
    H, W = cap.resolution
    init = torch.full((1, 3, tex_size, tex_size), 0.5, device=dev)
    model = difftex.TexturedMesh(difftex.load_mesh(mesh), init, filter=filter).to(dev)
    if dev.type == "cpu":
        difftex._native.load()

    mvp_all = cap.mvp().to(dev)
    budget = int(cache_mb * 2 ** 20) - frame_cache.image_bytes(len(cap), (H, W))
    compact = None
    if budget > 0:
        # Every process rasterizes every frame (a step's share may be any frame) and keeps the fragments while
        # they fit; the budget and the frames are the same everywhere, so every process decides alike.
        counts, compact = frame_cache.rasterize_frames(model, mvp_all, (H, W), budget_bytes=budget)
    else:
        # Each process rasterizes its share of the frames once; the counts are summed over processes.
        counts = torch.zeros(len(cap), dtype=torch.int64, device=dev)
        mine = torch.arange(d.rank, len(cap), d.world, device=dev)
        counts[mine] = visible_frames(mvp_all[mine], model.positions, model.faces, (H, W))
        if d.world > 1:
            torch.distributed.all_reduce(counts)
    keep = [k for k in range(len(cap)) if counts[k] > 0]
    if not keep:
        raise ValueError(f"capture {str(capture)!r}: no frame's camera sees the mesh {str(mesh)!r}; check the "
                         "camera axes (OpenGL: looking down -z, +y up) and that mesh and cameras share units")
    if d.main:
        for k in range(len(cap)):
            if counts[k] == 0:
                warnings.warn(f"frame {k} ({cap.frames[k].name!r}): the camera sees nothing of the mesh; "
                              "skipped (it would add no gradient)", CaptureWarning, stacklevel=2)
    ds = CaptureDataset(cap, frames=keep)
    sampler = StepSampler(len(ds), batch, seed + 1, iters, d)
    cache = frame_cache.FrameCache.load(compact.subset(keep), ds, dev) if compact is not None else None
    del compact

    def views(order) -> Iterator[tuple[Fragments, torch.Tensor, torch.Tensor]]:
        """(fragments, images, masks) of each list of frames ``order`` yields (a batch sampler)."""
        if cache is not None:
            yield from map(cache.batch, order)
            return
        loader = torch.utils.data.DataLoader(ds, batch_sampler=order, num_workers=workers,
                                             pin_memory=dev.type == "cuda")
        for b in loader:
            yield (model.rasterize(b["mvp"].to(dev, non_blocking=True), (H, W)),
                   b["image"].to(dev, non_blocking=True), b["mask"].to(dev, non_blocking=True))

    def batches():
        for frags, image, mask in views(sampler):
            img, _ = model(frags=frags)
            yield img, image, mask

    score = None
    if reference_texture is not None and d.main:
        ref = difftex.load_texture(reference_texture)[:, :3].to(dev)
        if ref.shape != init.shape:
            raise ValueError(f"reference_texture: expected a {tex_size}x{tex_size} RGB image like the fitted "
                             f"texture, got shape {tuple(ref.shape)}")
        # The demo's mask: texels a bilinear lookup at 4x the frames' resolution reads.
        seen = seen_texels(difftex.TexturedMesh(difftex.load_mesh(mesh), ref, learn_texture=False).to(dev),
                           mvp_all[keep], (H, W))
        score = lambda: psnr(model.texture.detach(), ref, mask=seen)  # noqa: E731
    config = {"mode": "capture", "capture": str(Path(capture).resolve()), "mesh": str(Path(mesh).resolve()),
              "filter": filter, "iters": iters, "batch": batch, "lr": lr, "seed": seed, "tex_size": tex_size,
              "frames": keep}
    run = train(model, batches(), sampler, config, d, out=Path(out), checkpoint_every=checkpoint_every,
                resume=resume, score=score, progress=progress, desc=f"fit {filter}")
    if not d.main:
        return {}

    # Pooled over every pixel of every frame, weighted by alpha (one pass, any capture size).
    sse, count, shown = 0.0, 0.0, []
    in_order = [list(range(i, min(i + batch, len(ds)))) for i in range(0, len(ds), batch)]
    with torch.no_grad():
        for frags, t, m in views(in_order):
            img, _ = model(frags=frags)
            sse += float((m * (img - t) ** 2).sum(dtype=torch.float64))
            count += float(m.sum(dtype=torch.float64)) * img.shape[1]
            if len(shown) < 4:
                shown += list(zip(t, img))[:4 - len(shown)]
    metrics = {
        "mode": "capture", "filter": filter, "iters": iters, "frames": len(cap), "frames_used": len(keep),
        "resolution": [H, W], "tex_size": tex_size,
        "image_psnr": 10 * math.log10(count / sse) if sse > 0 else float("inf"),
        "texture_psnr": score() if score is not None else None,
        "seconds": time.perf_counter() - t0, "fit_seconds": run["fit_seconds"],
        "steps_per_second": run["steps"] / run["fit_seconds"] if run["steps"] else float("nan"),
        "processes": d.world, "allreduce_bytes_per_step": run["allreduce_bytes"],
        "peak_rss_bytes": peak_rss_bytes(), "batch": batch, "lr": lr, "seed": seed,
        "workers": 0 if cache is not None else workers,
        "cached": cache is not None, "cache_bytes": cache.nbytes if cache is not None else 0,
    }
    if save:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        rows = [torch.cat([t, f, (4 * (f - t).abs()).clamp(0, 1)], -1) for t, f in shown]
        difftex.save_image(out / "views.png", torch.cat(rows, -2))
        difftex.save_image(out / "texture.png", model.texture.detach())
        plot_curves(out, run["curve"], f"fit_texture --capture: filter={filter}")
    return metrics


def write_outputs(out: Path, metrics, curve, targets, fits, tex, true_tex, seen) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    # A few views, nearest to farthest: target / fit / 4x error.
    order = torch.argsort((targets.sum(1) > 0).flatten(1).sum(1), descending=True)
    pick = order[torch.linspace(0, len(order) - 1, 4).long()]
    rows = [torch.cat([targets[i], fits[i], (4 * (fits[i] - targets[i]).abs()).clamp(0, 1)], -1) for i in pick]
    difftex.save_image(out / "views.png", torch.cat(rows, -2))
    difftex.save_image(out / "texture.png", torch.cat([tex[0], true_tex[0], seen[0].expand_as(tex[0]).to(tex.dtype)], -1))
    plot_curves(out, curve, f"fit_texture: filter={metrics['filter']}")


def plot_curves(out: Path, curve: dict, title: str) -> None:
    """curves.png: the loss and the texture PSNR against the step."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    ax[0].semilogy(curve["iter"], curve["loss"])
    ax[0].set_xlabel("iteration"); ax[0].set_ylabel("image MSE"); ax[0].set_title("loss")
    ax[1].plot(curve["iter"], curve["texture_psnr"])
    ax[1].set_xlabel("iteration"); ax[1].set_ylabel("dB"); ax[1].set_title("texture PSNR (seen texels)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--filter", default="trilinear", choices=FILTERS)
    p.add_argument("--iters", type=int, default=300)
    p.add_argument("--res", type=int, default=128, help="demo / --make-capture: image size")
    p.add_argument("--views", type=int, default=48, help="demo / --make-capture: number of views")
    p.add_argument("--batch", type=int, default=8, help="views per step, over all processes")
    p.add_argument("--lr", type=float, default=0.03)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--target-filter", default="ewa")
    p.add_argument("--stochastic", type=int, default=0, metavar="K",
                   help="demo: fit through stochastic filtering, K draws a pixel (0: deterministic)")
    p.add_argument("--no-decorrelate", action="store_true",
                   help="--stochastic: the gradient from the value's own draws (adds the variance term)")
    p.add_argument("--eval-views", type=int, default=16, help="demo: held-out views")
    p.add_argument("--out", default=None, help="default results/fit_texture (results/fit_capture with --capture)")
    p.add_argument("--make-capture", metavar="DIR", help="write the demo's spot views as a transforms.json capture")
    p.add_argument("--capture", metavar="DIR", help="fit to this transforms.json capture (needs --mesh)")
    p.add_argument("--mesh", help="the captured object's mesh (OBJ / GLB / glTF / PLY with uv)")
    p.add_argument("--tex-size", type=int, default=1024, help="--capture: fitted texture is N x N RGB")
    p.add_argument("--workers", type=int, default=2,
                   help="--capture: DataLoader worker processes (none start when the frames are cached)")
    p.add_argument("--cache-mb", type=float, default=CACHE_MB, metavar="MIB",
                   help="--capture: hold every frame's fragments and image in memory when they fit this many MiB "
                        "(per process; 0: rasterize and load each step's views anew)")
    p.add_argument("--skip-bad", action="store_true", help="--capture: skip bad frames with a warning")
    p.add_argument("--reference-texture", help="--capture: score the fit against this texture")
    p.add_argument("--checkpoint-every", type=int, default=0, metavar="K")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.make_capture:
        path = make_capture(args.make_capture, args.res, args.views, args.seed, args.target_filter, args.batch)
        print(f"wrote {path} and {args.views} images")
        return
    ok = False
    try:
        if args.capture:
            if not args.mesh:
                p.error("--capture needs --mesh")
            if args.stochastic or args.no_decorrelate:
                p.error("--stochastic / --no-decorrelate: the demo's fit only, not --capture")
            out = args.out or "results/fit_capture"
            m = fit_capture(args.capture, args.mesh, args.filter, args.iters, args.batch, args.lr, args.seed, out,
                            args.tex_size, args.workers, args.skip_bad, args.reference_texture,
                            not args.no_progress, cache_mb=args.cache_mb, checkpoint_every=args.checkpoint_every,
                            resume=args.resume, device=args.device)
            written = "metrics.json, views.png, texture.png, curves.png"
        else:
            out = args.out or "results/fit_texture"
            m = fit(args.filter, args.iters, args.res, args.views, args.batch, args.lr, args.seed, out,
                    args.target_filter, args.eval_views, progress=not args.no_progress, checkpoint_every=args.checkpoint_every,
                    resume=args.resume, device=args.device, stochastic=args.stochastic,
                    decorrelate=not args.no_decorrelate)
            written = "metrics.json, views.png, texture.png, curves.png"
        if m:
            print(json.dumps(m, indent=2))
            print(f"wrote {out}/{written}")
        ok = True
    finally:
        runtime.teardown(ok)


if __name__ == "__main__":
    main()

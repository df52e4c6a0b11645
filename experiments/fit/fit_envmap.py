"""Learn an environment cube map and a Phong highlight from images of a mirror sphere, through difftex.

In the spirit of nvdiffrast's envphong sample (written from scratch): a unit
sphere reflects an environment and carries a Phong highlight,

    image = env(r) + k_s max(r . l, 0)^n,   r = the view vector mirrored about the normal,

with a random light direction l per view (so the highlight moves across the
environment from view to view and the two can be told apart). The targets are
rendered from the real HDR environment ``data/envmap/venice_sunset_1k.hdr``
(converted to a 64^2 cube with ``equirect_to_cube``, read with the anisotropic
filter), a Phong colour k_s and exponent n; the fit learns a 32^2 cube (as
log radiance), k_s and log n with Adam on the log1p of the images (the sun
is 10^4 times the sky), reading its cube with ``--filter`` at the exact
per-pixel direction derivatives (``difftex.testing.reflection_dirs``).
Rasterization is done once: only the environment and the Phong terms change.

Reports the environment's PSNR (on log1p radiance, peak the target's largest)
over the directions the views see, the Phong parameters' relative errors, and
writes to ``--out``: metrics.json, views.png (target / fit / 4x error, tone
mapped), envmap.png (fitted / true cube unfolded to latitude-longitude, and the
seen directions), curves.png (loss, environment PSNR, Phong errors).

    python -m experiments.fit.fit_envmap [--iters 300] [--res 64] [--views 48] [--filter trilinear]
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch
from tqdm import tqdm

import difftex
from difftex import camera
from difftex.envmap import cube_to_equirect, cubemap, equirect_to_cube
from difftex.io.files import data_path
from difftex.metrics import psnr
from difftex.testing import icosphere, reflection_dirs

HDR = "envmap/venice_sunset_1k.hdr"
TRUE_KS = (0.9, 0.75, 0.5)
TRUE_EXP = 40.0


def tonemap(x: torch.Tensor) -> torch.Tensor:
    """Reinhard, then a 2.2 gamma: HDR radiance -> [0, 1] for pictures."""
    return (x.clamp_min(0) / (1 + x.clamp_min(0))) ** (1 / 2.2)


def scene(views: int, res: int, seed: int, fov_deg: float = 30.0):
    """Rasterize the mirror sphere from random eyes: (r, r_dx, r_dy [V, R, R, 3], mask [V, 1, R, R], light [V, 3])."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(views, 3, generator=g)
    eye = d / d.norm(dim=-1, keepdim=True) * (2.6 + 0.8 * torch.rand(views, 1, generator=g))
    light = torch.randn(views, 3, generator=g)
    light = light / light.norm(dim=-1, keepdim=True)
    up = torch.where(d[:, 1:2].abs() > 0.95 * d.norm(dim=-1, keepdim=True), torch.tensor([1.0, 0, 0]),
                     torch.tensor([0.0, 1, 0]))
    mvp = camera.perspective(fov_deg, 1.0, 0.1, 10.0, degrees=True) @ camera.look_at(eye, torch.zeros(views, 3), up)
    verts, faces = icosphere(4)
    frags = difftex.rasterize(camera.transform(verts, mvp), faces, (res, res))
    p, pdx, pdy = difftex.interpolate(verts, faces, frags, derivatives=True)
    r, rdx, rdy = reflection_dirs(p, pdx, pdy, p, pdx, pdy, eye.view(views, 1, 1, 3))
    mask = (frags.tri_id >= 0)
    m = mask.unsqueeze(-1)
    # Background pixels read +x with a zero footprint and are masked out of the images.
    r = torch.where(m, r, torch.tensor([1.0, 0, 0]))
    return r, torch.where(m, rdx, 0.0), torch.where(m, rdy, 0.0), mask.unsqueeze(1), light


def render(env, ks, n, r, rdx, rdy, mask, light, filter):
    spec = (r * light.view(-1, 1, 1, 3)).sum(-1).clamp_min(0).unsqueeze(1) ** n  # [V, 1, R, R]
    img = cubemap(env, r, filter=filter, dirs_dx=rdx, dirs_dy=rdy) + ks.view(1, 3, 1, 1) * spec
    return img * mask


def fit(iters: int = 300, res: int = 64, views: int = 48, batch: int = 6, size: int = 32, lr: float = 0.05,
        filter: str = "trilinear", seed: int = 0, out: str | Path = "results/fit_envmap", progress: bool = True,
        save: bool = True, eval_every: int = 25) -> dict:
    """Run one fit and return its metrics (also written to ``out``/metrics.json when ``save``)."""
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    hdr = difftex.load_texture(data_path(HDR))
    true_env = equirect_to_cube(hdr, 64)  # [1, 6, 3, 64, 64]
    r, rdx, rdy, mask, light = scene(views, res, seed)
    ks_true, n_true = torch.tensor(TRUE_KS), torch.tensor(TRUE_EXP)
    with torch.no_grad():
        targets = torch.cat([render(true_env, ks_true, n_true, *(x[i] for x in (r, rdx, rdy, mask, light)),
                                    "anisotropic") for i in torch.split(torch.arange(views), 8)])
    seen = r[mask[:, 0]].view(1, 1, -1, 3)  # every direction a view sees
    want = torch.log1p(cubemap(true_env, seen))
    peak = float(want.max())

    theta = torch.full((1, 6, 3, size, size), math.log(0.5), requires_grad=True)  # log radiance
    ks_raw = torch.full((3,), 0.2, requires_grad=True)
    log_n = torch.tensor(math.log(10.0), requires_grad=True)
    opt = torch.optim.Adam([theta, ks_raw, log_n], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, iters, eta_min=lr / 10)
    curve = {"iter": [], "loss": [], "env_psnr": [], "ks_error": [], "exp_error": []}

    def evaluate():
        with torch.no_grad():
            env_psnr = psnr(torch.log1p(cubemap(theta.exp(), seen)), want, peak)
            ks_err = float(((ks_raw - ks_true).norm() / ks_true.norm()))
            n_err = float((log_n.exp() - n_true).abs() / n_true)
        return env_psnr, ks_err, n_err

    g = torch.Generator().manual_seed(seed + 1)
    losses = []
    bar = tqdm(range(iters), disable=not progress, desc=f"fit_envmap ({filter})")
    for it in bar:
        idx = torch.randperm(views, generator=g)[:batch]
        img = render(theta.exp(), ks_raw, log_n.exp(), *(x[idx] for x in (r, rdx, rdy, mask, light)), filter)
        loss = (torch.log1p(img.clamp_min(0)) - torch.log1p(targets[idx])).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
        if (it + 1) % eval_every == 0 or it == 0 or it == iters - 1:
            e, k, n = evaluate()
            for key, v in zip(curve, (it + 1, losses[-1], e, k, n)):
                curve[key].append(v)
            bar.set_postfix(loss=f"{losses[-1]:.2e}", env_psnr=f"{e:.1f}")
    env_psnr, ks_err, n_err = evaluate()
    seconds = time.perf_counter() - t0
    with torch.no_grad():
        fits = torch.cat([render(theta.exp(), ks_raw, log_n.exp(), *(x[i] for x in (r, rdx, rdy, mask, light)), filter)
                          for i in torch.split(torch.arange(views), 8)])
    metrics = {
        "filter": filter, "iters": iters, "res": res, "views": views, "size": size,
        "env_psnr": env_psnr, "initial_env_psnr": curve["env_psnr"][0],
        "image_psnr": psnr(torch.log1p(fits), torch.log1p(targets), peak, mask=mask.expand_as(fits)),
        "ks": ks_raw.detach().tolist(), "ks_true": list(TRUE_KS), "ks_error": ks_err,
        "exponent": float(log_n.detach().exp()), "exponent_true": TRUE_EXP, "exponent_error": n_err,
        "final_loss": sum(losses[-10:]) / len(losses[-10:]), "seconds": seconds,
    }
    if save:
        _save(Path(out), metrics, curve, targets, fits, theta.detach().exp(), true_env, seen)
    return metrics


def _save(out: Path, metrics, curve, targets, fits, env, true_env, seen) -> None:
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    pick = torch.linspace(0, targets.shape[0] - 1, 4).long()
    rows = [torch.cat([tonemap(targets[i]), tonemap(fits[i]),
                       (4 * (tonemap(fits[i]) - tonemap(targets[i])).abs()).clamp(0, 1)], -1) for i in pick]
    difftex.save_image(out / "views.png", torch.cat(rows, -2))
    H = 128
    fitted = cube_to_equirect(env, (H, 2 * H))
    true = cube_to_equirect(true_env, (H, 2 * H))
    # The seen directions, splatted onto the map.
    uv = difftex.envmap.direction_to_equirect_uv(seen[0, 0])
    cols = (uv[:, 0] * 2 * H).long().clamp(0, 2 * H - 1)
    rows_ = (uv[:, 1] * H).long().clamp(0, H - 1)
    hits = torch.zeros(H * 2 * H)
    hits[rows_ * 2 * H + cols] = 1
    difftex.save_image(out / "envmap.png", torch.cat([tonemap(fitted[0]), tonemap(true[0]),
                                                      hits.view(1, H, 2 * H).expand(3, H, 2 * H)], -2))
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.2))
    ax[0].semilogy(curve["iter"], curve["loss"])
    ax[0].set_xlabel("iteration"); ax[0].set_title("loss (log1p image MSE)")
    ax[1].plot(curve["iter"], curve["env_psnr"])
    ax[1].set_xlabel("iteration"); ax[1].set_ylabel("dB"); ax[1].set_title("environment PSNR (seen directions)")
    ax[2].semilogy(curve["iter"], curve["ks_error"], label="k_s")
    ax[2].semilogy(curve["iter"], curve["exp_error"], label="exponent")
    ax[2].set_xlabel("iteration"); ax[2].set_title("Phong relative error"); ax[2].legend()
    fig.suptitle(f"fit_envmap: filter={metrics['filter']}")
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=110)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=300)
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--views", type=int, default=48)
    p.add_argument("--batch", type=int, default=6)
    p.add_argument("--size", type=int, default=32, help="learned cube face size")
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--filter", default="trilinear")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/fit_envmap")
    args = p.parse_args()
    m = fit(args.iters, args.res, args.views, args.batch, args.size, args.lr, args.filter, args.seed, args.out)
    print(json.dumps(m, indent=2))
    print(f"wrote {args.out}/metrics.json, views.png, envmap.png, curves.png")


if __name__ == "__main__":
    main()

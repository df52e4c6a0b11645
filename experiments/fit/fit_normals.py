"""Recover a bump (height) map and an albedo texture of a plane from shaded images under known lights.

Photometric stereo through difftex: the plane is rasterized once (the
camera and geometry are fixed); each target image is the Blinn-Phong
shading (known small specular) of the true albedo and the true height
map's bump normals under one of ``--lights`` directional lights around the
view axis. Adam fits an albedo texture (starts grey) and a height map
(starts flat) so that renders under the same lights match; the bump
normals come from the slope of the filtered height (``difftex.shading.bump``,
the derivative of the trilinear interpolant), so the height map learns
through the second derivative of ``sample``.

Reports the recovered normals' mean angular error (degrees, over the
pixels) and the albedo PSNR against the truth. Writes to ``--out``:
metrics.json, images.png (targets under two lights | fit | albedo truth /
fit | normals truth / fit as colours) and curves.png (loss, normal error,
albedo PSNR).

    python -m experiments.fit.fit_normals [--iters 300] [--res 96] [--tex 48] [--lights 4]
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from tqdm import tqdm

import difftex
from difftex.metrics import psnr
from difftex.shading import blinn_phong, bump, tangent_frames
from difftex.testing import spot_texture

KS, SHININESS = 0.15, 24.0
SCALE = 1.0  # bump scale: slope in height units per uv unit


def true_maps(tex: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The truth: albedo [1, 3, tex, tex] (spot's texture, area-averaged) and height [1, 1, tex, tex] (smooth bumps)."""
    albedo = F.interpolate(spot_texture(), size=(tex, tex), mode="area").clamp(0.02, 1)
    t = (torch.arange(tex, dtype=torch.float32) + 0.5) / tex
    v, u = torch.meshgrid(t, t, indexing="ij")
    g = torch.Generator().manual_seed(5)
    h = 0.03 * torch.sin(2 * math.pi * 2 * u) * torch.cos(2 * math.pi * 1.5 * v)
    for _ in range(6):
        cu, cv = torch.rand(2, generator=g) * 0.8 + 0.1
        w = 0.06 + 0.06 * float(torch.rand(1, generator=g))
        a = 0.08 * (float(torch.rand(1, generator=g)) - 0.3)
        h = h + a * torch.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * w * w))
    return albedo, h[None, None]


def lights(k: int, elevation_deg: float = 45.0) -> torch.Tensor:
    """[k, 3] unit directions to k lights evenly spaced in azimuth at one elevation above the plane (+z)."""
    az = torch.arange(k, dtype=torch.float32) * 2 * math.pi / k + 0.3
    el = math.radians(elevation_deg)
    return torch.stack([math.cos(el) * az.cos(), math.cos(el) * az.sin(), torch.full_like(az, math.sin(el))], -1)


def plane_scene(res: int):
    """The plane z = 0 over [-1, 1]^2 filling a res x res orthographic view: uv, uv_dx, uv_dy, frames, mask."""
    pos = torch.tensor([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=torch.float32) * 1.0
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uv = torch.stack([(pos[:, 0] + 1) / 2, (1 - pos[:, 1]) / 2], -1)  # v down as y goes up (DESIGN.md)
    clip = torch.cat([pos[:, :2], torch.zeros(4, 1), torch.ones(4, 1)], -1)
    frags = difftex.rasterize(clip[None], faces, (res, res))
    uv_p, uv_dx, uv_dy = difftex.interpolate(uv, faces, frags, derivatives=True)
    frames = tangent_frames(pos, faces, uv).at(frags, faces)
    return uv_p, uv_dx, uv_dy, frames, frags.tri_id >= 0


def render(albedo, height, scene, dirs):
    """[K, res, res, 3] images of the plane under each light (K = len(dirs)) and the normals [1, res, res, 3]."""
    uv, dx, dy, frames, _ = scene
    kd = difftex.sample(albedo, uv, filter="trilinear", uv_dx=dx, uv_dy=dy, wrap="clamp").movedim(1, -1)
    n = bump(height, uv, frames, SCALE, filter="trilinear", uv_dx=dx, uv_dy=dy, wrap="clamp")
    view = torch.tensor([0.0, 0.0, 1.0])
    img = blinn_phong(n, view, dirs[:, None, None, None, :], kd, KS, SHININESS)
    return img, n


def angular_error_deg(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    cos = (a * b).sum(-1).clamp(-1, 1)
    return float(torch.rad2deg(torch.acos(cos))[mask].mean())


def run(iters: int = 300, res: int = 96, tex: int = 48, n_lights: int = 4, lr: float = 0.02,
        out: Path | None = None, progress: bool = True, log_every: int = 10) -> dict:
    """Fit; returns the metrics (and writes the figures when ``out`` is given)."""
    t0 = time.time()
    torch.manual_seed(0)
    albedo_true, height_true = true_maps(tex)
    scene = plane_scene(res)
    mask = scene[4]
    dirs = lights(n_lights)
    with torch.no_grad():
        target, n_true = render(albedo_true, height_true, scene, dirs)
    albedo = torch.full_like(albedo_true, 0.5).requires_grad_()
    height = torch.zeros_like(height_true).requires_grad_()
    # Heights are ~0.03 against albedos ~0.5: the height's step is scaled down to match.
    opt = torch.optim.Adam([{"params": [albedo], "lr": lr}, {"params": [height], "lr": lr * 0.05}])
    curves = {"iter": [], "loss": [], "normal_error_deg": [], "albedo_psnr": []}
    n_fit = None

    def record(i: int, loss: float) -> None:
        curves["iter"].append(i)
        curves["loss"].append(loss)
        curves["normal_error_deg"].append(angular_error_deg(n_fit, n_true, mask))
        curves["albedo_psnr"].append(psnr(albedo.detach().clamp(0, 1), albedo_true))

    bar = tqdm(range(iters + 1), disable=not progress, desc="fit_normals")
    for i in bar:
        img, n = render(albedo, height, scene, dirs)
        loss = F.mse_loss(img, target)
        n_fit = n.detach()
        if i % log_every == 0 or i == iters:
            record(i, float(loss.detach()))
            bar.set_postfix(loss=f"{float(loss.detach()):.2e}", err=f"{curves['normal_error_deg'][-1]:.2f}deg",
                            psnr=f"{curves['albedo_psnr'][-1]:.1f}dB")
        if i == iters:
            break
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            albedo.clamp_(0, 1)
    metrics = {
        "iters": iters, "res": res, "tex": tex, "lights": n_lights,
        "normal_error_deg_start": curves["normal_error_deg"][0], "normal_error_deg": curves["normal_error_deg"][-1],
        "albedo_psnr_start": curves["albedo_psnr"][0], "albedo_psnr": curves["albedo_psnr"][-1],
        "image_psnr": psnr(img.detach().clamp(0, 1), target.clamp(0, 1)),
        "seconds": round(time.time() - t0, 1),
    }
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "metrics.json").write_text(json.dumps({**metrics, "curves": curves}, indent=1))
        _figures(out, target, img.detach(), albedo_true, albedo.detach(), n_true, n_fit, curves)
    return metrics


def _figures(out, target, img, albedo_true, albedo, n_true, n_fit, curves) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    enc = lambda n: ((n[0] + 1) / 2).clamp(0, 1).numpy()
    tiles = [("target, light 1", target[0].clamp(0, 1).numpy()), ("fit, light 1", img[0].clamp(0, 1).numpy()),
             ("target, light 2", target[1].clamp(0, 1).numpy()), ("fit, light 2", img[1].clamp(0, 1).numpy()),
             ("albedo truth", albedo_true[0].permute(1, 2, 0).numpy()),
             ("albedo fit", albedo[0].permute(1, 2, 0).clamp(0, 1).numpy()),
             ("normals truth", enc(n_true)), ("normals fit", enc(n_fit))]
    fig, axes = plt.subplots(2, 4, figsize=(12, 6.4))
    for ax, (title, im) in zip(axes.flat, tiles):
        ax.imshow(im, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "images.png", dpi=80)
    plt.close(fig)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.2))
    axes[0].semilogy(curves["iter"], curves["loss"])
    axes[0].set_title("image MSE")
    axes[1].plot(curves["iter"], curves["normal_error_deg"])
    axes[1].set_title("mean normal error (degrees)")
    axes[2].plot(curves["iter"], curves["albedo_psnr"])
    axes[2].set_title("albedo PSNR (dB)")
    for ax in axes:
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=80)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--iters", type=int, default=300)
    p.add_argument("--res", type=int, default=96)
    p.add_argument("--tex", type=int, default=48)
    p.add_argument("--lights", type=int, default=4)
    p.add_argument("--lr", type=float, default=0.02)
    p.add_argument("--out", type=Path, default=Path("results/fit_normals"))
    a = p.parse_args()
    m = run(a.iters, a.res, a.tex, a.lights, a.lr, out=a.out)
    print(json.dumps(m, indent=1))


if __name__ == "__main__":
    main()

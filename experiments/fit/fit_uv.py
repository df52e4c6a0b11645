"""Recover wrong uv coordinates of the spot cow from images, alone or jointly with the texture.

The start is the true uv moved by a texture matrix (shift, rotation about
the texture centre, scale) plus per-vertex noise; targets are renders with
the true uv and texture. The fit learns uv = A(uv_start) + r with Adam: an
affine texture matrix A, which every textured edge in every view informs,
and a per-vertex residual r under a graph-Laplacian penalty (a wrong
texture matrix moves neighbouring vertices alike, noise does not), with a
coarse-to-fine
``lod_bias`` schedule: the blurred texture of a high level gives gradients
a wide basin, level 0 the final precision. With ``--joint`` the texture is
learned too, starting from a blurred copy of the true one.

Writes to ``--out``: metrics.json ({"uv_error_before", "uv_error_after"}
in texels, "ratio", "image_psnr", "seconds", ...) and uv.png (uv layout
before / after over the texture, and target / start / fit renders).

    python -m experiments.fit.fit_uv [--iters 150] [--res 128] [--views 24] [--joint]
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
from difftex.mapping import texture_matrix, uv_transform
from difftex.metrics import psnr
from difftex.testing import spot_mesh, spot_texture
from experiments.fit.fit_texture import random_views, render_all, select


def uv_laplacian(uv_faces: torch.Tensor, count: int):
    """The uniform graph Laplacian over the edges of the uv triangles, as a function.

    ``lap(x)[i] = x[i] - mean of x over i's neighbours``, for x [T, K].
    """
    e = torch.cat([uv_faces[:, [0, 1]], uv_faces[:, [1, 2]], uv_faces[:, [2, 0]]])
    e = torch.unique(torch.sort(torch.cat([e, e.flip(1)]), dim=1).values, dim=0)
    i = torch.cat([e[:, 0], e[:, 1]])
    j = torch.cat([e[:, 1], e[:, 0]])
    deg = torch.bincount(i, minlength=count).clamp_min(1).unsqueeze(1)

    def lap(x: torch.Tensor) -> torch.Tensor:
        return x - torch.zeros_like(x).index_add(0, i, x[j]) / deg
    return lap


def blur(tex: torch.Tensor, sigma: float) -> torch.Tensor:
    r = int(3 * sigma)
    x = torch.arange(-r, r + 1, dtype=tex.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    C = tex.shape[1]
    tex = F.conv2d(F.pad(tex, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    return F.conv2d(F.pad(tex, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


def fit_uv(iters: int = 150, res: int = 128, views: int = 24, batch: int = 8, lr: float = 2e-3,
           shift=(0.02, -0.015), angle_deg: float = 2.0, scale: float = 1.03, noise_texels: float = 0.5,
           smooth: float = 10.0, bias_start: float = 4.0, filter: str = "trilinear", joint: bool = False,
           seed: int = 0, out: str | Path = "results/fit_uv", progress: bool = True, save: bool = True) -> dict:
    """Run one uv fit; returns (and with ``save`` writes) its metrics."""
    torch.manual_seed(seed)
    mesh = spot_mesh()
    true_tex = spot_texture()
    size = true_tex.shape[-1]
    mvp = random_views(views, seed, dist_range=(1.8, 4.0))

    t0 = time.perf_counter()
    target_model = difftex.TexturedMesh(mesh, true_tex, filter=filter, learn_texture=False)
    frags = target_model.rasterize(mvp, (res, res))
    targets = render_all(target_model, frags, batch)

    g = torch.Generator().manual_seed(seed + 7)
    M = uv_transform(shift, math.radians(angle_deg), scale)
    uv_start = texture_matrix(mesh.uv, M) + torch.randn(mesh.uv.shape, generator=g) * noise_texels / size
    start_tex = blur(true_tex, 4.0) if joint else true_tex
    model = difftex.TexturedMesh(mesh, start_tex, filter=filter, learn_texture=joint)
    # uv = A(uv_start) + residual: a texture matrix carries the global error,
    # which every textured edge informs; the smooth residual takes the rest.
    affine = torch.zeros(2, 3, requires_grad=True)
    residual = torch.zeros_like(uv_start, requires_grad=True)
    eye = torch.eye(3)[:2]
    bottom = torch.tensor([[0.0, 0.0, 1.0]])

    def current_uv() -> torch.Tensor:
        return texture_matrix(uv_start, torch.cat([eye + affine, bottom])) + residual

    L = uv_laplacian(mesh.uv_faces, mesh.uv.shape[0])
    groups = [{"params": [affine], "lr": lr}, {"params": [residual], "lr": lr * 0.25}]
    if joint:
        groups.append({"params": [model.texture], "lr": 0.01})
    opt = torch.optim.Adam(groups)
    gen = torch.Generator().manual_seed(seed + 1)

    def uv_error() -> float:
        with torch.no_grad():
            return float((current_uv() - mesh.uv).norm(dim=-1).mean() * size)

    before = uv_error()
    t_fit = time.perf_counter()
    bar = tqdm(range(iters), disable=not progress, desc="fit uv")
    for it in bar:
        # Coarse to fine: the level bias falls linearly to 0 over the first 70%.
        model.lod_bias = bias_start * max(0.0, 1.0 - it / (0.7 * iters))
        idx = torch.randperm(views, generator=gen)[:batch]
        img, _ = model(frags=select(frags, idx), uv=current_uv())
        ref = targets[idx] if model.lod_bias == 0 else _blurred_targets(target_model, frags, idx, model.lod_bias)
        loss = torch.mean((img - ref) ** 2) + smooth * torch.mean(L(residual) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if joint:
            with torch.no_grad():
                model.texture.clamp_(0, 1)
        if it % 10 == 0 or it == iters - 1:
            bar.set_postfix(loss=f"{loss.item():.2e}", uv_err=f"{uv_error():.2f}")
    model.lod_bias = 0.0
    after = uv_error()
    uv_fit = current_uv().detach()
    with torch.no_grad():
        model.uv.copy_(uv_fit)
    fits = render_all(model, frags, batch)
    metrics = {
        "uv_error_before": before, "uv_error_after": after, "ratio": before / max(after, 1e-12),
        "image_psnr": psnr(fits, targets), "joint": joint, "filter": filter, "iters": iters,
        "res": res, "views": views, "seconds": time.perf_counter() - t0, "fit_seconds": time.perf_counter() - t_fit,
        "shift": list(shift), "angle_deg": angle_deg, "scale": scale, "noise_texels": noise_texels,
    }
    if save:
        start_model = difftex.TexturedMesh(mesh, start_tex, filter=filter, learn_texture=False)
        with torch.no_grad():
            start_model.uv.copy_(uv_start)
        starts = render_all(start_model, frags, batch)
        write_outputs(Path(out), metrics, mesh, uv_start, uv_fit, true_tex, targets, starts, fits)
    return metrics


def _blurred_targets(target_model, frags, idx, bias: float) -> torch.Tensor:
    """Targets seen through the same level bias as the fit, so both blur alike."""
    with torch.no_grad():
        target_model.lod_bias = bias
        ref = target_model(frags=select(frags, idx))[0]
        target_model.lod_bias = 0.0
    return ref


def write_outputs(out: Path, metrics, mesh, uv_start, uv_fit, tex, targets, starts, fits) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    fig, ax = plt.subplots(1, 3, figsize=(13, 4.6))
    img = tex[0].permute(1, 2, 0).numpy()
    for a, uv, title in ((ax[0], uv_start, f"start: {metrics['uv_error_before']:.1f} texels"),
                         (ax[1], uv_fit, f"fit: {metrics['uv_error_after']:.2f} texels")):
        a.imshow(img, extent=(0, 1, 1, 0))
        seg = uv[mesh.uv_faces][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2, 2).numpy()
        a.add_collection(LineCollection(seg, colors="tab:blue", linewidths=0.2))
        true = mesh.uv[mesh.uv_faces][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2, 2).numpy()
        a.add_collection(LineCollection(true, colors="tab:red", linewidths=0.2, alpha=0.6))
        a.set_xlim(0.3, 0.7); a.set_ylim(0.7, 0.3)
        a.set_title(title + " (blue) vs true (red)")
    views = torch.cat([torch.cat([targets[i], starts[i], fits[i]], -1) for i in range(2)], -2)
    ax[2].imshow(views.permute(1, 2, 0).clamp(0, 1).numpy())
    ax[2].set_title("target | start | fit")
    for a in ax:
        a.set_xticks([]); a.set_yticks([])
    fig.tight_layout()
    fig.savefig(out / "uv.png", dpi=110)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=150)
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--views", type=int, default=24)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--filter", default="trilinear")
    p.add_argument("--joint", action="store_true", help="learn the texture too (from a blurred start)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/fit_uv")
    args = p.parse_args()
    m = fit_uv(args.iters, args.res, args.views, args.batch, args.lr, filter=args.filter, joint=args.joint,
               seed=args.seed, out=args.out)
    print(json.dumps(m, indent=2))


if __name__ == "__main__":
    main()

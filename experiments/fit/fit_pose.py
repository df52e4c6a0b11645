"""Recover a cube's pose from its silhouettes through analytic antialiasing.

Targets are antialiased silhouettes (coverage images) of a unit cube seen
by ``--views`` cameras around it; the fit starts from the true rotation
turned by ``--start-deg`` degrees about a random axis (and, with
``--translate``, shifted) and minimises the squared difference of the
silhouettes with Adam. Without :func:`difftex.antialias` the silhouette
is piecewise constant in the pose and has no gradient; with it the
silhouette edges move the vertices. The images are compared blurred
(Gaussian, sigma falling to 0 over the first half), which widens the
basin: an edge pixel then feels target coverage several pixels away.

A cube's silhouettes cannot tell its 24 rotational symmetries apart, so
the error is the angle to the nearest symmetric copy of the true pose.

Writes to ``--out``: metrics.json ({"start_deg", "final_deg", "seconds",
"cpu_seconds", ...}) and pose.png (target | start | fit silhouettes of two views and the
error curve).

    python -m experiments.fit.fit_pose [--iters 150] [--res 80] [--views 4] [--start-deg 45]
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from tqdm import tqdm

import difftex
from difftex import camera

CUBE_FACES = torch.tensor([
    [0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
    [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5],
])


def cube(dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit cube centred at the origin: vertices [8, 3] (vertex i has coordinates from its bits), faces [12, 3]."""
    v = torch.tensor([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=dtype) - 0.5
    return v, CUBE_FACES.clone()


def rotation(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: [3] axis * angle (radians) -> [3, 3], differentiable (finite at 0)."""
    theta2 = (axis_angle * axis_angle).sum()
    theta = torch.sqrt(theta2 + 1e-24)
    k = axis_angle / theta
    K = torch.zeros(3, 3, dtype=axis_angle.dtype)
    K = K.index_put((torch.tensor([0, 0, 1, 1, 2, 2]), torch.tensor([1, 2, 0, 2, 0, 1])),
                    torch.stack([-k[2], k[1], k[2], -k[0], -k[1], k[0]]))
    eye = torch.eye(3, dtype=axis_angle.dtype)
    return eye + torch.sin(theta) * K + (1 - torch.cos(theta)) * (K @ K)


def cube_symmetries(dtype=torch.float64) -> torch.Tensor:
    """[24, 3, 3] the rotations that map the cube onto itself (signed permutation matrices, det +1)."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((-1.0, 1.0), repeat=3):
            m = torch.zeros(3, 3, dtype=dtype)
            for i, (j, s) in enumerate(zip(perm, signs)):
                m[i, j] = s
            if torch.det(m) > 0:
                mats.append(m)
    return torch.stack(mats)


def pose_error_deg(R: torch.Tensor, R_true: torch.Tensor) -> float:
    """Angle (degrees) between R and the nearest symmetric copy R_true S of the true rotation."""
    Rs = R_true.to(torch.float64) @ cube_symmetries()
    rel = R.to(torch.float64).T @ Rs
    cos = (rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    # atan2 of the skew part: exact near 0, where acos of a rounded cosine is not.
    sin = torch.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    return float(torch.rad2deg(torch.atan2(sin.norm(dim=-1) / 2, cos)).min())


def view_matrices(views: int, dist: float = 3.2, dtype=torch.float32) -> torch.Tensor:
    """[N, 4, 4] clip-from-world matrices of cameras spread on a ring, tilted alternately up and down."""
    proj = camera.perspective(40.0, 1.0, 0.5, 10.0, degrees=True, dtype=dtype)
    mats = []
    for i in range(views):
        a = 2 * math.pi * i / views + 0.3
        e = 0.45 if i % 2 == 0 else -0.3
        eye = (dist * math.cos(e) * math.sin(a), dist * math.sin(e), dist * math.cos(e) * math.cos(a))
        mats.append(proj @ camera.look_at(eye, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), dtype=dtype))
    return torch.stack(mats)


def silhouettes(verts: torch.Tensor, faces: torch.Tensor, mvp: torch.Tensor, res: int) -> torch.Tensor:
    """[N, 1, res, res] antialiased coverage of the mesh in each view, differentiable w.r.t. ``verts``."""
    pos = camera.transform(verts, mvp)  # [N, 8, 4]
    frags = difftex.rasterize(pos, faces, (res, res))
    mask = frags.mask.to(verts.dtype)[:, None]
    return difftex.antialias(mask, frags, pos, faces)


def blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    if sigma < 0.3:
        return img
    r = int(math.ceil(3 * sigma))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    img = F.conv2d(F.pad(img, (r, r, 0, 0)), k.view(1, 1, 1, -1))
    return F.conv2d(F.pad(img, (0, 0, r, r)), k.view(1, 1, -1, 1))


def fit_pose(iters: int = 150, res: int = 80, views: int = 4, start_deg: float = 45.0, lr: float = 0.03,
             sigma_start: float = 4.0, translate: bool = False, seed: int = 0, out: str | Path = "results/fit_pose",
             progress: bool = True, save: bool = True) -> dict:
    """Run one pose fit; returns (and with ``save`` writes) its metrics."""
    g = torch.Generator().manual_seed(seed)
    verts, faces = cube()
    mvp = view_matrices(views)
    true_aa = torch.randn(3, generator=g)
    R_true = rotation(true_aa)
    t_true = torch.zeros(3)
    axis = torch.randn(3, generator=g)
    axis = axis / axis.norm()
    R_start = rotation(axis * math.radians(start_deg)) @ R_true
    t_start = (torch.randn(3, generator=g) * 0.1) if translate else torch.zeros(3)
    with torch.no_grad():
        targets = silhouettes(verts @ R_true.T + t_true, faces, mvp, res)

    t0, c0 = time.perf_counter(), time.process_time()
    # The pose is R = rotation(delta) @ R_start: delta starts at 0, where
    # the axis-angle map is smooth, and Adam moves it.
    delta = torch.zeros(3, requires_grad=True)
    shift = t_start.clone().requires_grad_(translate)
    params = [delta] + ([shift] if translate else [])
    opt = torch.optim.Adam(params, lr=lr)
    curve = []
    bar = tqdm(range(iters), disable=not progress, desc="fit pose")
    for it in bar:
        sigma = sigma_start * max(0.0, 1.0 - it / (0.5 * iters))
        R = rotation(delta) @ R_start
        img = silhouettes(verts @ R.T + shift, faces, mvp, res)
        loss = torch.mean((blur(img, sigma) - blur(targets, sigma)) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        err = pose_error_deg(R.detach(), R_true)
        curve.append((it, loss.item(), err))
        if it % 10 == 0 or it == iters - 1:
            bar.set_postfix(loss=f"{loss.item():.2e}", deg=f"{err:.2f}")
    with torch.no_grad():
        R_fit = rotation(delta) @ R_start
        fits = silhouettes(verts @ R_fit.T + shift, faces, mvp, res)
        starts = silhouettes(verts @ R_start.T + t_start, faces, mvp, res)
    metrics = {
        "start_deg": pose_error_deg(R_start, R_true), "final_deg": pose_error_deg(R_fit, R_true),
        "final_translation_error": float((shift.detach() - t_true).norm()), "translate": translate,
        "iters": iters, "res": res, "views": views, "lr": lr, "seed": seed,
        "silhouette_mae": float((fits - targets).abs().mean()), "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
    }
    if save:
        write_outputs(Path(out), metrics, targets, starts, fits, curve)
    return metrics


def write_outputs(out: Path, metrics: dict, targets, starts, fits, curve) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"width_ratios": [1.4, 1]})
    rows = [torch.cat([targets[i, 0], starts[i, 0], fits[i, 0], (fits[i, 0] - targets[i, 0]).abs()], -1)
            for i in range(min(2, targets.shape[0]))]
    ax[0].imshow(torch.cat(rows, 0).numpy(), cmap="gray", vmin=0, vmax=1)
    ax[0].set_title("target | start | fit | |fit - target|  (2 of the views)")
    ax[0].set_xticks([]); ax[0].set_yticks([])
    it, loss, err = zip(*curve)
    ax[1].semilogy(it, err, label="pose error (deg)")
    ax[1].semilogy(it, loss, label="loss")
    ax[1].axhline(2.0, color="gray", lw=0.8, ls="--")
    ax[1].set_xlabel("Adam step")
    ax[1].set_title(f"{metrics['start_deg']:.0f} deg -> {metrics['final_deg']:.3f} deg in {metrics['iters']} steps")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(out / "pose.png", dpi=100)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=150)
    p.add_argument("--res", type=int, default=80)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--start-deg", type=float, default=45.0)
    p.add_argument("--lr", type=float, default=0.03)
    p.add_argument("--translate", action="store_true", help="fit the translation too")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/fit_pose")
    args = p.parse_args()
    m = fit_pose(args.iters, args.res, args.views, args.start_deg, args.lr, translate=args.translate,
                 seed=args.seed, out=args.out)
    print(json.dumps(m, indent=2))


if __name__ == "__main__":
    main()

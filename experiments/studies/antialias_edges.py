"""How close antialiased silhouettes come to box-filtered coverage, by mesh density and neighbour rings.

Each scene's coverage mask (1 on the mesh, 0 off) is antialiased with
:func:`difftex.antialias` (``rings`` = 0, the paper's test of the pixel's
own triangle, up to 3) and compared with the 8x8 supersampled coverage on
the pixels the silhouette crosses (reference strictly between 0 and 1):
mean absolute error, against the aliased mask's. Scenes: a cube, icosphere
subdivisions 1-4 and spot, at 128x128. Prints the table and writes the
figure (a crop of spot's outline and the errors by ring count).

    python -m experiments.studies.antialias_edges [--res 128] [--out docs/images/antialias.png]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch
import torch.nn.functional as F

import difftex
from difftex.testing import icosphere, spot_mesh, spot_mvp

SS = 8
RINGS = (0, 1, 2, 3)


def scenes() -> dict:
    """{name: (verts [V, 3], faces [F, 3], mvp [4, 4])}, float64."""
    from experiments.fit.fit_pose import cube, view_matrices

    mvp = spot_mvp(2.5, (0.3, 0.2, 1.0)).double()
    out = {"cube": (*cube(torch.float64), view_matrices(1, dtype=torch.float64)[0])}
    for s in (1, 2, 3, 4):
        v, f = icosphere(s, dtype=torch.float64)
        out[f"icosphere({s})"] = (v * 0.5, f, mvp)
    m = spot_mesh()
    out["spot"] = (m.positions.double(), m.faces, mvp)
    return out


def edge_errors(res: int = 128, names: tuple[str, ...] | None = None) -> dict:
    """{scene: {"faces", "edge_px", "mask", rings...: mean abs error on silhouette pixels}} and the images."""
    result = {}
    for name, (v, f, mvp) in scenes().items():
        if names is not None and name not in names:
            continue
        pos = difftex.camera.transform(v, mvp)
        frags = difftex.rasterize(pos, f, (res, res))
        mask = frags.mask.double()[:, None]
        ref = F.avg_pool2d(difftex.rasterize(pos, f, (res * SS, res * SS)).mask.double()[:, None], SS)
        edge = (ref > 0) & (ref < 1)
        row = {"faces": int(f.shape[0]), "edge_px": int(edge.sum()), "mask": float((mask - ref)[edge].abs().mean()),
               "images": {"mask": mask, "reference": ref}}
        for k in RINGS:
            aa = difftex.antialias(mask, frags, pos, f, rings=k)
            row[k] = float((aa - ref)[edge].abs().mean())
            row["images"][k] = aa
        result[name] = row
    return result


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [1.6, 1]})
    im = result["spot"]["images"]
    # The 40x40 window with the most silhouette pixels.
    ref = im["reference"][0, 0]
    edge = ((ref > 0) & (ref < 1)).double()[None, None]
    n = 40
    count = F.avg_pool2d(edge, n, stride=1)[0, 0]
    r, c = divmod(int(count.argmax()), count.shape[1])
    crop = (slice(r, r + n), slice(c, c + n))
    tiles = [im[k][0, 0][crop] for k in ("mask", 0, 2, "reference")]
    ax[0].imshow(torch.cat(tiles, 1).numpy(), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    ax[0].set_title("spot's outline: aliased | rings=0 (paper) | rings=2 | 8x8 supersampled")
    ax[0].set_xticks([]); ax[0].set_yticks([])
    names = list(result)
    x = torch.arange(len(names)).float()
    width = 0.16
    ax[1].bar(x - 2 * width, [result[n]["mask"] for n in names], width, label="aliased mask", color="gray")
    for i, k in enumerate(RINGS):
        ax[1].bar(x + (i - 1) * width, [result[n][k] for n in names], width, label=f"rings={k}")
    ax[1].set_xticks(x.numpy(), [f"{n.replace('icosphere', 'ico')}\n{result[n]['faces']}" for n in names], fontsize=7)
    ax[1].set_xlabel("scene, triangles (128x128)")
    ax[1].set_ylabel("mean |error| on silhouette pixels")
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--out", default="docs/images/antialias.png")
    args = p.parse_args()
    result = edge_errors(args.res)
    print(f"{'scene':14s} {'faces':>6s} {'edge px':>7s} {'mask':>6s} " + " ".join(f"rings={k}" for k in RINGS))
    for name, r in result.items():
        print(f"{name:14s} {r['faces']:6d} {r['edge_px']:7d} {r['mask']:6.3f} "
              + " ".join(f"{r[k]:7.3f}" for k in RINGS))
    plot(result, Path(args.out))


if __name__ == "__main__":
    main()

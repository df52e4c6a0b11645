"""The painter's algorithm against the z-buffer on the two scenes that defeat it.

The seed notes: sort triangles far to near and paint back to front (the
painter's algorithm), but "object-based depth order does not always
exist". Two triangles that pierce each other and three that overlap in a
cycle (``difftex.testing.visibility``) are drawn by :func:`difftex.painter`
(sorted by the farthest corner, and by the mean corner depth) and by the
z-buffer (:func:`difftex.rasterize`); both are compared pixel by pixel with
a brute-force float64 reference (every triangle tested at every pixel
centre). Prints the wrong-pixel counts and writes the figure.

    python -m experiments.studies.painter_foil [--res 128] [--out docs/images/painter.png]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from difftex import painter, rasterize
from difftex.testing.visibility import brute_force_ids, cyclic_triangles, intersecting_triangles

SCENES = {"two intersecting triangles": intersecting_triangles, "cyclic overlap of three": cyclic_triangles}


def wrong_pixels(res: int = 128) -> dict:
    """{scene: {"painter (farthest)", "painter (mean)", "z-buffer", "covered"}} pixel counts, with the id images."""
    out = {}
    for name, scene in SCENES.items():
        pos, faces = scene()
        truth = brute_force_ids(pos, faces, (res, res))
        ids = {"z-buffer": rasterize(pos, faces, (res, res)).tri_id[0]}
        for key in ("farthest", "mean"):
            ids[f"painter ({key})"] = painter(pos, faces, (res, res), sort=key).tri_id[0]
        out[name] = {"covered": int((truth >= 0).sum()), "truth": truth, "ids": ids,
                     **{k: int((v != truth).sum()) for k, v in ids.items()}}
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(["white", "tab:blue", "tab:orange", "tab:green"])
    fig, ax = plt.subplots(2, 3, figsize=(10, 6.8))
    for r, (name, res) in enumerate(result.items()):
        p, z, truth = res["ids"]["painter (farthest)"], res["ids"]["z-buffer"], res["truth"]
        ax[r, 0].imshow(p + 1, cmap=cmap, vmin=0, vmax=3, interpolation="nearest")
        ax[r, 0].set_title(f"painter: {res['painter (farthest)']} wrong px")
        ax[r, 1].imshow(z + 1, cmap=cmap, vmin=0, vmax=3, interpolation="nearest")
        ax[r, 1].set_title(f"z-buffer: {res['z-buffer']} wrong px")
        wrong = torch.stack([(p != truth).float(), torch.zeros_like(truth, dtype=torch.float),
                             torch.zeros_like(truth, dtype=torch.float)], -1)
        ax[r, 2].imshow(wrong * 0.8 + 0.2 * (truth >= 0).float()[..., None], interpolation="nearest")
        ax[r, 2].set_title("painter's wrong pixels (red)")
        ax[r, 0].set_ylabel(f"{name}\n({res['covered']} px covered)")
    for a in ax.flat:
        a.set_xticks([]); a.set_yticks([])
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--out", default="docs/images/painter.png")
    args = p.parse_args()
    result = wrong_pixels(args.res)
    for name, r in result.items():
        print(f"{name}: " + ", ".join(f"{k} {r[k]}" for k in ("covered", "painter (farthest)", "painter (mean)",
                                                             "z-buffer")))
    plot(result, Path(args.out))


if __name__ == "__main__":
    main()

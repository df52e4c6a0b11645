"""Cube map against equirectangular map at equal texel count: lookup error by elevation.

The seed notes call the spherical (latitude-longitude) map "prone to
distortion" and the cube map the alternative. Measured here: a closed-form
smooth function of direction is stored in a cube map of S^2 texels a face
and in an equirectangular map of H x 2H texels with 2 H^2 = 6 S^2 (the same
texel count), each texel holding the function at its centre's direction;
both are read with bilinear filtering (``difftex.envmap.cubemap`` /
``difftex.envmap.equirect``) at random directions, and the absolute error
against the function is binned by elevation (degrees above the horizon).

    python -m experiments.studies.envmap_poles [--size 32] [--out docs/images/envmap_poles.png]
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from difftex.envmap import cube_to_direction, cubemap, equirect, equirect_uv_to_direction


def field(d: torch.Tensor) -> torch.Tensor:
    """[..., 3] unit directions -> [..., 1], a smooth function with detail at every elevation."""
    x, y, z = d.unbind(-1)
    return (torch.sin(3 * x + 1) * torch.cos(2 * z) + 0.5 * torch.sin(4 * y + 2 * x)).unsqueeze(-1)


def _texel_centres(n: int, dtype: torch.dtype) -> torch.Tensor:
    return (torch.arange(n, dtype=dtype) + 0.5) / n


def cube_of(S: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """[1, 6, 1, S, S]: the field at every cube texel centre."""
    c = _texel_centres(S, dtype)
    v, u = torch.meshgrid(c, c, indexing="ij")
    face = torch.arange(6).view(6, 1, 1).expand(6, S, S)
    d = cube_to_direction(face, torch.stack((u, v), -1).expand(6, S, S, 2))
    return field(d / d.norm(dim=-1, keepdim=True)).permute(0, 3, 1, 2).unsqueeze(0)


def equirect_of(H: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """[1, 1, H, 2H]: the field at every equirectangular texel centre."""
    v, u = torch.meshgrid(_texel_centres(H, dtype), _texel_centres(2 * H, dtype), indexing="ij")
    return field(equirect_uv_to_direction(torch.stack((u, v), -1))).permute(2, 0, 1).unsqueeze(0)


def errors_by_elevation(S: int, n: int = 200_000, bins: int = 18, seed: int = 0) -> dict:
    """Mean and largest absolute bilinear error per elevation bin for the cube (S^2 a face) and the
    equirectangular map of the same texel count (H = round(S sqrt 3))."""
    H = round(S * math.sqrt(3))
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    truth = field(d)[:, 0]
    dirs = d.view(1, 1, n, 3)
    err = {"cube": (cubemap(cube_of(S), dirs)[0, 0, 0] - truth).abs(),
           "equirect": (equirect(equirect_of(H), dirs)[0, 0, 0] - truth).abs()}
    elevation = torch.rad2deg(torch.asin(d[:, 1].clamp(-1, 1)))
    edges = torch.linspace(-90, 90, bins + 1, dtype=torch.float64)
    which = torch.bucketize(elevation, edges[1:-1])
    out = {"S": S, "H": H, "texels": {"cube": 6 * S * S, "equirect": 2 * H * H},
           "centres": ((edges[:-1] + edges[1:]) / 2).tolist()}
    for name, e in err.items():
        out[name] = {"mean": [e[which == b].mean().item() for b in range(bins)],
                     "max": [e[which == b].max().item() for b in range(bins)]}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=32, help="cube face size S (the equirect map gets the same texels)")
    p.add_argument("--out", default="results/envmap_poles/envmap_poles.png",
                   help="the chart (docs/images/envmap_poles.png is the one the README shows)")
    args = p.parse_args()
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = errors_by_elevation(args.size)
    print(f"cube {r['texels']['cube']} texels (S = {r['S']}), equirect {r['texels']['equirect']} texels "
          f"(H = {r['H']}); mean |error| by elevation:")
    print("elevation  cube      equirect")
    for c, a, b in zip(r["centres"], r["cube"]["mean"], r["equirect"]["mean"]):
        print(f"{c:+6.0f}    {a:.2e}  {b:.2e}")
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    for name, colour in (("cube", "tab:blue"), ("equirect", "tab:red")):
        ax.semilogy(r["centres"], r[name]["mean"], "-o", color=colour, ms=3, label=f"{name} mean")
        ax.semilogy(r["centres"], r[name]["max"], "--", color=colour, label=f"{name} max")
    ax.set_xlabel("elevation (degrees)")
    ax.set_ylabel("|bilinear lookup - f(direction)|")
    ax.set_title(f"equal texel count: cube 6x{r['S']}^2 vs equirect {r['H']}x{2 * r['H']}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""Every filter on one grazing view of a textured plane, side by side with the reference.

The spot texture (1024x1024, repeat) on the ground plane of
``difftex.scenes.grazing_plane`` (camera 1 unit up, pitched 20 degrees down),
rendered by each filter at 192x192 and by 16x16 supersampled bilinear (the
reference). Writes a labelled PNG grid with each filter's PSNR and forward
time, and prints the table.

    python experiments/compare_filters.py [--out docs/images/filters.png]
"""
from __future__ import annotations

import argparse
import importlib
import time
from pathlib import Path

import torch
import torch.nn.functional as F

import difftex
from difftex.metrics import psnr
from difftex.testing.scenes import grazing_plane

ROOT = Path(__file__).resolve().parent.parent


def methods() -> list[tuple[str, dict]]:
    out = [("nearest", {}), ("bilinear", {}), ("bicubic", {}), ("trilinear", {}),
           ("anisotropic", {"max_aniso": 4}), ("anisotropic", {"max_aniso": 16}), ("ewa", {"max_aniso": 16})]
    if "auto" in importlib.import_module("difftex.texture.options").FILTERS:
        out.append(("auto", {}))
    return out


def render(tex, res: int, pitch: float, filter: str, **kw) -> torch.Tensor:
    uv, dx, dy = grazing_plane(res, pitch)
    return difftex.sample(tex, uv, filter=filter, wrap="repeat", uv_dx=dx, uv_dy=dy, **kw)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", type=int, default=192)
    p.add_argument("--pitch", type=float, default=20.0)
    p.add_argument("--ss", type=int, default=16)
    p.add_argument("--out", default="results/compare_filters/filters.png")
    args = p.parse_args()
    torch.set_num_threads(1)  # steadier timings on a shared machine
    tex = difftex.load_texture(ROOT / "data" / "spot" / "spot_texture.png")
    uv_ss, _, _ = grazing_plane(args.res, args.pitch, ss=args.ss)
    ref = F.avg_pool2d(difftex.sample(tex, uv_ss, filter="bilinear", wrap="repeat"), args.ss)
    tiles, rows = [ref], ["| filter | PSNR dB | forward ms |", "|---|---|---|"]
    labels = [f"reference ({args.ss}x{args.ss} bilinear)"]
    for name, kw in methods():
        render(tex, args.res, args.pitch, name, **kw)  # warm-up
        t = time.perf_counter()
        img = render(tex, args.res, args.pitch, name, **kw)
        ms = (time.perf_counter() - t) * 1e3
        label = name + (f" {kw['max_aniso']}" if name == "anisotropic" else "")
        db = psnr(img, ref)
        tiles.append(img)
        labels.append(f"{label}: {db:.1f} dB, {ms:.0f} ms")
        rows.append(f"| {label} | {db:.2f} | {ms:.1f} |")
    print("\n".join(rows))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cols = 3
    n = len(tiles)
    fig, axes = plt.subplots(-(-n // cols), cols, figsize=(3.3 * cols, 3.5 * -(-n // cols)))
    for ax in axes.flat:
        ax.axis("off")
    for ax, img, label in zip(axes.flat, tiles, labels):
        ax.imshow(img[0].permute(1, 2, 0).clamp(0, 1).numpy())
        ax.set_title(label, fontsize=9)
    fig.suptitle(f"spot texture on a plane, camera pitched {args.pitch:g} degrees, {args.res}x{args.res}")
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""Every filter on one grazing view of a textured plane, side by side with the reference.

The spot texture (1024x1024, repeat) on the ground plane of
``difftex.testing.grazing_plane`` (camera 1 unit up, pitched 20 degrees down),
rendered by each filter at 192x192 and by 16x16 supersampled bilinear (the
reference). Writes a labelled PNG grid with each filter's PSNR and forward
time (median of ``--repeats`` interleaved rounds), and prints the table.

    python -m experiments.studies.compare_filters [--out docs/images/filters.png]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

import difftex
from difftex.metrics import psnr
from difftex.testing import grazing_plane, spot_texture, supersampled, time_interleaved
from difftex.texture.options import FILTERS


def methods() -> list[tuple[str, dict]]:
    out = [("nearest", {}), ("bilinear", {}), ("bicubic", {}), ("trilinear", {}),
           ("anisotropic", {"max_aniso": 4}), ("anisotropic", {"max_aniso": 16}), ("ewa", {"max_aniso": 16})]
    if "auto" in FILTERS:
        out.append(("auto", {}))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", type=int, default=192)
    p.add_argument("--pitch", type=float, default=20.0)
    p.add_argument("--ss", type=int, default=16)
    p.add_argument("--repeats", type=int, default=3, help="timed rounds (median reported)")
    p.add_argument("--out", default="results/compare_filters/filters.png",
                   help="the PNG grid (docs/images/filters.png is the one the README shows)")
    args = p.parse_args()
    torch.set_num_threads(1)  # steadier timings on a shared machine
    tex = spot_texture()
    uv_ss, _, _ = grazing_plane(args.res, args.pitch, ss=args.ss)
    ref = supersampled(tex, uv_ss, args.ss, "repeat")
    tiles, rows = [ref], ["| filter | PSNR dB | forward ms |", "|---|---|---|"]
    labels = [f"reference ({args.ss}x{args.ss} bilinear)"]
    uv, dx, dy = grazing_plane(args.res, args.pitch)

    def render(name: str, kw: dict):
        return lambda: difftex.sample(tex, uv, filter=name, wrap="repeat", uv_dx=dx, uv_dy=dy, **kw)

    with torch.no_grad():
        timings = time_interleaved([render(name, kw) for name, kw in methods()], args.repeats)
        for (name, kw), timing in zip(methods(), timings):
            img = render(name, kw)()
            label = name + (f" {kw['max_aniso']}" if name == "anisotropic" else "")
            db = psnr(img, ref)
            tiles.append(img)
            labels.append(f"{label}: {db:.1f} dB, {timing.median:.0f} ms")
            rows.append(f"| {label} | {db:.2f} | {timing.median:.1f} |")
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

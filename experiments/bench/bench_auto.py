"""filter="auto" against anisotropic 16 and trilinear: PSNR, time and taps, and auto's tolerance sweep.

Scenes and references are the speed-vs-accuracy suite, :mod:`difftex.testing.suite` (17
scenes: planes from head-on to 5 degrees with the closed-form checker and
the spot texture, the spherical-mapped sphere from magnified to 100x, spot
from three distances; ``--res`` pixels a side, 128 by default).

Times are medians of forward passes with 1 thread, the three filters run
alternately (interleaved) so they see the same machine load; each pass
builds the pyramid from the texture (part of the cost, as in training).
"Taps" counts trilinear taps (anisotropic / auto) or pixels (trilinear).
The sweep gives auto's PSNR minus anisotropic 16's and its share of
anisotropic's taps at several tolerances.

Prints markdown tables and writes them to docs/auto_filter.md.

    python -m experiments.bench.bench_auto [--res 128] [--repeats 7] [--out docs/auto_filter.md]
"""
from __future__ import annotations

import argparse
import platform
from pathlib import Path

import torch

import difftex
from difftex.metrics import psnr
from difftex.testing import build_scenes, time_interleaved
from difftex.texture.filters.anisotropic import tap_count
from difftex.texture.filters.auto import auto_tap_count
from difftex.texture.lod import ellipse, footprint
from difftex.texture.options import DEFAULT_TOLERANCE

ROOT = Path(__file__).resolve().parents[2]

SWEEP = (0.0, DEFAULT_TOLERANCE, 0.25, 0.5, 1.0)
FILTERS = (("trilinear", {"filter": "trilinear"}), ("anisotropic 16", {"filter": "anisotropic", "max_aniso": 16}),
           ("auto", {"filter": "auto"}))

NOTES = """
## How auto chooses (difftex/texture/filters/auto.py)

Per pixel, with the footprint's axes from `difftex.texture.lod.ellipse` (level-0 texels, times `2^lod_bias`):
`N_a = min(ceil(major / max(minor, 1/2)), max_aniso)` and `N = ceil(N_a / (1 + tolerance))` trilinear taps
(`N = N_a` where the axis ratio exceeds max_aniso: those taps are already wider than the minor axis), run
through the anisotropic filter's own code (`anisotropic_taps` with these N). Pixels whose major axis is
under half a texel get one tap at level 0 (bilinear), round footprints one tap (trilinear), long ones 2-16.
`tolerance` (default 0.1) is how much wider (as a fraction) a tap's prefilter may be than anisotropic's;
with 0 auto equals anisotropic wherever the minor axis is at least half a texel.

## Findings

* Within 0.5 dB of anisotropic 16 on every scene above (worst -0.33 dB, the 5-degree spot plane), never
  more taps. On these scenes that leaves little to save: anisotropic's taps are nearly all needed for its
  accuracy, so auto takes 0-3 % fewer taps and its time is anisotropic's within this machine's noise
  (forward+backward in experiments/studies/speed_vs_accuracy.py's runs: mean over scenes 1.02-1.04x; single scenes 0.79-1.36x, the outliers on different scenes from run to run). It saves where footprints are magnified below half a texel (one read instead of anisotropic's two) or round:
  on a sphere magnified 4x (not in the table) auto reads half of anisotropic's taps, 56.7 vs 64.3 dB.
* Issue 19's target (0.7x anisotropic-16's forward+backward in the mean over these scenes, within 0.5 dB
  on each) is out of reach of any choice among the filters difftex has: in one run
  (docs/speed_vs_accuracy.md, its last table) trilinear alone, one tap a pixel, is 0.72x and 14-24 dB short
  on the grazing planes, and the cheapest single filter within 0.5 dB, picked per scene with hindsight
  (bilinear, trilinear, anisotropic 2-16, ripmap or sat), averages 0.90x. (Before the N-tap forward and
  backward read eight points at a time, anisotropic-16 was slower and these were 0.59x and 0.87x: the faster
  the taps, the more of every filter's time is the per-call work they share.) A per-pixel mix pays every
  filter's per-call work (pyramid, table) on top.
* What the first version gave away: with tolerance 0.25 it took 7-10 % fewer taps on grazing planes but
  fell 2.1 dB under anisotropic 16 on the closed-form checker plane at 5 degrees (1.2 dB on the spot
  plane); with a one-texel spacing floor it read plain bilinear on a sphere magnified 2x, 5.3 dB under
  anisotropic, whose two level-0 taps there act as supersampling inside the pixel. Below half a texel the
  gap between one and two level-0 taps stays 5-8 dB, but both errors are under one 8-bit level (52-72 dB).
* Making nearly-round footprints (axis ratio 1-1.25) one trilinear tap, as a first version did, costs
  3-5 dB on spot's texture: anisotropic's two taps there sit a full level finer than trilinear's one, and
  trilinear's level (box pyramid + bilinear) is already blurrier than the pixel's box footprint. So the
  tolerance scales the tap count relative to anisotropic's, and the one-tap case is only reached where
  `N_a / (1 + tolerance) <= 1`.
* Larger tolerances trade fast (the sweep table above).
* A count rounded from the axis ratio itself, `ceil(ratio / (1 + tolerance))` with at least two taps where
  anisotropic takes two, saves 6-7 % of the taps at tolerance 0.1 but loses up to 0.8 dB; not kept.
* "Brilinear" taps (snapping each tap's level to an integer within a band, one bilinear read instead of
  two) were tried and dropped: -0.2 to -1.2 dB for at most ~10 % time on these scenes.
* A plain texture tensor given to any bilinear-tap mip filter (auto included) builds only the pyramid
  levels the footprints read (`difftex.levels_needed` gives the count), with identical values and gradients.
"""


def taps(scene, filter: str, tolerance: float = DEFAULT_TOLERANCE) -> int:
    """Trilinear taps of ``filter`` over the image (trilinear: one a pixel)."""
    dx, dy = scene.uv_dx.reshape(-1, 2), scene.uv_dy.reshape(-1, 2)
    if filter == "trilinear":
        return dx.shape[0]
    H, W = scene.texture.shape[-2:]
    fp = footprint(dx, dy, H, W)
    ell = ellipse(fp)
    n = tap_count(ell, fp, 16) if filter == "anisotropic 16" else auto_tap_count(ell, fp, 0.0, 16, tolerance)
    return int(n.sum())


def lookup(scene, **kw) -> torch.Tensor:
    return difftex.sample(scene.texture, scene.uv, uv_dx=scene.uv_dx, uv_dy=scene.uv_dy, wrap=scene.wrap, **kw)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default=str(ROOT / "docs" / "auto_filter.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows, sweep = [], []
    with torch.no_grad():
        for scene in build_scenes(args.res, ss_rates=()):
            score = lambda out: psnr(out, scene.reference, mask=scene.mask)
            timings = time_interleaved([lambda kw=kw: lookup(scene, **kw) for _, kw in FILTERS], args.repeats)
            row = {name: (score(lookup(scene, **kw)), t.median, taps(scene, name))
                   for (name, kw), t in zip(FILTERS, timings)}
            rows.append((scene.name, row))
            a16, n16 = row["anisotropic 16"][0], row["anisotropic 16"][2]
            sweep.append((scene.name, [(score(lookup(scene, filter="auto", tolerance=t)) - a16,
                                        taps(scene, "auto", t) / n16) for t in SWEEP]))
            print(scene.name, {k: (round(v[0], 2), round(v[1], 1), v[2]) for k, v in row.items()}, flush=True)
    lines = [
        "# filter=\"auto\" vs anisotropic 16 vs trilinear",
        "",
        f"Generated by `python -m experiments.bench.bench_auto` (auto tolerance {DEFAULT_TOLERANCE}, the default) on the "
        f"scenes of experiments/studies/speed_vs_accuracy.py at {args.res}x{args.res}. PSNR in dB against the scene's "
        "reference (closed form for the checker planes, else 16x16 supersampled bilinear) over its scored "
        f"pixels; forward time in ms (median of {args.repeats}, the three filters interleaved, 1 thread, pyramid "
        f"built inside the timed call; torch {torch.__version__}, {platform.machine()}, shared 2-core machine, so "
        "+-20% noise); taps = trilinear taps (trilinear: one per pixel).",
        "",
        "| scene | trilinear dB / ms / taps | aniso 16 dB / ms / taps | auto dB / ms / taps | auto - aniso16 dB |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for name, row in rows:
        cells = [f"{row[f][0]:.2f} / {row[f][1]:.1f} / {row[f][2]}" for f, _ in FILTERS]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {row['auto'][0] - row['anisotropic 16'][0]:+.2f} |")
    lines += ["", "Tolerance sweep: auto's PSNR minus anisotropic 16's (dB) / auto's taps as a share of "
              "anisotropic's.", "",
              "| scene | " + " | ".join(f"tolerance {t:g}" for t in SWEEP) + " |",
              "| --- |" + " ---: |" * len(SWEEP)]
    for name, cells in sweep:
        lines.append(f"| {name} | " + " | ".join(f"{d:+.2f} / {r:.2f}" for d, r in cells) + " |")
    worst = [min(cells[i][0] for _, cells in sweep) for i in range(len(SWEEP))]
    lines.append("| worst | " + " | ".join(f"{w:+.2f}" for w in worst) + " |")
    text = "\n".join(lines) + "\n" + NOTES
    print(text)
    Path(args.out).write_text(text)


if __name__ == "__main__":
    main()

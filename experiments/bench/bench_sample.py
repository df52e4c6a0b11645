"""Speed of difftex.sample's single-level reads against Dr.Jit and grid_sample, measured in the same run.

A 1024x1024 RGB texture sampled at 512x512 points (``--size``, ``--points``),
bilinear and bicubic (``--filters``), every wrap mode (``--wraps``), forward
and forward+backward (gradients to the texture and the uv). The peers are
timed interleaved with ours, in a new order every round (a pause before
each library's turn: after a call torch's and Dr.Jit's worker threads spin
for 10-20 ms and would slow the next call on a 2-core machine; in a fixed
order, our planar bilinear clamp forward, timed right after Dr.Jit's, took
6.6-6.9 ms after a 30 ms pause, 3.4-4.8 ms shuffled). Two tables:

* **steady state** (the speed issues' protocol, ``difftex.testing.time_blocks``):
  blocks of ``--calls`` back-to-back calls of one library, the median of
  all but the first ``--skip`` of each block, libraries interleaved block
  by block (``--blocks`` rounds): a render or training loop's time, its
  own threads awake and its caches warm;
* **first call after an idle pause** (``time_interleaved``): each timed
  call the first after the pause (on some VMs such a call finds the caches
  emptied and its worker threads slow to wake, see
  difftex/testing/timing.py), reported apart.

The peers:

* **Dr.Jit** (the JIT behind Mitsuba 3; the ``peers`` extra, LLVM backend on
  the CPU): ``Texture2f`` with its wrap mode (repeat, clamp, mirror: it has
  no border constant) and filter (bilinear: ``eval``; bicubic: ``eval_cubic``,
  a cubic B-spline, not difftex's Keys cubic, so those values differ). The
  texture is built once, channels-last, outside the timed calls; a timed
  call evaluates the points (and backpropagates to the texture tensor and
  the points). Skipped with a message where drjit is not installed.
* **ours, channels_last**: the same texture given in torch's channels_last
  memory format (Dr.Jit's interleaved layout), which the native kernel
  reads in place.
* **grid_sample**: difftex's own torch path (``difftex.backend("grid_sample")``,
  grid_sample with the folding / padding of every wrap mode).

On a shared VM the first call after a pause runs slower than any kernel
explains: measured here, torch's sum of the 12 MB texture took 5.9-6.2 ms
right after a 30 ms pause and 0.27-0.30 ms in a loop (a pure-Python loop
1.0x), so the after-the-pause table mostly times how the host wakes the
memory path; its first line measures that once per run.

Printed per case: medians in ms, the median of the paired ratio ours / peer
(the k-th timed call of one with the k-th of the other; after a pause: the
same round) with its interquartile range, and the achieved bandwidth: the
bytes a read must move at least (texture once, uv, the output; with the
backward also the output gradient, the texture gradient zeroed and
written, the uv gradient) over the time. Before timing, the script checks
that Dr.Jit reads the same point for the same uv: the bilinear values (and
texture gradients) of both agree to float32 rounding. Last, the trilinear
filter's forward+backward against our bilinear one (same points, the
view's uv derivatives).

    python -m experiments.bench.bench_sample [--uv view|random] [--filters bilinear] [--blocks 8] [--out docs/bench_sample.md]

Target (issue 19, on a quiet 2-core machine): bilinear and bicubic at most
0.8x Dr.Jit, forward and forward+backward, every wrap mode; trilinear
forward+backward at most 2x our bilinear forward+backward.
"""
from __future__ import annotations

import argparse
import math
import statistics
from typing import Callable, Optional

import torch

import difftex
from difftex.testing import time_interleaved
from difftex.testing.timing import Timing, time_blocks
from difftex import _native as native

FILTERS = {"bilinear": "Linear", "bicubic": "cubic", "nearest": "Nearest"}
DRJIT_WRAPS = ("repeat", "clamp", "mirror")


def make_uv(res: int, pattern: str, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """[1, res, res, 2] uv of a rotated view 1.3x the texture (or uniform random), and its uv_dx, uv_dy."""
    if pattern == "random":
        g = torch.Generator().manual_seed(seed)
        uv = torch.rand(1, res, res, 2, generator=g)
    else:
        s = (torch.arange(res, dtype=torch.float32) + 0.5) / res - 0.5
        yy, xx = torch.meshgrid(s, s, indexing="ij")
        a, scale = math.radians(17), 1.3
        uv = torch.stack((scale * (math.cos(a) * xx - math.sin(a) * yy) + 0.5,
                          scale * (math.sin(a) * xx + math.cos(a) * yy) + 0.5), -1)[None]
    a, scale = math.radians(17), 1.3 / res
    dx = torch.tensor([math.cos(a), math.sin(a)]) * scale
    dy = torch.tensor([-math.sin(a), math.cos(a)]) * scale
    return uv.contiguous(), dx.expand_as(uv).contiguous(), dy.expand_as(uv).contiguous()


def native_paths() -> str:
    """Which vector paths the native kernel takes on this CPU (the forward's width decides its speed)."""
    kernel = native.load()
    if kernel is None:
        return "native kernel not built: the torch path"
    if kernel.wide_available():
        return "native forward sixteen points at a time (AVX-512), backward eight (AVX2)"
    return "native reads eight points at a time (AVX2)" if kernel.simd_available() else "native scalar loops"


def bytes_moved(C: int, H: int, W: int, M: int, grad: bool, item: int = 4) -> int:
    """The least bytes a read moves: texture, uv, output; backward: output gradient, texture gradient (zero + write
    + the texture read again) and uv gradient."""
    n = C * H * W + 2 * M + C * M
    if grad:
        n += C * M + 3 * C * H * W + 2 * M
    return n * item


class DrJit:
    """Dr.Jit's ``Texture2f`` (LLVM) over the same texture and points; None where drjit is missing."""

    def __init__(self, tex: torch.Tensor, uv: torch.Tensor, threads: int):
        import drjit as dr
        from drjit.llvm.ad import Array2f, Float, TensorXf, Texture2f
        self.dr, self.Array2f, self.Float, self.Texture2f = dr, Array2f, Float, Texture2f
        dr.set_thread_count(threads)
        self.data = TensorXf(tex[0].permute(1, 2, 0).contiguous().numpy())  # channels-last, Dr.Jit's layout
        flat = uv.reshape(-1, 2)
        self.u, self.v = Float(flat[:, 0].numpy()), Float(flat[:, 1].numpy())
        self.textures = {}

    def texture(self, filter: str, wrap: str):
        key = (filter, wrap)
        if key not in self.textures:
            dr = self.dr
            mode = dr.FilterMode.Nearest if filter == "nearest" else dr.FilterMode.Linear
            t = self.dr.llvm.ad.TensorXf(self.data)
            dr.enable_grad(t)
            self.textures[key] = (t, self.Texture2f(t, filter_mode=mode, wrap_mode=getattr(dr.WrapMode, wrap.title())))
        return self.textures[key]

    def step(self, filter: str, wrap: str, grad: bool) -> Callable[[], object]:
        dr = self.dr
        t, tex = self.texture(filter, wrap)

        def run():
            pos = self.Array2f(self.u, self.v)
            if grad:
                dr.enable_grad(pos)
            out = tex.eval_cubic(pos) if filter == "bicubic" else tex.eval(pos)
            if not grad:
                dr.eval(out)
                dr.sync_thread()  # the LLVM backend runs kernels asynchronously: wait for them
                return out
            dr.backward_from(dr.llvm.ad.Array3f(*out) if len(out) == 3 else out[0])
            gt, gp = dr.grad(t), dr.grad(pos)
            dr.eval(gt, gp)
            dr.sync_thread()
            # The texture's gradient accumulates over calls (as a parameter's .grad does in torch):
            # clearing it here stops later backward passes from reaching it (drjit 1.x).
            return out, gt, gp
        return run

    def values(self, filter: str, wrap: str) -> tuple[torch.Tensor, torch.Tensor]:
        """[C, M] values and the [C, H, W] texture gradient for a unit output gradient (a fresh texture)."""
        self.textures.pop((filter, wrap), None)
        out, gt, _ = self.step(filter, wrap, True)()
        self.textures.pop((filter, wrap), None)
        vals = torch.stack([torch.from_numpy(self.dr.llvm.Float(o).numpy().copy()) for o in out])
        g = torch.from_numpy(gt.numpy().copy()).permute(2, 0, 1)
        return vals, g


def ours_step(tex: torch.Tensor, uv: torch.Tensor, grad: bool, backend: str, **kw) -> Callable[[], object]:
    """One timed call of difftex.sample (and its backward where ``grad``), as a user makes it.

    The default backend ("auto") is called plainly, without ``difftex.backend``'s context: measured on this
    machine, entering and leaving it costs about 0.1 ms right after a timed call's pause (a cold cache), which
    is 4% of a 1024^2 bilinear forward and not part of the read. Inputs that need no gradient build no graph.
    """
    t, u = tex.clone().requires_grad_(grad), uv.clone().requires_grad_(grad)

    def call():
        out = difftex.sample(t, u, **kw)
        return torch.autograd.grad(out, (t, u), torch.ones_like(out)) if grad else out

    def run():
        if backend == "auto":
            return call()
        with difftex.backend(backend):
            return call()
    return run


def ratio_stats(a, b) -> tuple[float, float, float]:
    """Median and quartiles of the paired a / b (two Timings of one time_interleaved or time_blocks call)."""
    r = [x / y for x, y in zip(a.times_ms, b.times_ms)]
    if len(r) < 2:
        return r[0], r[0], r[0]
    q = statistics.quantiles(r, n=4, method="inclusive")
    return statistics.median(r), q[0], q[2]


def agreement(peer: Optional[DrJit], tex: torch.Tensor, uv: torch.Tensor, wraps) -> list[str]:
    """Dr.Jit's bilinear values and texture gradients against ours: do both read the same point for the same uv?"""
    lines = []
    if peer is None:
        return lines
    for wrap in wraps:
        if wrap not in DRJIT_WRAPS:
            continue
        t = tex.clone().requires_grad_()
        out = difftex.sample(t, uv, filter="bilinear", wrap=wrap)
        (g,) = torch.autograd.grad(out, t, torch.ones_like(out))
        vals, gd = peer.values("bilinear", wrap)
        dv = (out.detach().reshape(vals.shape) - vals).abs().max().item()
        dg = ((g[0] - gd).abs().max() / g.abs().max()).item()
        lines.append(f"- bilinear {wrap}: values differ by at most {dv:.1e}, texture gradients by {dg:.1e} "
                     "of the largest")
    return lines


def timed(args, fns, steady: bool) -> list[Timing]:
    """Times of fns: steady state (time_blocks) or each call the first after a pause (time_interleaved)."""
    if steady:
        return time_blocks(fns, args.blocks, calls=args.calls, skip=args.skip, pause=args.pause, shuffle=True)
    # in a new order every round: a call right after Dr.Jit's ran 2x slower even after the pause
    return time_interleaved(fns, args.reps, warmup=2, pause=args.pause, shuffle=True)


def table(args, tex, uv, peer, steady: bool) -> list[str]:
    """The table of every filter, wrap and pass, in the steady state or as the first call after a pause."""
    H, W = tex.shape[-2:]
    M = uv.shape[1] * uv.shape[2]
    rows = ["| filter | wrap | pass | ours ms | ours channels_last ms | Dr.Jit ms | grid_sample ms | "
            "ours / Dr.Jit [IQR] | ours channels_last / Dr.Jit [IQR] | ours / grid_sample [IQR] | ours GB/s | "
            "Dr.Jit GB/s |", "|---" * 12 + "|"]
    tex_cl = tex.contiguous(memory_format=torch.channels_last)
    print("\n".join(rows), flush=True)
    for filt in args.filters:
        for wrap in args.wraps:
            for label, grad in (("forward", False), ("fwd+bwd", True)):
                kw = dict(filter=filt, wrap=wrap)
                fns = [ours_step(tex, uv, grad, "auto", **kw), ours_step(tex, uv, grad, "grid_sample", **kw),
                       ours_step(tex_cl, uv, grad, "auto", **kw)]
                has_peer = peer is not None and wrap in DRJIT_WRAPS
                if has_peer:
                    fns.append(peer.step(filt, wrap, grad))
                times = timed(args, fns, steady)
                ours, gs, cl = times[0], times[1], times[2]
                gb = bytes_moved(3, H, W, M, grad) / 1e6
                rg = ratio_stats(ours, gs)
                cells = [filt, wrap, label, f"{ours.median:.2f}", f"{cl.median:.2f}"]
                if has_peer:
                    rd, rc = ratio_stats(ours, times[3]), ratio_stats(cl, times[3])
                    cells += [f"{times[3].median:.2f}", f"{gs.median:.2f}", f"{rd[0]:.2f} [{rd[1]:.2f}-{rd[2]:.2f}]",
                              f"{rc[0]:.2f} [{rc[1]:.2f}-{rc[2]:.2f}]"]
                else:
                    cells += ["-", f"{gs.median:.2f}", "-", "-"]
                cells += [f"{rg[0]:.2f} [{rg[1]:.2f}-{rg[2]:.2f}]", f"{gb / ours.median:.1f}",
                          f"{gb / times[3].median:.1f}" if has_peer else "-"]
                rows.append("| " + " | ".join(cells) + " |")
                print(rows[-1], flush=True)
    return rows


def wake_cost(tex: torch.Tensor, args) -> str:
    """The machine's own slowdown after the pause: torch's sum of the texture, as the first call after it and in the steady state."""
    total = lambda: tex.sum()  # noqa: E731
    (cold,) = timed(args, [total], False)
    (warm,) = timed(args, [total], True)
    return (f"The machine after the pause: torch's sum of the {tex.numel() * tex.element_size() / 2**20:.0f} MB "
            f"texture takes {cold.median:.2f} ms as the first call after it, {warm.median:.2f} ms in the steady state "
            f"({cold.median / warm.median:.1f}x): every library's first call pays this.")


def run(args) -> list[str]:
    torch.manual_seed(0)
    tex = torch.rand(1, 3, args.size, args.size)
    uv, dx, dy = make_uv(args.points, args.uv)
    peer = None
    try:
        peer = DrJit(tex, uv, torch.get_num_threads())
    except ImportError:
        print("# drjit is not installed (pip install 'difftex[peers]'): Dr.Jit columns skipped")
    rows = [wake_cost(tex, args), ""]
    print("# " + rows[0])
    for steady in (True, False):
        title = (f"**Steady state** (time_blocks): blocks of {args.calls} back-to-back calls of one library, the "
                 f"median of calls {args.skip + 1}-{args.calls} of every block, libraries interleaved block by block, "
                 f"{args.blocks} rounds (a render or training loop's time)."
                 if steady else "**First call after an idle pause**: each timed call the first after a "
                 f"{args.pause * 1e3:.0f} ms pause, {args.reps} rounds.")
        print("# " + title)
        rows += [title, ""] + table(args, tex, uv, peer, steady) + [""]
        if steady and not args.after_pause:
            break
    # Trilinear against our own bilinear, forward+backward, the same points.
    tri = ours_step(tex, uv, True, "auto", filter="trilinear", wrap="repeat", uv_dx=dx, uv_dy=dy)
    bil = ours_step(tex, uv, True, "auto", filter="bilinear", wrap="repeat")
    for steady in (True, False) if args.after_pause else (True,):
        a, b = timed(args, [tri, bil], steady)
        r = ratio_stats(a, b)
        rows.append(f"- trilinear fwd+bwd {a.median:.2f} ms, bilinear fwd+bwd {b.median:.2f} ms: trilinear / bilinear "
                    f"{r[0]:.2f} [{r[1]:.2f}-{r[2]:.2f}] (repeat, "
                    f"{'steady state' if steady else 'first call after a pause'})")
        print(rows[-1], flush=True)
    agree = agreement(peer, tex, uv, args.wraps)
    if agree:
        rows += ["", "Dr.Jit reads the same point for the same uv:"] + agree
        print("\n".join(rows[-len(agree) - 1:]), flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=1024, help="texture side in texels")
    p.add_argument("--points", type=int, default=512, help="points per side")
    p.add_argument("--uv", default="view", choices=["view", "random"])
    p.add_argument("--blocks", type=int, default=8, help="steady state: rounds of one block per library")
    p.add_argument("--calls", type=int, default=8, help="steady state: back-to-back calls per block")
    p.add_argument("--skip", type=int, default=2, help="steady state: untimed leading calls of every block")
    p.add_argument("--reps", type=int, default=15, help="after a pause: timed rounds")
    p.add_argument("--pause", type=float, default=0.03,
                   help="seconds slept before every block (steady state) or timed call (after a pause)")
    p.add_argument("--no-after-pause", dest="after_pause", action="store_false",
                   help="only the steady-state table (and trilinear line)")
    p.add_argument("--filters", nargs="+", default=["bilinear", "bicubic"], choices=list(FILTERS))
    p.add_argument("--wraps", nargs="+", default=["repeat", "clamp", "mirror", "border"],
                   choices=["repeat", "clamp", "mirror", "border"])
    p.add_argument("--out", default=None, help="also write the table to this markdown file")
    args = p.parse_args()
    head = (f"torch {torch.__version__}, {torch.get_num_threads()} threads, texture {args.size}^2 RGB float32, "
            f"{args.points}^2 points ({args.uv}), libraries interleaved in shuffled order; {native_paths()}")
    print("# " + head)
    rows = run(args)
    if args.out:
        with open(args.out, "w") as f:
            f.write(head + "\n\n" + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()

"""sample() at the largest finite uv: every filter x wrap x dtype, forward and backward, kernel and torch path.

Issue 42: at |v| >= 2^52 with wrap "repeat" the native backward of the tap filters never returned (its
band key kept v's whole periods, capped at 2^52, and stepped a band index down to [0, nb) one nb at a
time: about 2^50 steps). A hang cannot be caught inside the process that hangs, so each path's grid
runs in a child process (this file run as a script, the same interpreter and the same difftex) under a
deadline: a hang fails the test by its deadline, and the suite moves on.

The grid: float32 at 1e30, 3e38 and -3e38, float64 at 1e300 (finite, and far past 2^52 where no
fraction is left); uv points with both coordinates huge and with one huge and one ordinary; three
footprints (a point on level 0, a minified anisotropic one, the same with the derivatives needing a
gradient, which takes the torch front end of the tap filters instead of the kernel's). Each case
checks that

* values, texture gradient, uv gradient and derivative gradients are finite (stability.md: a finite uv
  gives finite values and gradients), and the values within the texels' range (bicubic aside);
* they equal those of the same read at the *equivalent* small uv (the huge coordinate is a whole number
  of periods: repeat and mirror read it at 0; clamp and border read it far past the edge, at
  ``sign * (10 + 0.5 / n)``, which keeps its phase on the texel grid, 0), to float rounding;
* on the kernel, they equal the torch path's at the same uv (as tests/test_backend.py holds them at
  ordinary uv).
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

# Wall-clock deadline of one path's whole grid (the child process): the grid takes a few seconds of
# compute (under 10 s on a loaded 2-core machine, torch path), plus the interpreter's start and imports.
DEADLINE_S = 120.0

WRAPS = ("repeat", "clamp", "mirror", "border")
# (dtype name, magnitude): the largest finite magnitudes the issue names (3e38 is within float32's 3.4e38).
MAGNITUDES = (("float32", 1e30), ("float32", 3e38), ("float32", -3e38), ("float64", 1e300))
# Footprints (uv_dx, uv_dy per point, in uv units on an 8 x 8 texture) and whether they need a gradient:
# "point" reads level 0 with one tap; "minify" (1.6 x 0.8 texels, tilted so the tap axis has a v part)
# reads two levels, several anisotropic taps.
FOOTPRINTS = (("point", (0.01, 0.0), (0.0, 0.01), False),
              ("minify", (0.2, 0.1), (-0.02, -0.05), False),
              ("minify-grad", (0.2, 0.1), (-0.02, -0.05), True))
BORDER = 0.25


def _filters() -> tuple[str, ...]:
    from difftex.texture.options import FILTERS
    return FILTERS


def _points(mag: float) -> list[tuple[float, float]]:
    """uv of the 12 points: both coordinates huge (different multiples of mag), or one huge, one ordinary."""
    f = [1.0, 0.75, 0.5, 0.625]  # exact binary fractions: mag * f stays a whole number of periods
    both = [(mag * a, mag * b) for a, b in zip(f, f[1:] + f[:1])]
    u_only = [(mag * a, 0.3 + 0.1 * i) for i, a in enumerate(f)]
    v_only = [(0.35 + 0.1 * i, mag * a) for i, a in enumerate(f)]
    return both + u_only + v_only


def _equivalent(c: float, wrap: str, n: int) -> float:
    """The small coordinate a huge whole-number one ``c`` reads like along an axis of n texels (others unchanged).

    repeat: c is a whole number of periods (1), mirror an even number (every float of this size is even):
    both read like 0. clamp / border: far past the edge, where every tap clamps (reads the border constant);
    ``10 + 0.5 / n`` is on the texel grid like c, so EWA's weights (which depend on that phase) match too.
    """
    if abs(c) < 1e6:
        return c
    if wrap in ("repeat", "mirror"):
        return 0.0
    return math.copysign(10.0 + 0.5 / n, c)


def _run_case(filter: str, wrap: str, dtype: torch.dtype, uv_list, dx, dy, deriv_grad: bool):
    """One read, forward and backward: (value, texture grad, uv grad, uv_dx grad, uv_dy grad)."""
    import difftex
    from difftex.texture.options import MIP_FILTERS
    g = torch.Generator().manual_seed(42)
    tex = torch.rand(1, 3, 8, 8, generator=g, dtype=torch.float64).to(dtype).requires_grad_()
    uv = torch.tensor(uv_list, dtype=torch.float64).to(dtype).view(1, 3, 4, 2).requires_grad_()
    kw = {}
    ins = [tex, uv]
    if filter in MIP_FILTERS:
        udx = torch.tensor(dx, dtype=dtype).expand(1, 3, 4, 2).clone().requires_grad_(deriv_grad)
        udy = torch.tensor(dy, dtype=dtype).expand(1, 3, 4, 2).clone().requires_grad_(deriv_grad)
        kw = {"uv_dx": udx, "uv_dy": udy}
        if deriv_grad:
            ins += [udx, udy]
    out = difftex.sample(tex, uv, filter=filter, wrap=wrap, border_value=BORDER, **kw)
    # A fixed, uneven output gradient (not all ones, which hides sign errors).
    w = torch.linspace(0.5, 1.5, out.numel(), dtype=torch.float64).to(dtype).view_as(out)
    grads = torch.autograd.grad(out, ins, w, allow_unused=True)
    grads = [torch.zeros_like(x) if gr is None else gr for x, gr in zip(ins, grads)]
    return [out.detach()] + list(grads)


def _spread(filter: str, wrap: str, footprint: str) -> bool:
    """Whether the huge read need not equal the equivalent one: taps spread along the footprint's axis (anisotropic,
    auto), whose offsets (a tenth of the texture here) are far below the ulp of a huge coordinate, so they all
    land on the point itself, while at the equivalent small uv they spread. (clamp / border: every tap is past
    the edge either way.) The rounding of the input, as for any float (docs/stability.md, "Large uv")."""
    return filter in ("anisotropic", "auto") and wrap in ("repeat", "mirror") and footprint != "point"


def _child(path: str) -> int:
    """Runs the grid of one path, printing ``BEGIN``/``OK``/``FAIL`` lines as it goes (flushed: a parent that
    kills this process on its deadline still reads which case was running)."""
    import difftex
    if path == "native":
        difftex.backend("native")  # RuntimeError (not a silent fallback) where the kernel is not there
    else:
        assert os.environ.get("DIFFTEX_NATIVE") == "0"
        difftex.backend("grid_sample")
    torch.manual_seed(0)
    failures = 0
    t0 = time.perf_counter()
    for filter in _filters():
        for wrap in WRAPS:
            for dname, mag in MAGNITUDES:
                dtype = getattr(torch, dname)
                for fname, dx, dy, deriv_grad in FOOTPRINTS:
                    if fname != "point" and filter in ("nearest", "bilinear", "bicubic"):
                        continue  # the single-level filters ignore the footprint
                    case = f"{filter} {wrap} {dname} {mag:g} {fname}"
                    print("BEGIN", case, flush=True)
                    pts = _points(mag)
                    # The references first, then the huge read (whose hang is what the deadline catches).
                    refs = {}
                    if not _spread(filter, wrap, fname):
                        eq = [(_equivalent(u, wrap, 8), _equivalent(v, wrap, 8)) for u, v in pts]
                        refs["the equivalent uv's"] = _run_case(filter, wrap, dtype, eq, dx, dy, deriv_grad)
                    if path == "native":  # the kernel against the torch path at the same uv (as test_backend)
                        with difftex.backend("grid_sample"):
                            refs["the torch path's"] = _run_case(filter, wrap, dtype, pts, dx, dy, deriv_grad)
                    got = _run_case(filter, wrap, dtype, pts, dx, dy, deriv_grad)
                    problems = []
                    tol = dict(rtol=1e-4, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-11)
                    names = ("value", "texture grad", "uv grad", "uv_dx grad", "uv_dy grad")
                    for i, (name, a) in enumerate(zip(names, got)):
                        if not bool(torch.isfinite(a).all()):
                            problems.append(f"{name} not finite: {a.flatten()[:6].tolist()}")
                            continue
                        for what, ref in refs.items():
                            if not torch.allclose(a, ref[i], **tol):
                                problems.append(f"{name} differs from {what} by {(a - ref[i]).abs().max().item():.3g}")
                    # Every filter but bicubic averages texels (and the border constant) with positive weights.
                    lo, hi = min(0.0, BORDER), 1.0
                    if filter != "bicubic" and not bool(((got[0] >= lo - 1e-6) & (got[0] <= hi + 1e-6)).all()):
                        problems.append(f"value outside [{lo}, {hi}]: {got[0].flatten()[:6].tolist()}")
                    if problems:
                        failures += 1
                        print("FAIL", case, "; ".join(problems), flush=True)
                    else:
                        print("OK", case, flush=True)
    print(f"DONE {failures} failures in {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


def _run_child(path: str) -> tuple[str, float]:
    """This file as a script for ``path`` ("native" / "torch"): (its output, seconds); fails at the deadline."""
    import difftex
    root = str(Path(difftex.__file__).resolve().parents[1])  # the difftex this test imported, not another copy
    env = dict(os.environ)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if path == "torch":
        env["DIFFTEX_NATIVE"] = "0"
    t0 = time.perf_counter()
    try:
        res = subprocess.run([sys.executable, str(Path(__file__).resolve()), path], env=env, cwd=root,
                             capture_output=True, text=True, timeout=DEADLINE_S)
    except subprocess.TimeoutExpired as e:  # the child is killed by now
        out = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        begun = [line for line in out.splitlines() if line.startswith("BEGIN")]
        pytest.fail(f"{path} path: the grid did not finish within {DEADLINE_S:.0f} s (a hang); last case "
                    f"started: {begun[-1][6:] if begun else 'none (stuck before the grid)'}")
    elapsed = time.perf_counter() - t0
    assert res.returncode == 0, f"{path} path: the child failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    return res.stdout, elapsed


def _check(path: str) -> None:
    out, elapsed = _run_child(path)
    lines = out.splitlines()
    fails = [line for line in lines if line.startswith("FAIL")]
    done = [line for line in lines if line.startswith("DONE")]
    assert done, f"{path} path: the grid did not report its end:\n{out[-3000:]}"
    ok = [line for line in lines if line.startswith("OK")]
    # Every case ran: 10 filters x 4 wraps x 4 magnitudes x (1 footprint for the 3 single-level filters, 3 else).
    n_filters = len(_filters())
    assert len(ok) + len(fails) == len(WRAPS) * len(MAGNITUDES) * (3 + 3 * (n_filters - 3))
    assert not fails, f"{path} path: {len(fails)} cases failed:\n" + "\n".join(fails[:40])


def test_huge_uv_native_kernel_finishes_finite():
    """The kernel's forward and backward at |uv| up to 3e38 / 1e300: done within the deadline, finite, and equal
    to the equivalent small uv (issue 42: the repeat backward of the tap filters hung)."""
    from tests.conftest import use_backend
    with use_backend("native"):  # builds the kernel here, outside the child's deadline; skips where none
        pass
    _check("native")


def test_huge_uv_torch_path_finishes_finite():
    """The same grid on the torch path (DIFFTEX_NATIVE=0: grid_sample and the torch mip filters)."""
    _check("torch")


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1]))

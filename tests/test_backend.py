"""``difftex.backend``: the switch itself, and the fast backends against the gather reference.

Both fast backends, the native CPU kernel (``difftex.texture.native``)
and the torch one (``texture/filters/grid.py``: grid_sample with padding / folding,
the unpadded read with edge points handed to the reference, the hand-written
backward, the sparse scatter into a coarser level's spread, and the one-node
pyramid read of ``texture/filters/trilinear.py``), must give the values and the
gradients of ``difftex.backend("reference")`` for texture, uv, both derivatives
and a per-pixel lod_bias. Textures up to 33 x 64 against up to 2 x 7 x 9
points, so that both the padded and the unpadded-plus-edge reads and both
the dense and the sparse level gradients occur. Seeded: CI sees the same
cases every run.
"""
from __future__ import annotations

import importlib
import random
import threading

import pytest
import torch

import difftex
from difftex import WRAP_MODES
from difftex.texture.options import FILTERS, MIP_FILTERS
from tests.conftest import use_backend

MIP = MIP_FILTERS

pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py: many small ops


def _config(i: int) -> dict:
    """Case ``i``: uniform choices from a generator seeded by ``i`` (hypothesis would favour the first,
    smallest choices, and rarely reach the large-texture, few-point cases that take the sparse scatter)."""
    r = random.Random(i)
    B = r.randint(1, 2)
    return dict(
        filter=FILTERS[i % len(FILTERS)],
        wrap=(r.choice(WRAP_MODES), r.choice(WRAP_MODES)),
        dtype=r.choice([torch.float32, torch.float64]),
        B=B, Bt=r.choice([1, B]), C=r.choice([1, 3]),
        H=r.choice([1, 2, 5, 8, 13, 16, 33]), W=r.choice([1, 3, 8, 12, 31, 64]),
        Ho=r.choice([1, 3, 7]), Wo=r.choice([1, 4, 9]),
        scale=r.choice([1e-3, 0.05, 0.3, 2.0]),  # derivatives, uv per pixel
        degenerate=r.random() < 0.3,  # one zero and one infinite footprint
        transposed=r.random() < 0.3,  # non-contiguous texture and uv
        bias_map=r.random() < 0.5, mipmap=r.random() < 0.3,
        max_aniso=r.choice([1, 2, 4.5, 16]), seed=i)


def _run(cfg: dict, impl: str, frozen: bool = False, with_grads: bool = True):
    """Values and gradients of one case under backend ``impl``; ``frozen``: derivatives and bias without
    gradients; ``with_grads=False``: the values only, nothing requiring a gradient."""
    with use_backend(impl):
        return _run_case(cfg, frozen, with_grads)


def _run_case(cfg: dict, frozen: bool, with_grads: bool):
    g = torch.Generator().manual_seed(cfg["seed"])
    dt = cfg["dtype"]
    B, Bt, C, H, W, Ho, Wo = (cfg[k] for k in ("B", "Bt", "C", "H", "W", "Ho", "Wo"))
    tex = torch.rand(Bt, C, H, W, generator=g, dtype=dt)
    uv = torch.rand(B, Ho, Wo, 2, generator=g, dtype=dt) * 3 - 1
    dx, dy = (torch.randn(B, Ho, Wo, 2, generator=g, dtype=dt) * cfg["scale"] for _ in range(2))
    bias = torch.randn(B, Ho, Wo, generator=g, dtype=dt)
    if cfg["degenerate"]:
        dx[0, 0, 0] = dy[0, 0, 0] = 0.0
        dx[-1, -1, -1, 0] = float("inf")
    if cfg["transposed"]:
        tex = tex.transpose(2, 3).contiguous().transpose(2, 3)
        uv = uv.transpose(1, 2).contiguous().transpose(1, 2)
    leaves = [t.requires_grad_(with_grads) for t in ((tex, uv) if frozen else (tex, uv, dx, dy, bias))]
    kw = {}
    if cfg["filter"] in MIP:
        kw = dict(uv_dx=dx, uv_dy=dy, lod_bias=bias if cfg["bias_map"] else 0.3, max_aniso=cfg["max_aniso"])
    texture = difftex.mipmap(tex) if cfg["mipmap"] else tex
    out = difftex.sample(texture, uv, filter=cfg["filter"], wrap=cfg["wrap"], border_value=0.25, **kw)
    if not with_grads:
        return out
    w = torch.randn(out.shape, generator=g, dtype=dt)
    grads = torch.autograd.grad((out * w).sum(), leaves, allow_unused=True)
    return out.detach(), [torch.zeros_like(x) if gr is None else gr for x, gr in zip(leaves, grads)]


def _compare(cfg: dict, impl: str, frozen: bool = False) -> None:
    fast, fast_grads = _run(cfg, impl, frozen)
    ref, ref_grads = _run(cfg, "reference", frozen)
    tol = 1e-4 if cfg["dtype"] == torch.float32 else 1e-9
    torch.testing.assert_close(fast, ref, atol=tol, rtol=tol, equal_nan=True)
    assert len(fast_grads) == (2 if frozen else 5)
    for name, a, b in zip(("texture", "uv", "uv_dx", "uv_dy", "lod_bias"), fast_grads, ref_grads):
        assert torch.isfinite(a).all(), name
        # Gradients sum many terms (a texel read by every point): relative to their largest entry.
        s = max(1.0, b.abs().max().item())
        torch.testing.assert_close(a, b, atol=10 * tol * s, rtol=10 * tol, msg=lambda m: f"{name}: {m}")


@pytest.mark.parametrize("impl", ["native", "grid_sample"])
@pytest.mark.parametrize("case", range(96))
def test_fast_path_matches_the_reference(case, impl):
    _compare(_config(case), impl)


@pytest.mark.parametrize("case", [i for i in range(96) if FILTERS[i % len(FILTERS)] in MIP and
                                  FILTERS[i % len(FILTERS)] != "ewa"])
def test_kernel_front_end_matches_the_reference(case):
    # Derivatives and bias without gradients: the bilinear-tap mip filters take
    # the native kernel's footprint front end (tests/texture/native checks that they do).
    _compare(_config(case), "native", frozen=True)


@pytest.mark.parametrize("case", [i for i in range(96) if FILTERS[i % len(FILTERS)] in MIP])
def test_kernel_forward_without_gradients_matches_the_reference(case):
    # No gradient at all (rendering): the values alone, through the kernels' no-gradient paths.
    cfg = _config(case)
    fast = _run(cfg, "native", frozen=True, with_grads=False)
    ref = _run(cfg, "reference", frozen=True, with_grads=False)
    tol = 1e-4 if cfg["dtype"] == torch.float32 else 1e-9
    torch.testing.assert_close(fast, ref, atol=tol, rtol=tol, equal_nan=True)


def test_the_switch_restores_the_previous_choice_and_names_bad_ones():
    backend_mod = importlib.import_module("difftex.backend")
    assert backend_mod.current() == "auto"
    with difftex.backend("reference"):
        assert backend_mod.current() == "reference" and backend_mod.single_level() == "gather"
        with difftex.backend("grid_sample"):
            assert backend_mod.current() == "grid_sample" and backend_mod.single_level() == "grid_sample"
        assert backend_mod.current() == "reference"
    assert backend_mod.current() == "auto"
    difftex.backend("grid_sample")  # a plain call: stays until changed
    try:
        assert backend_mod.current() == "grid_sample"
    finally:
        difftex.backend("auto")
    with pytest.raises(ValueError, match=r"backend: unknown choice 'torch'; expected one of \('auto', 'native'"):
        difftex.backend("torch")
    with pytest.raises(ValueError, match=r"backend: unknown choice None"):
        difftex.backend(None)


def test_the_choice_is_per_thread():
    seen = []
    with difftex.backend("reference"):
        worker = threading.Thread(target=lambda: seen.append(importlib.import_module("difftex.backend").current()))
        worker.start()
        worker.join()
    assert seen == ["auto"]


def test_the_rule_sends_only_cpu_float32_and_float64_to_the_kernel():
    backend_mod = importlib.import_module("difftex.backend")
    x = torch.zeros(2)
    assert backend_mod.wants_native(x) and backend_mod.wants_native(x.double())
    assert not backend_mod.wants_native(x.half()) and not backend_mod.wants_native(x.to("meta"))
    for choice in ("grid_sample", "reference"):
        with difftex.backend(choice):
            assert not backend_mod.wants_native(x)


def test_native_raises_where_the_kernel_is_off(monkeypatch):
    from difftex import _native as native
    monkeypatch.setenv("DIFFTEX_NATIVE", "0")
    tex, uv = torch.rand(1, 1, 8, 8), torch.rand(1, 2, 2, 2)
    d = torch.full((1, 2, 2, 2), 0.3)
    assert native.kernel(uv) is None  # auto: falls back
    out = difftex.sample(tex, uv, filter="trilinear", uv_dx=d, uv_dy=d)
    with difftex.backend("grid_sample"):
        torch.testing.assert_close(out, difftex.sample(tex, uv, filter="trilinear", uv_dx=d, uv_dy=d))
    with difftex.backend("native"), pytest.raises(RuntimeError, match=r"difftex.backend\('native'\): the native "
                                                                    r"CPU kernels are not available"):
        difftex.sample(tex, uv, filter="trilinear", uv_dx=d, uv_dy=d)

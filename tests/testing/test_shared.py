"""difftex.testing: the icosphere, the supersampled reference, the grid_sample peers and the timing harness."""
from __future__ import annotations

import time

import pytest
import torch

import difftex
from difftex.testing import (Timing, checker_noise_texture, grazing_plane, grid_sample_lookup, icosphere,
                             kornia_lookup, supersampled, time_blocks, time_interleaved)


@pytest.mark.parametrize("n", [0, 2])
def test_icosphere_counts_radius_and_orientation(n):
    V, F_ = icosphere(n, radius=2.0, dtype=torch.float64)
    assert F_.shape == (20 * 4 ** n, 3) and V.shape == (10 * 4 ** n + 2, 3)  # Euler: V = F / 2 + 2
    assert V.dtype == torch.float64 and F_.dtype == torch.int64
    torch.testing.assert_close(V.norm(dim=-1), torch.full((V.shape[0],), 2.0, dtype=torch.float64))
    a, b, c = V[F_].unbind(1)
    outward = (torch.linalg.cross(b - a, c - a) * (a + b + c)).sum(-1)
    assert (outward > 0).all()  # counter-clockwise seen from outside
    with pytest.raises(ValueError, match="subdivisions=-1"):
        icosphere(-1)


def test_supersampled_is_the_box_mean_of_the_sub_samples_in_any_chunking():
    tex = checker_noise_texture(64)
    uv4 = grazing_plane(8, 20.0, ss=4)[0]
    want = difftex.sample(tex, uv4, filter="bilinear", wrap="repeat").view(1, 3, 8, 4, 8, 4).mean((3, 5))
    for rows in (1, 3, 16):
        torch.testing.assert_close(supersampled(tex, uv4, 4, "repeat", chunk_rows=rows), want, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match=r"uv_ss of shape \(1, 32, 32, 2\)"):
        supersampled(tex, uv4, 3)


@pytest.mark.parametrize("wrap", ["repeat", "clamp", ("repeat", "clamp")])
def test_grid_sample_peer_reads_like_difftex_bilinear(wrap):
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(1, 3, 5, 7, generator=g, dtype=torch.float64)
    uv = torch.rand(2, 6, 4, 2, generator=g, dtype=torch.float64) * 3 - 1  # outside [0, 1] too
    want = difftex.sample(tex, uv, filter="bilinear", wrap=wrap)
    torch.testing.assert_close(grid_sample_lookup(tex, uv, wrap), want, atol=1e-12, rtol=0)
    torch.testing.assert_close(kornia_lookup(tex.expand(2, -1, -1, -1), uv, wrap), want, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="wrap must be one of"):
        grid_sample_lookup(tex, uv, "mirror")


def test_timing_harness_interleaves_and_pauses():
    calls = []
    fns = [lambda: calls.append("a"), lambda: (calls.append("b"), time.sleep(0.005))]
    t0 = time.perf_counter()
    ta, tb = time_interleaved(fns, repeats=4, warmup=1, pause=0.01)
    elapsed = time.perf_counter() - t0
    assert calls == ["a", "b"] * 5  # one warm-up round, then four, each calling both in turn
    assert len(ta.times_ms) == len(tb.times_ms) == 4
    assert tb.median >= 5.0 and ta.median < tb.median
    assert elapsed >= 8 * 0.01  # the pause before each of the 8 timed calls
    assert tb.ratio_to(ta) > 1.0
    t = Timing((1.0, 2.0, 3.0, 4.0, 10.0))
    assert (t.median, t.min, t.spread) == (3.0, 1.0, 2.0)
    assert Timing((2.0, 4.0)).ratio_to(Timing((1.0, 1.0))) == 3.0
    with pytest.raises(ValueError, match="repeats >= 1"):
        time_interleaved(fns, repeats=0)
    with pytest.raises(ValueError, match="settle=-1"):
        time_interleaved(fns, settle=-1)


def test_settle_calls_each_function_untimed_right_before_its_timed_call():
    calls = []

    def a():  # calls 4 and 7 of a (warm-up, then two settling calls before each timed one) are the slow ones
        calls.append("a")
        n = calls.count("a")
        time.sleep(0.004 if n > 1 and n % 3 == 1 else 0)
    fns = [a, lambda: calls.append("b")]
    ta, tb = time_interleaved(fns, repeats=2, warmup=1, pause=0.0, settle=2)
    assert calls == ["a", "b"] + ["a"] * 3 + ["b"] * 3 + ["a"] * 3 + ["b"] * 3  # warm-up round without settling
    assert min(ta.times_ms) >= 4.0 and max(ta.times_ms) < 4.0 + 3.0  # only the third call of each run is timed


def test_shuffled_rounds_call_every_function_once_a_round():
    calls = []
    fns = [lambda i=i: calls.append(i) for i in range(4)]
    time_interleaved(fns, repeats=3, warmup=0, pause=0.0, shuffle=True)
    rounds = [sorted(calls[i:i + 4]) for i in range(0, 12, 4)]
    assert rounds == [[0, 1, 2, 3]] * 3
    assert len({tuple(calls[i:i + 4]) for i in range(0, 12, 4)}) > 1  # seed 0 gives different orders


def test_time_blocks_times_all_but_the_first_calls_of_each_block_of_back_to_back_calls():
    calls = []

    def a():  # the first two calls of every block (after the warm-up call) are the slow ones
        calls.append("a")
        n = calls.count("a") - 1
        time.sleep(0.004 if n >= 1 and (n - 1) % 4 < 2 else 0)
    fns = [a, lambda: calls.append("b")]
    ta, tb = time_blocks(fns, blocks=3, calls=4, skip=2, pause=0.0, shuffle=False)
    assert calls == ["a", "b"] + (["a"] * 4 + ["b"] * 4) * 3  # warm-up, then a block of each per round
    assert len(ta.times_ms) == len(tb.times_ms) == 6
    assert max(ta.times_ms) < 4.0  # the slow (skipped) calls are not timed
    for bad in (dict(blocks=0), dict(skip=-1), dict(calls=2, skip=2), dict(pause=-1.0)):
        with pytest.raises(ValueError, match="time_blocks: expected functions, blocks >= 1"):
            time_blocks(fns, **bad)

"""The timing harness of the benchmarks: functions timed interleaved, medians and spread.

On a shared machine the load drifts by 2-3x within a minute, so functions
that are compared are timed in rounds, each round calling every function
once (in a new random order when ``shuffle``, so that none always runs
after one that evicts the caches): a load spike hits them alike, and the
per-round ratio of two functions is steadier than the ratio of their
medians. Between timed calls the harness sleeps ``pause`` seconds: after a
call torch's intra-op worker threads spin for 10-20 ms on a 2-core machine,
which would otherwise be charged to the next function.

The pause has a cost of its own on some virtual machines: on the 2-core VM
of 2026-12-03, a torch.add of 4M floats on 2 threads took 0.58 ms back to
back but 5.9-7.9 ms after a 10-50 ms sleep (1.1-2.1 ms with
``OMP_WAIT_POLICY=passive``; a plain pthread condition-variable wake took
0.06 ms), in periods of minutes to hours. An OpenMP worker that went to
sleep after its spin then seems to wait several ms to be scheduled, and
torch's parallel regions wait for it at their barrier. A call of a few ms on
two threads then carries several ms that a loop of calls never sees. Part of
it is the caches: on one thread the same add took 1.2 ms back to back and
3.3-3.7 ms after 20 ms of sleep or of busy-waiting alike (other tenants
evict the shared L3 within milliseconds).

Dr.Jit pays a cost after a pause too: its 1024^2 bilinear clamp forward of
512^2 points took 2.5-3.9 ms after a pause in the runs of one day and
3.8-8.0 ms in those of the next, but 0.89-0.97 ms as the ninth call of a
loop; ours (channels_last) 3.6-7.7 ms after the pause, 0.85-1.07 ms in the
loop. Calls of a few ms are therefore timed both ways:
after the pause alone, and with ``settle`` untimed calls of the same
function between the pause and the timed one (its own threads awake, as in
a render or training loop; 5-8 calls reached the loop's time there, 2-3 did
not). The pause still keeps one library's spinning threads off the next.
To see whether the penalty is present: time a 2-thread torch.add of a few
million floats back to back and after a 20 ms sleep.
"""
from __future__ import annotations

import random
import statistics
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch


@dataclass(frozen=True)
class Timing:
    """Wall-clock times of one function over the timed rounds, in ms (round order)."""

    times_ms: tuple[float, ...]

    @property
    def median(self) -> float:
        return statistics.median(self.times_ms)

    @property
    def min(self) -> float:
        return min(self.times_ms)

    @property
    def spread(self) -> float:
        """Interquartile range in ms (0 for fewer than two rounds)."""
        if len(self.times_ms) < 2:
            return 0.0
        q = statistics.quantiles(self.times_ms, n=4, method="inclusive")
        return q[2] - q[0]

    def ratio_to(self, other: "Timing") -> float:
        """Median over the rounds of this time / ``other``'s in the same round (both from one harness call)."""
        if len(other.times_ms) != len(self.times_ms):
            raise ValueError(f"Timing.ratio_to: other has {len(other.times_ms)} rounds, expected "
                             f"{len(self.times_ms)} (time both in one time_interleaved call)")
        return statistics.median(a / b for a, b in zip(self.times_ms, other.times_ms))


def _synchronize(device: Optional[torch.device | str]) -> None:
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def time_interleaved(fns: Sequence[Callable[[], object]], repeats: int = 9, *, warmup: int = 1,
                     pause: float = 0.02, settle: int = 0, shuffle: bool = False, seed: int = 0,
                     device: Optional[torch.device | str] = None) -> list[Timing]:
    """Time each of ``fns`` ``repeats`` times, interleaved in rounds; one :class:`Timing` per function.

    Args:
        fns: callables without arguments (what they return is dropped).
        repeats: timed rounds (>= 1).
        warmup: untimed rounds first (allocator, lazy imports, kernel builds).
        pause: seconds slept before every timed call (see the module doc).
        settle: untimed calls of the same function between the pause and its
            timed call: the time of a call in a loop of calls, its own
            worker threads awake (see the module doc).
        shuffle: a new order of ``fns`` every round (seeded by ``seed``).
        device: a CUDA device is synchronized around every timed call, so
            that the time is the kernels' and not their launch's.

    Raises:
        ValueError: ``repeats`` < 1, ``warmup``, ``pause`` or ``settle`` < 0, or no functions.
    """
    if not fns or repeats < 1 or warmup < 0 or pause < 0 or settle < 0:
        raise ValueError(f"time_interleaved: expected functions, repeats >= 1, warmup >= 0, pause >= 0 and "
                         f"settle >= 0, got {len(fns)} functions, repeats={repeats}, warmup={warmup}, "
                         f"pause={pause}, settle={settle}")
    rng = random.Random(seed)
    order = list(range(len(fns)))
    times: list[list[float]] = [[] for _ in fns]
    for r in range(warmup + repeats):
        if shuffle:
            rng.shuffle(order)
        for i in order:
            if pause and r >= warmup:
                time.sleep(pause)
            for _ in range(settle if r >= warmup else 0):
                fns[i]()
            _synchronize(device)
            t = time.perf_counter()
            fns[i]()
            _synchronize(device)
            if r >= warmup:
                times[i].append((time.perf_counter() - t) * 1e3)
    return [Timing(tuple(ts)) for ts in times]


def time_blocks(fns: Sequence[Callable[[], object]], blocks: int = 8, *, calls: int = 8, skip: int = 2,
                pause: float = 0.03, shuffle: bool = True, seed: int = 0,
                device: Optional[torch.device | str] = None) -> list[Timing]:
    """Steady-state times: blocks of ``calls`` back-to-back calls of one function, interleaved block by block.

    The protocol of the speed issues for calls of a few ms on a 2-core
    machine: each block sleeps ``pause`` (the previous library's spinning
    worker threads settle), calls one function ``calls`` times in a row and
    keeps the times of all but the first ``skip`` (its own threads awake,
    its caches warm: a render or training loop's time). Every round runs
    one block of every function, in a new order when ``shuffle``. The first
    call after the pause is what :func:`time_interleaved` times; report it
    apart.

    Args:
        fns: callables without arguments (what they return is dropped).
        blocks: rounds (>= 1); each function gets ``blocks * (calls - skip)`` times.
        calls: calls per block (> ``skip``).
        skip: untimed leading calls of every block (>= 0).
        pause, shuffle, seed, device: as for :func:`time_interleaved`; one
            untimed warm-up round of single calls comes first.

    Returns:
        One :class:`Timing` per function, its times in call order; ``ratio_to``
        pairs the k-th timed call of one function with the k-th of another.

    Raises:
        ValueError: no functions, ``blocks`` < 1, ``skip`` < 0, ``calls`` <= ``skip`` or ``pause`` < 0.
    """
    if not fns or blocks < 1 or skip < 0 or calls <= skip or pause < 0:
        raise ValueError(f"time_blocks: expected functions, blocks >= 1, skip >= 0, calls > skip and pause >= 0, "
                         f"got {len(fns)} functions, blocks={blocks}, calls={calls}, skip={skip}, pause={pause}")
    rng = random.Random(seed)
    order = list(range(len(fns)))
    for fn in fns:
        fn()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(blocks):
        if shuffle:
            rng.shuffle(order)
        for i in order:
            if pause:
                time.sleep(pause)
            for c in range(calls):
                _synchronize(device)
                t = time.perf_counter()
                fns[i]()
                _synchronize(device)
                if c >= skip:
                    times[i].append((time.perf_counter() - t) * 1e3)
    return [Timing(tuple(ts)) for ts in times]

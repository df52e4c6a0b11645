"""What a long fit needs around its loop: torch.distributed setup, gradient averaging, the step sampler,
atomic checkpoints.

Data parallelism (``torchrun --nproc-per-node N -m experiments.fit.fit_texture ...``): every process holds the
whole texture, draws the same global batch of views per step (one seeded sampler), renders its contiguous share
of it and scales its loss by ``1 / world`` so that the all-reduced (summed) gradient is the one-process mean;
the identical Adam step then keeps every copy equal. An explicit all-reduce rather than DDP: the parameters are
one or two big tensors, so DDP's bucketing buys nothing, and the loop stays one code path for 1 and N processes.
Several machines: ``torchrun --nnodes M --nproc-per-node N --rdzv-backend c10d --rdzv-endpoint HOST:PORT ...``
on each; a CUDA process uses ``cuda:LOCAL_RANK``. Only rank 0 writes, so ``--out`` must be on its machine (and
``--resume`` needs the checkpoint where every process can read it, e.g. a shared folder).

Checkpoints (:func:`save_checkpoint`) go to a temporary file in the same folder, are fsynced and renamed over
the previous one (``os.replace`` is atomic on POSIX and Windows), then the folder is fsynced so that the rename
itself survives a power cut. A kill at any moment leaves either the old or the new checkpoint, never a partial
one; stale temporary files are removed by the next save or load.
"""
from __future__ import annotations

import os
import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import torch
import torch.distributed as dist

CHECKPOINT = "checkpoint.pt"
# Test hook: SIGKILL this process inside the n-th checkpoint write, after half of its bytes (1-based count).
KILL_IN_WRITE_ENV = "DIFFTEX_FIT_KILL_IN_CHECKPOINT_WRITE"
# Test hook: SIGKILL this process right after step n's optimiser update (0-based step).
KILL_AT_STEP_ENV = "DIFFTEX_FIT_KILL_AT_STEP"


@dataclass(frozen=True)
class Dist:
    """This process's place in the run: rank, world size, device."""

    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0


def setup(device: str = "cpu") -> Dist:
    """Join the process group when started by torchrun (WORLD_SIZE > 1), else a single process.

    gloo on the CPU, nccl on CUDA (one GPU per process, ``cuda:LOCAL_RANK``).
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    dev = torch.device(device)
    if world == 1:
        return Dist(0, 1, dev)
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if dev.type == "cuda":
        dev = torch.device("cuda", local)
        torch.cuda.set_device(dev)
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if dev.type == "cuda" else "gloo")
    return Dist(dist.get_rank(), dist.get_world_size(), dev)



def all_reduce_grads(params, d: Dist) -> int:
    """Sum every gradient over the processes (each already scaled by 1 / world); returns the bytes reduced."""
    n = 0
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        if d.world > 1:
            dist.all_reduce(p.grad, op=dist.ReduceOp.SUM)
        n += p.grad.numel() * p.grad.element_size()
    return n


def reduce_sum(x: float, d: Dist) -> float:
    if d.world == 1:
        return x
    t = torch.tensor([x], dtype=torch.float64, device=d.device if d.device.type == "cuda" else "cpu")
    dist.all_reduce(t)
    return float(t)


def barrier(d: Dist) -> None:
    if d.world > 1:
        dist.barrier()


def teardown(ok: bool) -> None:
    """Leave the process group, if one was joined. After a run that finished (``ok``), every rank waits
    for the others first: a rank that tore gloo down while rank 0 was still evaluating and saving aborted
    once in the tests ("terminate called without an active exception"). After an error no rank waits,
    since the others may never arrive."""
    if not dist.is_initialized():
        return
    if ok:
        dist.barrier()
    dist.destroy_process_group()


class StepSampler:
    """The views of each step: ``randperm(n)[:batch]`` from one seeded generator, this rank's contiguous share.

    Iterating yields lists of indices for steps ``start .. steps - 1``; the draws of the earlier steps are
    replayed (cheap) so that a resumed run, or a DataLoader that prefetches ahead of the loop, sees the same
    views as an uninterrupted one. ``state_at(step)`` is the generator's state before that step's draw.
    """

    def __init__(self, n: int, batch: int, seed: int, steps: int, d: Dist = Dist(), start: int = 0) -> None:
        if batch % d.world:
            raise ValueError(f"batch: the global batch {batch} must be a multiple of the number of processes "
                             f"{d.world} (every process renders an equal share)")
        if batch > n:
            raise ValueError(f"batch: {batch} views per step, but the capture has only {n}")
        self.n, self.batch, self.seed, self.steps, self.d, self.start = n, batch, seed, steps, d, start

    def __len__(self) -> int:
        return self.steps - self.start

    def __iter__(self) -> Iterator[list[int]]:
        gen = torch.Generator().manual_seed(self.seed)
        share = self.batch // self.d.world
        lo = self.d.rank * share
        for step in range(self.steps):
            idx = torch.randperm(self.n, generator=gen)[:self.batch]
            if step >= self.start:
                yield idx[lo:lo + share].tolist()

    def state_at(self, step: int) -> torch.Tensor:
        gen = torch.Generator().manual_seed(self.seed)
        for _ in range(step):
            torch.randperm(self.n, generator=gen)
        return gen.get_state()


class _KillingWriter:
    """File wrapper for the kill-in-write test hook: SIGKILLs the process once ``limit`` bytes are written."""

    def __init__(self, fh, limit: int) -> None:
        self.fh, self.limit, self.written = fh, limit, 0

    def write(self, b) -> int:
        n = self.fh.write(b)
        self.written += n
        if self.written >= self.limit:
            self.fh.flush()
            os.fsync(self.fh.fileno())
            os.kill(os.getpid(), signal.SIGKILL)
        return n

    def __getattr__(self, name):
        return getattr(self.fh, name)


_writes = 0


def _remove_stale(folder: Path) -> None:
    for p in folder.glob(f".{CHECKPOINT}.tmp-*"):
        try:
            p.unlink()
        except OSError:
            pass


def save_checkpoint(folder: Path, state: dict) -> Path:
    """Write ``state`` to ``folder/checkpoint.pt`` atomically (module docstring); returns the path."""
    global _writes
    folder.mkdir(parents=True, exist_ok=True)
    _remove_stale(folder)
    path = folder / CHECKPOINT
    tmp = folder / f".{CHECKPOINT}.tmp-{os.getpid()}"
    _writes += 1
    kill_n = int(os.environ.get(KILL_IN_WRITE_ENV, "0"))
    with open(tmp, "wb") as fh:
        if kill_n == _writes:
            # Half the size of the previous checkpoint (the same size, near enough): a truly partial file.
            size = path.stat().st_size if path.exists() else 1 << 16
            torch.save(state, _KillingWriter(fh, max(1, size // 2)))
        else:
            torch.save(state, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    if hasattr(os, "O_DIRECTORY"):  # POSIX: make the rename durable; Windows cannot open a folder
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    return path


def load_checkpoint(folder: Path, map_location="cpu") -> Optional[dict]:
    """The last complete checkpoint in ``folder`` (None if there is none); stale temporary files are removed."""
    if not folder.is_dir():
        return None
    _remove_stale(folder)
    path = folder / CHECKPOINT
    if not path.exists():
        return None
    return torch.load(path, map_location=map_location, weights_only=False)


def maybe_kill_at(step: int) -> None:
    """The kill-mid-run test hook."""
    if int(os.environ.get(KILL_AT_STEP_ENV, "-1")) == step:
        os.kill(os.getpid(), signal.SIGKILL)

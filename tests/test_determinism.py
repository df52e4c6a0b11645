"""A CPU run repeats bit for bit (DESIGN.md, "determinism"): the same read, many times, with other threads
competing for the cores, gives the same bits in every value and gradient.

Issue 42: two identical EWA reads on the torch path differed by up to 2.4e-7. The EWA pairs gathered their
point's ellipse with advanced indexing (``sx[point]``), whose CPU backward (index_put with accumulate) adds
the many pairs of a point into its entry with atomics from several threads: an order that changes from run
to run (measured: about 1 run in 16 differed from the first at the sizes below, loaded or not).
``vertex_normals`` and ``tangent_frames`` gathered shared vertices the same way.
"""
from __future__ import annotations

import threading

import pytest
import torch

import difftex
from difftex.geometry.mesh import vertex_normals
from difftex.shading.frames import tangent_frames
from tests.conftest import use_backend


@pytest.fixture
def loaded_two_threads():
    """Two intra-op threads, and two Python threads running matmuls meanwhile (they release the GIL), so that
    the reads share the two cores with other work, as on a loaded CI machine; restored afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(2)
    stop = threading.Event()

    def spin(seed: int) -> None:
        a = torch.rand(160, 160, generator=torch.Generator().manual_seed(seed))
        while not stop.is_set():
            a = torch.tanh(a @ a)

    workers = [threading.Thread(target=spin, args=(i,), daemon=True) for i in range(2)]
    for w in workers:
        w.start()
    try:
        yield
    finally:
        stop.set()
        for w in workers:
            w.join()
        torch.set_num_threads(n)


def _assert_repeats(run, times: int) -> None:
    """run() -> list of tensors; every one of ``times`` further runs gives the first run's bits."""
    first = run()
    for i in range(times):
        again = run()
        for k, (a, b) in enumerate(zip(first, again)):
            if not torch.equal(a, b):
                diff = (a - b).abs().max().item() if a.shape == b.shape else "shape"
                pytest.fail(f"run {i + 1}: output {k} differs from the first run's by {diff}")


def _scene(seed: int = 0, H: int = 64, W: int = 64, B: int = 2, Ho: int = 32, Wo: int = 32):
    """texture [1, 3, H, W], uv [B, Ho, Wo, 2] over three repeats, uv_dx / uv_dy of up to 6 x 1.6 texels."""
    g = torch.Generator().manual_seed(seed)
    tex = torch.rand(1, 3, H, W, generator=g)
    uv = torch.rand(B, Ho, Wo, 2, generator=g) * 3 - 1
    dx = (torch.rand(B, Ho, Wo, 2, generator=g) - 0.5) * 0.2
    dy = (torch.rand(B, Ho, Wo, 2, generator=g) - 0.5) * 0.05
    return tex, uv, dx, dy


def _read(filter: str, backend: str, **kw):
    """A run: sample forward + backward; (value, d/dtexture, d/duv, d/duv_dx, d/duv_dy)."""
    tex0, uv0, dx0, dy0 = _scene()

    def run():
        tex, uv, dx, dy = (t.clone().requires_grad_() for t in (tex0, uv0, dx0, dy0))
        with difftex.backend(backend):
            out = difftex.sample(tex, uv, filter=filter, wrap="repeat", uv_dx=dx, uv_dy=dy, **kw)
            w = torch.linspace(0.5, 1.5, out.numel()).view_as(out)  # an uneven output gradient
            grads = torch.autograd.grad(out, (tex, uv, dx, dy), w, allow_unused=True)
        return [out.detach()] + [torch.zeros(0) if g is None else g for g in grads]

    return run


@pytest.mark.parametrize("backend", ["grid_sample", "native"])
def test_ewa_read_is_bit_identical_under_load(backend, loaded_two_threads):
    # 150 repeats: at the old rate of 1 in 16 a run-order-dependent sum shows with probability 1 - 1e-4.
    with use_backend(backend):  # skips "native" where the kernel is not built
        pass
    _assert_repeats(_read("ewa", backend, max_aniso=8), 150)


@pytest.mark.parametrize("filter", ["bilinear", "trilinear", "anisotropic", "ripmap", "sat"])
def test_other_filters_are_bit_identical_under_load(filter, loaded_two_threads):
    _assert_repeats(_read(filter, "grid_sample"), 20)


def _grid_mesh(n: int = 80):
    """An n x n vertex grid of 2 (n - 1)^2 triangles with random heights: every vertex in up to 6 faces."""
    g = torch.Generator().manual_seed(1)
    ii, jj = torch.meshgrid(torch.arange(n - 1), torch.arange(n - 1), indexing="ij")
    v0 = (ii * n + jj).reshape(-1)
    faces = torch.cat((torch.stack((v0, v0 + 1, v0 + n), -1), torch.stack((v0 + 1, v0 + n + 1, v0 + n), -1)))
    y, x = torch.meshgrid(torch.linspace(0, 1, n), torch.linspace(0, 1, n), indexing="ij")
    pos = torch.stack((x.reshape(-1), y.reshape(-1), 0.1 * torch.rand(n * n, generator=g)), -1)
    uv = torch.stack((x.reshape(-1), y.reshape(-1)), -1)
    return pos, uv, faces


def test_normals_and_tangent_frames_are_bit_identical_under_load(loaded_two_threads):
    pos0, uv0, faces = _grid_mesh()
    w = torch.rand(pos0.shape[0], 3, generator=torch.Generator().manual_seed(2))

    def run():
        pos, uv = pos0.clone().requires_grad_(), uv0.clone().requires_grad_()
        n = vertex_normals(pos, faces)
        fr = tangent_frames(pos, faces, uv)
        loss = (n * w).sum() + (fr.tangents[:, :3] * w[:fr.tangents.shape[0]]).sum()
        return [n.detach(), fr.tangents.detach()] + list(torch.autograd.grad(loss, (pos, uv)))

    _assert_repeats(run, 20)

"""The native kernels as torch operators: every ``torch.ops.difftex`` op passes ``torch.library.opcheck``.

Each op is checked on the arguments the library itself passes it (recorded
from public calls: sample with every kernel filter, a cube map, rasterize,
depth peeling, the nvdiffrast layout), so the schema, the fake (meta)
implementation in ``difftex/_native.py`` and the CPU kernel are held to one
another where they are really used.
"""
from __future__ import annotations

import pytest
import torch

import difftex
from difftex import _native as native

pytestmark = pytest.mark.skipif(native.load() is None, reason="native kernels not built")

ALL_OPS = ("taps_forward", "taps_backward", "stochastic_taps_forward", "stochastic_taps_backward", "probe_offsets",
           "tap_front",
           "box2", "box2_adjoint", "ewa_forward", "ewa_backward", "sample_forward", "sample_backward", "raster",
           "raster_fragments", "raster_fused", "raster_fragments_backward", "cube_front", "cube_front_backward",
           "cube_read", "cube_read_backward", "sat_forward", "sat_backward", "ripmap_build", "ripmap_adjoint",
           "ripmap_read", "ripmap_read_backward")


class _Recorder:
    """Stands in for ``torch.ops.difftex``: forwards each call and keeps the first arguments of each op."""

    def __init__(self):
        self.calls: dict[str, tuple] = {}

    def __getattr__(self, name):
        op = getattr(torch.ops.difftex, name)

        def call(*args):
            self.calls.setdefault(name, tuple(_clone(a) for a in args))
            return op(*args)
        return call


def _clone(a):
    if isinstance(a, torch.Tensor):
        return a.detach().clone()
    if isinstance(a, (list, tuple)):
        return type(a)(_clone(x) for x in a)
    return a


@pytest.fixture(scope="module")
def recorded():
    kernel = native.load()
    rec = _Recorder()
    real = kernel._ops
    kernel._ops = rec
    try:
        g = torch.Generator().manual_seed(1)
        tex = torch.rand(1, 3, 32, 24, generator=g, dtype=torch.float64)
        uv = torch.rand(1, 6, 5, 2, generator=g, dtype=torch.float64)
        dx = torch.randn(1, 6, 5, 2, generator=g, dtype=torch.float64) * 0.2
        dy = torch.randn(1, 6, 5, 2, generator=g, dtype=torch.float64) * 0.05
        for f in ("bilinear", "trilinear", "anisotropic", "ewa", "ripmap", "sat"):
            t, u = tex.clone().requires_grad_(), uv.clone().requires_grad_()
            # Derivatives without a gradient: the taps' front end runs on the kernel too.
            difftex.sample(t, u, filter=f, uv_dx=dx, uv_dy=dy, wrap="mirror").sum().backward()
            t, u = tex.clone().requires_grad_(), uv.clone().requires_grad_()
            a, b = dx.clone().requires_grad_(), dy.clone().requires_grad_()
            difftex.sample(t, u, filter=f, uv_dx=a, uv_dy=b).sum().backward()
        for f in ("trilinear", "anisotropic"):  # stratified draws: the stochastic taps, the probes' offsets
            t, u = tex.clone().requires_grad_(), uv.clone().requires_grad_()
            a = dx.clone().requires_grad_()
            difftex.sample(t, u, filter=f, uv_dx=a, uv_dy=dy, stochastic=2, generator=g).sum().backward()
        cube = torch.rand(1, 6, 3, 16, 16, generator=g, dtype=torch.float64, requires_grad=True)
        dirs = torch.randn(1, 4, 5, 3, generator=g, dtype=torch.float64, requires_grad=True)
        ddx = (torch.randn(1, 4, 5, 3, generator=g, dtype=torch.float64) * 0.1).requires_grad_()
        difftex.envmap.cubemap(cube, dirs, filter="trilinear", dirs_dx=ddx, dirs_dy=ddx * 0.5).sum().backward()
        pos = torch.tensor([[-0.8, -0.8, 0.1, 1.0], [0.8, -0.7, 0.2, 1.0], [0.0, 0.9, 0.3, 1.0],
                            [-0.5, 0.5, 0.5, 1.0]], dtype=torch.float64, requires_grad=True)
        faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
        frags = difftex.rasterize(pos, faces, (12, 10))
        (frags.bary.sum() + frags.bary_dx.sum()).backward()
        difftex.rasterize(pos.detach(), faces, (12, 10), derivatives=False)
        difftex.depth_peel(pos.detach(), faces, (12, 10), 2)
        from difftex import nvdiffrast as dr
        dr.rasterize(dr.RasterizeCudaContext(), pos.detach()[None].float(), faces.int(), (12, 10))
    finally:
        kernel._ops = real
    return rec.calls


def test_every_op_is_exercised(recorded):
    missing = [name for name in ALL_OPS if name not in recorded]
    assert not missing, f"not reached by the recorded calls: {missing}"
    assert sorted(ALL_OPS) == sorted(n for n in dir(torch.ops.difftex) if not n.startswith("_") and
                                     isinstance(getattr(torch.ops.difftex, n), torch._ops.OpOverloadPacket))


@pytest.mark.parametrize("name", ALL_OPS)
def test_opcheck(recorded, name):
    if name not in recorded:
        pytest.skip(f"{name} not recorded (test_every_op_is_exercised fails)")
    op = getattr(torch.ops.difftex, name).default
    torch.library.opcheck(op, recorded[name],
                          test_utils=("test_schema", "test_autograd_registration", "test_faketensor"))


@pytest.mark.parametrize("packed", [False, True])
def test_opcheck_raster_fragments_without_derivatives(packed):
    # rasterize(..., derivatives=False) and nvdiffrast without output_db: the derivative outputs are empty [0].
    pos = torch.tensor([[[-0.8, -0.8, 0.1, 1.0], [0.8, -0.7, 0.2, 1.0], [0.0, 0.9, 0.3, 1.0]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    tri_id = difftex.rasterize(pos, faces, (6, 5)).tri_id
    args = (pos, faces, tri_id, packed, 0, False)
    out = torch.ops.difftex.raster_fragments(*args)
    assert [tuple(t.shape) for t in out][2:] == ([(0,)] if packed else
                                           [(0,), (0,), (1, 6, 5, 3), (1, 6, 5), (0,), (0,)])
    torch.library.opcheck(torch.ops.difftex.raster_fragments.default, args,
                          test_utils=("test_schema", "test_autograd_registration", "test_faketensor"))

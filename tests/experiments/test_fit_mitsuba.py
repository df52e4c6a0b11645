"""experiments/bench/bench_fit_mitsuba.py: the mesh it hands Mitsuba and the libLLVM it picks (the fit itself
needs the peers extra and runs in the benchmark, not here)."""
from __future__ import annotations

import numpy as np
import torch

import difftex
from experiments.bench import bench_fit_mitsuba as bfm


def _read_ply(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").split("\n")
    nv = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in header if h.startswith("element face")).split()[-1])
    vert = np.frombuffer(data, dtype="<f4", count=5 * nv, offset=end).reshape(nv, 5)
    face = np.frombuffer(data, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=nf, offset=end + 20 * nv)
    return vert, face


def test_ply_splits_face_varying_corners(tmp_path):
    # Two triangles sharing an edge whose uv differ across it (a seam): 4 positions, 5 (position, uv) pairs.
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    faces = torch.tensor([[0, 1, 2], [2, 1, 3]])
    uv = torch.tensor([[0.0, 0], [0.5, 0], [0, 0.5], [0.6, 0.1], [0.7, 0.6], [0.9, 0.9]])
    uv_faces = torch.tensor([[0, 1, 2], [3, 1, 4]])
    bfm.write_ply(tmp_path / "m.ply", difftex.Mesh(pos, faces, uv, uv_faces))
    vert, face = _read_ply(tmp_path / "m.ply")
    assert vert.shape[0] == 5 and face.shape[0] == 2
    assert (face["n"] == 3).all()
    for f in range(2):
        for k in range(3):
            v = vert[face["i"][f, k]]
            np.testing.assert_array_equal(v[:3], pos[faces[f, k]].numpy())
            np.testing.assert_array_equal(v[3:], uv[uv_faces[f, k]].numpy())


def test_libllvm_from_the_environment_wins(monkeypatch):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/some/libLLVM.so.99")
    assert bfm.pick_libllvm() == "/some/libLLVM.so.99"


def test_libllvm_search_takes_the_newest_of_16_or_later(monkeypatch, tmp_path):
    for name in ("libLLVM-15.so", "libLLVM.so.18.1", "libLLVM-22-rust-1.95.0-stable.so", "libLLVM-14.so.1"):
        (tmp_path / name).touch()
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(bfm, "LIBLLVM_GLOBS", [str(tmp_path / "libLLVM*.so*")])
    assert bfm.pick_libllvm() == str(tmp_path / "libLLVM-22-rust-1.95.0-stable.so")
    for name in ("libLLVM.so.18.1", "libLLVM-22-rust-1.95.0-stable.so"):
        (tmp_path / name).unlink()
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    assert bfm.pick_libllvm() is None  # 15 and 14 only: Dr.Jit's differentiable kernels abort on them

"""Small meshes and frames shared by the shading tests."""
import math

import torch


def grid_plane(n: int, dtype=torch.float64):
    """An n x n vertex grid on z = 0 over [0, 1]^2, counter-clockwise seen from +z: (pos [V, 3], faces [F, 3])."""
    y, x = torch.meshgrid(torch.linspace(0, 1, n, dtype=dtype), torch.linspace(0, 1, n, dtype=dtype), indexing="ij")
    pos = torch.stack([x, y, torch.zeros_like(x)], -1).reshape(-1, 3)
    idx = torch.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = torch.cat([torch.stack([a, b, d], -1).reshape(-1, 3), torch.stack([a, d, c], -1).reshape(-1, 3)])
    return pos, faces


def uv_sphere(n_theta: int = 16, n_phi: int = 32, dtype=torch.float64):
    """A latitude-longitude unit sphere with one position per point and face-varying uv (seam and pole copies).

    u = phi / 2pi, v = theta / pi (theta from the +z pole), so dP/du is along
    e_phi and dP/dv along e_theta. Returns pos, faces, uv, uv_faces and the
    per-position (theta, phi).
    """
    th = torch.arange(1, n_theta, dtype=dtype) * math.pi / n_theta
    ph = torch.arange(n_phi, dtype=dtype) * 2 * math.pi / n_phi
    T, P = torch.meshgrid(th, ph, indexing="ij")
    ring = torch.stack([T.sin() * P.cos(), T.sin() * P.sin(), T.cos()], -1).reshape(-1, 3)
    pos = torch.cat([torch.tensor([[0, 0, 1.0]], dtype=dtype), ring, torch.tensor([[0, 0, -1.0]], dtype=dtype)])
    angles = torch.cat([torch.tensor([[0.0, 0.0]], dtype=dtype), torch.stack([T, P], -1).reshape(-1, 2),
                        torch.tensor([[math.pi, 0.0]], dtype=dtype)])

    def pid(i, j):
        if i == 0:
            return 0
        if i == n_theta:
            return len(pos) - 1
        return 1 + (i - 1) * n_phi + j % n_phi

    tid = lambda i, j: i * (n_phi + 1) + j
    vv, uu = torch.meshgrid(torch.linspace(0, 1, n_theta + 1, dtype=dtype), torch.linspace(0, 1, n_phi + 1, dtype=dtype),
                            indexing="ij")
    uv = torch.stack([uu, vv], -1).reshape(-1, 2)
    faces, uv_faces = [], []
    for i in range(n_theta):
        for j in range(n_phi):
            # (i, j) -> (i + 1, j) -> (i, j + 1): along +theta then +phi, counter-clockwise from outside.
            for tri in (((i, j), (i + 1, j), (i, j + 1)), ((i, j + 1), (i + 1, j), (i + 1, j + 1))):
                p = [pid(*c) for c in tri]
                if len(set(p)) == 3:
                    faces.append(p)
                    uv_faces.append([tid(*c) for c in tri])
    return pos, torch.tensor(faces), uv, torch.tensor(uv_faces), angles


def random_frames(shape, dtype=torch.float64, seed=0):
    """Random orthonormal frames [*shape, 3, 3] (rows T, B, N), right-handed."""
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(*shape, 3, 3, dtype=dtype, generator=g))
    return q.transpose(-1, -2)

"""Z-buffer rasterizer with differentiable perspective-correct barycentrics.

The rasterizer works in 2D homogeneous coordinates (Olano & Greer, "Triangle
scan conversion using 2D homogeneous coordinates", 1997): with clip-space
vertices ``h_i = (X_i, Y_i, W_i)`` and a pixel ``p = (x, y, 1)`` in NDC, the
edge functions ``e_i = (h_j x h_k) . p`` are proportional to the
perspective-correct barycentrics of the point of the triangle's plane that
projects onto ``p``. All three have the sign of ``det[h_0 h_1 h_2]`` exactly
when that point lies inside the triangle *and* in front of the eye (w > 0),
so triangles crossing w = 0 need no clipping and no pixel gets a wrong id.
NDC depth ``z = sum_i e_i Z_i / det`` is affine in screen space; fragments
outside ``-1 <= z <= 1`` are dropped, which clips at the near and far planes
exactly.

Visibility (which triangle owns a pixel) is discrete and computed without
autograd; the barycentrics, their screen-space derivatives and the depth of
the winning triangle are then recomputed from ``pos`` with differentiable
torch ops.

Conventions (DESIGN.md section 2): clip space is OpenGL style, row 0 is the
top of the image (NDC y = +1), pixel ``(r, c)`` has its centre at NDC
``x = (c + 0.5) / W * 2 - 1``, ``y = 1 - (r + 0.5) / H * 2``, depth is NDC z
(smaller is nearer) and background pixels have ``tri_id = -1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Sequence

import torch
from torch import Tensor

__all__ = ["Fragments", "rasterize"]

# Candidate (triangle, pixel) pairs evaluated per chunk; bounds the memory of
# the visibility pass at a few hundred MB whatever the mesh or resolution.
_CHUNK_CANDIDATES = 1 << 20
# Largest candidate block for one triangle; bigger bounding boxes are split
# into bands of rows so that one huge triangle cannot exceed the chunk size.
_MAX_BLOCK = 1 << 16
# Bins with fewer triangles than this are merged into a bigger bin: an extra
# kernel launch per tiny bin costs more than the wasted candidates.
_MIN_BIN = 64
_KEY_EMPTY = torch.iinfo(torch.int64).max


@dataclass(frozen=True)
class Fragments:
    """Per-pixel output of :func:`rasterize`.

    Attributes:
        tri_id: [B, H, W] int64, index into ``faces`` of the visible
            triangle, -1 for background.
        bary: [B, H, W, 3] perspective-correct barycentrics of the visible
            triangle's corners (sum to 1); zero on background.
        depth: [B, H, W] NDC z of the visible surface (smaller is nearer);
            zero on background.
        bary_dx: [B, H, W, 3] d(bary) / d(pixel column), analytic.
        bary_dy: [B, H, W, 3] d(bary) / d(pixel row), analytic (rows grow
            downwards, so this is -H/2 times d(bary)/d(NDC y)).

    ``bary``, ``depth``, ``bary_dx`` and ``bary_dy`` are differentiable with
    respect to the clip-space positions given to :func:`rasterize`.
    """

    tri_id: Tensor
    bary: Tensor
    depth: Tensor
    bary_dx: Tensor
    bary_dy: Tensor

    @property
    def mask(self) -> Tensor:
        """[B, H, W] bool, True where a triangle is visible."""
        return self.tri_id >= 0

    @property
    def resolution(self) -> tuple[int, int]:
        """(H, W) of the rasterized image."""
        return int(self.tri_id.shape[1]), int(self.tri_id.shape[2])


# --------------------------------------------------------------------------
# input checking


def _check_pos(pos: Tensor, name: str = "pos") -> Tensor:
    if not isinstance(pos, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(pos).__name__}")
    if pos.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{name} must be float32 or float64, got dtype {pos.dtype}")
    if pos.dim() == 2:
        pos = pos.unsqueeze(0)
    if pos.dim() != 3 or pos.shape[-1] != 4:
        raise ValueError(
            f"{name} must have shape [B, V, 4] or [V, 4] (clip-space x, y, z, w), "
            f"got {tuple(pos.shape)}"
        )
    if not bool(torch.isfinite(pos.detach()).all()):
        raise ValueError(f"{name} contains non-finite values (NaN or inf); clip-space positions must be finite")
    return pos


def _check_faces(faces: Tensor, num_vertices: int, device: torch.device, name: str = "faces") -> Tensor:
    if not isinstance(faces, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(faces).__name__}")
    if faces.dtype.is_floating_point or faces.dtype.is_complex or faces.dtype == torch.bool:
        raise TypeError(f"{name} must be an integer tensor, got dtype {faces.dtype}")
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"{name} must have shape [F, 3], got {tuple(faces.shape)}")
    faces = faces.to(device=device, dtype=torch.int64)
    if faces.numel() > 0:
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0 or hi >= num_vertices:
            raise ValueError(
                f"{name} indices must lie in [0, {num_vertices - 1}] (number of vertices), "
                f"got values in [{lo}, {hi}]"
            )
    return faces


def _check_resolution(resolution: Sequence[int]) -> tuple[int, int]:
    try:
        h, w = resolution
    except (TypeError, ValueError):
        raise ValueError(f"resolution must be a pair (H, W), got {resolution!r}") from None
    if isinstance(h, bool) or isinstance(w, bool):
        raise TypeError(f"resolution must hold two ints, got {resolution!r}")
    try:
        hi, wi = int(h), int(w)
    except (TypeError, ValueError):
        raise TypeError(f"resolution must hold two ints, got {resolution!r}") from None
    if hi != h or wi != w:
        raise TypeError(f"resolution must hold two ints, got {resolution!r}")
    if hi <= 0 or wi <= 0:
        raise ValueError(f"resolution must be positive, got (H, W) = ({hi}, {wi})")
    if hi * wi > 2**31 - 1:
        raise ValueError(f"resolution {hi}x{wi} is too large (more than 2**31 pixels)")
    return hi, wi


# --------------------------------------------------------------------------
# shared maths


def _pow2_scale(v: Tensor) -> Tensor:
    """Per-triangle power-of-two factor bringing max |coordinate| into [0.5, 1).

    Homogeneous coordinates may be scaled freely; a power of two keeps the
    products exact, so the edge functions of two triangles sharing an edge
    stay exact negatives of each other (watertightness), and huge inputs
    cannot overflow the cross products. ``v``: [..., 3, 4] -> [...].
    """
    m = v.detach().abs().amax(dim=(-1, -2))
    _, exp = torch.frexp(m)
    return torch.ldexp(torch.ones_like(m), -exp)


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross product with one rounding per term, no fused multiply-add.

    ``_cross(b, a)`` is then bit-for-bit ``-_cross(a, b)``, which the fill
    rule relies on: two triangles sharing an edge see exactly opposite edge
    functions.
    """
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), dim=-1)


def _edge_normals(v: Tensor) -> tuple[Tensor, Tensor]:
    """Homogeneous edge functions of triangles ``v`` [..., 3, 4] (clip space).

    Returns ``n`` [..., 3, 3] where row i = (a_i, b_i, c_i) of
    ``e_i(x, y) = a_i x + b_i y + c_i`` (NDC x, y), and ``det`` [...].
    """
    h = v[..., [0, 1, 3]]
    h0, h1, h2 = h.unbind(-2)
    n = torch.stack((_cross(h1, h2), _cross(h2, h0), _cross(h0, h1)), dim=-2)
    det = (h0 * n[..., 0, :]).sum(-1)
    return n, det


def _pixel_centres(n: int, dtype: torch.dtype, device: torch.device, flip: bool) -> Tensor:
    """NDC coordinates of pixel centres along one axis (row 0 = NDC y +1)."""
    c = (torch.arange(n, dtype=dtype, device=device) + 0.5) * (2.0 / n) - 1.0
    return -c if flip else c


def _next_pow2_exp(n: Tensor) -> Tensor:
    """ceil(log2(n)) for integer n >= 1, elementwise, as int64."""
    _, e = torch.frexp((n - 1).to(torch.float64))
    return e.to(torch.int64)


# --------------------------------------------------------------------------
# visibility


@dataclass
class _Setup:
    """Per-triangle data of the visibility pass, for triangles that survive culling."""

    tri: Tensor  # [N] int64, global index b * F + f
    coef: Tensor  # [N, 3, 3] sign-normalised edge functions (inside: e >= thr)
    thr: Tensor  # [N, 3] 0 where the fill rule owns the edge, else the smallest positive
    zcoef: Tensor  # [N, 3] z_ndc = zx * x + zy * y + zc
    c0: Tensor  # [N] first bbox column
    r0: Tensor  # [N] first bbox row
    bw: Tensor  # [N] bbox width in pixels (>= 1)
    bh: Tensor  # [N] bbox height in pixels (>= 1)


def _setup_triangles(pos: Tensor, faces: Tensor, H: int, W: int, cull_backfaces: bool) -> _Setup:
    B = pos.shape[0]
    F = faces.shape[0]
    dtype, device = pos.dtype, pos.device
    v = pos[:, faces].reshape(B * F, 3, 4)

    # Early cull: every vertex beyond the same clip plane (valid for any sign
    # of w, since the visible set -w <= x, y, z <= w is convex).
    X, Y, Z, Wc = v.unbind(-1)
    outside = (
        (X > Wc).all(1) | (X < -Wc).all(1) | (Y > Wc).all(1) | (Y < -Wc).all(1)
        | (Z > Wc).all(1) | (Z < -Wc).all(1)
    )
    tri = torch.nonzero(~outside).squeeze(1)
    v = v[tri]
    v = v * _pow2_scale(v)[:, None, None]

    n, det = _edge_normals(v)
    keep = det != 0  # zero-area (or edge-on) triangles cover nothing
    if cull_backfaces:
        keep &= det > 0  # front faces are counter-clockwise in NDC (OpenGL)

    # Screen bounding box. Points of the triangle in front of the near plane
    # (z >= -w) form a convex polygon: its vertices are the kept corners and
    # the edge / plane crossings. If all of them have w > 0 (any ordinary
    # projection), the projected polygon is their convex hull; otherwise
    # fall back to the whole screen, which is correct, only slower.
    d = v[..., 2] + v[..., 3]  # z + w per corner, [N, 3]
    vi, vj = v, v.roll(-1, dims=1)
    di, dj = d, d.roll(-1, dims=1)
    cross = (di >= 0) != (dj >= 0)
    denom = torch.where(cross, di - dj, torch.ones_like(di))
    t = (di / denom).unsqueeze(-1)
    pts = torch.cat((v, vi + t * (vj - vi)), dim=1)  # [N, 6, 4]
    use = torch.cat((d >= 0, cross), dim=1)
    pw = pts[..., 3]
    bbox_ok = (~use | (pw > 0)).all(1)
    pw_safe = torch.where(use & (pw > 0), pw, torch.ones_like(pw))
    px, py = pts[..., 0] / pw_safe, pts[..., 1] / pw_safe
    inf = torch.full_like(px, float("inf"))
    xmin = torch.where(use, px, inf).amin(1)
    xmax = torch.where(use, px, -inf).amax(1)
    ymin = torch.where(use, py, inf).amin(1)
    ymax = torch.where(use, py, -inf).amax(1)
    keep &= use.any(1)
    one = torch.ones_like(xmin)
    xmin = torch.where(bbox_ok, xmin, -one).clamp(-1, 1)
    xmax = torch.where(bbox_ok, xmax, one).clamp(-1, 1)
    ymin = torch.where(bbox_ok, ymin, -one).clamp(-1, 1)
    ymax = torch.where(bbox_ok, ymax, one).clamp(-1, 1)
    # Pixel centres inside [min, max], widened by a small margin so rounding
    # of the projected corners never drops a pixel the edge test accepts.
    m = 1e-3
    c0 = torch.ceil((xmin + 1) * (W / 2) - 0.5 - m).clamp(0, W).to(torch.int64)
    c1 = torch.floor((xmax + 1) * (W / 2) - 0.5 + m).clamp(-1, W - 1).to(torch.int64)
    r0 = torch.ceil((1 - ymax) * (H / 2) - 0.5 - m).clamp(0, H).to(torch.int64)
    r1 = torch.floor((1 - ymin) * (H / 2) - 0.5 + m).clamp(-1, H - 1).to(torch.int64)
    bw, bh = c1 - c0 + 1, r1 - r0 + 1
    keep &= (bw > 0) & (bh > 0)

    sel = torch.nonzero(keep).squeeze(1)
    tri, n, det, v = tri[sel], n[sel], det[sel], v[sel]
    c0, r0, bw, bh = c0[sel], r0[sel], bw[sel], bh[sel]

    # Orient every edge function so that the inside is e >= 0.
    sgn = torch.sign(det)
    coef = n * sgn[:, None, None]
    # Top-left style fill rule: a pixel centre exactly on an edge belongs to
    # the triangle whose edge gradient (a, b) points towards +x (or +y when
    # the edge is horizontal), i.e. the sample is nudged by (d, d^2). Two
    # triangles sharing an edge have exactly opposite coefficients, so
    # exactly one of them owns such a pixel: no cracks, no double coverage.
    a, b = coef[..., 0], coef[..., 1]
    owns = (a > 0) | ((a == 0) & (b > 0))
    tiny = torch.finfo(dtype).tiny * torch.finfo(dtype).eps  # smallest subnormal
    thr = torch.where(owns, torch.zeros_like(a), torch.full_like(a, tiny))
    # z_ndc = sum_i e_i Z_i / det, affine in NDC (x, y).
    zcoef = (n * v[..., 2:3]).sum(1) / det[:, None]
    return _Setup(tri, coef, thr, zcoef, c0, r0, bw, bh)


def _split_rows(s: _Setup) -> _Setup:
    """Split bounding boxes bigger than _MAX_BLOCK candidates into row bands."""
    ws = torch.ones_like(s.bw) << _next_pow2_exp(s.bw)
    hs = torch.ones_like(s.bh) << _next_pow2_exp(s.bh)
    big = ws * hs > _MAX_BLOCK
    if not bool(big.any()):
        return s
    band = (_MAX_BLOCK // ws).clamp(min=1)
    nb = torch.where(big, (s.bh + band - 1) // band, torch.ones_like(band))
    rep = torch.repeat_interleave(torch.arange(len(nb), device=nb.device), nb)
    start = torch.cumsum(nb, 0) - nb
    k = torch.arange(len(rep), device=nb.device) - start[rep]  # band index
    band_r = band[rep]
    r0 = s.r0[rep] + k * torch.where(big[rep], band_r, torch.zeros_like(band_r))
    bh = torch.where(big[rep], torch.minimum(band_r, s.bh[rep] - k * band_r), s.bh[rep])
    return _Setup(s.tri[rep], s.coef[rep], s.thr[rep], s.zcoef[rep], s.c0[rep], r0, s.bw[rep], bh)


def _candidate_chunks(s: _Setup) -> Iterator[tuple[_Setup, int, int]]:
    """Group triangles by power-of-two bbox size and yield bounded chunks.

    Yields (chunk, Hs, Ws): every triangle of the chunk tests an Hs x Ws
    block of pixels starting at its bbox corner (at most 4x its bbox, or
    8x for the few triangles of a merged sparse bin).
    """
    ew = _next_pow2_exp(s.bw)
    eh = _next_pow2_exp(s.bh)
    key, order = torch.sort(ew * 64 + eh)
    # One gather per field here, so that chunks below are free slices.
    s = _Setup(*(getattr(s, f)[order] for f in _Setup.__dataclass_fields__))
    ew, eh = ew[order], eh[order]
    uniq, counts = torch.unique_consecutive(key, return_counts=True)
    uniq_l, counts_l = uniq.tolist(), counts.tolist()
    # Merge sparse bins into the next bin (at most 2x bigger per axis): a
    # few wasted candidates cost less than one more pass of kernel launches.
    groups: list[tuple[int, int, int, int]] = []  # (start, stop, ew, eh)
    start, pending, mw, mh = 0, 0, 0, 0
    for i, (k, c) in enumerate(zip(uniq_l, counts_l)):
        pending += c
        mw, mh = max(mw, k // 64), max(mh, k % 64)
        nxt = uniq_l[i + 1] if i + 1 < len(uniq_l) else None
        if nxt is not None and pending < _MIN_BIN and nxt // 64 - mw <= 1 and 0 <= nxt % 64 - mh <= 1:
            continue
        groups.append((start, start + pending, mw, mh))
        start, pending, mw, mh = start + pending, 0, 0, 0
    for g0, g1, ws_e, hs_e in groups:
        Ws, Hs = 1 << ws_e, 1 << hs_e
        per = max(1, _CHUNK_CANDIDATES // (Ws * Hs))
        for c in range(g0, g1, per):
            c1 = min(g1, c + per)
            yield _Setup(*(getattr(s, f)[c:c1] for f in _Setup.__dataclass_fields__)), Hs, Ws


def _fragments(
    pos: Tensor, faces: Tensor, H: int, W: int, cull_backfaces: bool
) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """Yield chunks of covered fragments: (pixel, tri, z), each [m].

    ``pixel`` is the flat index b * H * W + r * W + c, ``tri`` the global
    triangle index b * F + f, ``z`` the NDC depth. A fragment is covered
    when the pixel centre is inside the triangle (fill rule applied), in
    front of the eye and between the near and far planes.
    """
    dtype, device = pos.dtype, pos.device
    F = faces.shape[0]
    if F == 0:
        return
    s = _setup_triangles(pos, faces, H, W, cull_backfaces)
    if s.tri.numel() == 0:
        return
    s = _split_rows(s)
    nan = float("nan")
    xs = torch.cat((_pixel_centres(W, dtype, device, flip=False), torch.tensor([nan], dtype=dtype, device=device)))
    ys = torch.cat((_pixel_centres(H, dtype, device, flip=True), torch.tensor([nan], dtype=dtype, device=device)))
    for c, Hs, Ws in _candidate_chunks(s):
        lw, lh = Ws.bit_length() - 1, Hs.bit_length() - 1
        j = torch.arange(Ws, device=device)
        i = torch.arange(Hs, device=device)
        # Columns / rows beyond the bbox read NaN, which fails every test.
        col = torch.where(j < c.bw[:, None], c.c0[:, None] + j, W)  # [n, Ws]
        row = torch.where(i < c.bh[:, None], c.r0[:, None] + i, H)  # [n, Hs]
        x = xs[col]
        y = ys[row]
        covered = None
        for k in range(3):
            # The same operation order for every triangle, ((a x) + c) + (b y),
            # so shared edges evaluate to exact negatives of each other.
            axc = c.coef[:, k, 0:1] * x + c.coef[:, k, 2:3]
            by = c.coef[:, k, 1:2] * y
            e = axc[:, None, :] + by[:, :, None]
            inside = e >= c.thr[:, k, None, None]
            covered = inside if covered is None else covered.logical_and_(inside)
        idx = torch.nonzero(covered.view(-1)).squeeze(1)
        if idx.numel() == 0:
            continue
        t = idx >> (lw + lh)
        jj = idx & (Ws - 1)
        ii = (idx >> lw) & (Hs - 1)
        z = c.zcoef[t, 0] * x[t, jj] + c.zcoef[t, 2] + c.zcoef[t, 1] * y[t, ii]
        b = torch.div(c.tri, F, rounding_mode="floor")
        base = (b * H + c.r0) * W + c.c0
        pix = base[t] + ii * W + jj
        tri = c.tri[t]
        ok = (z >= -1) & (z <= 1)
        if not bool(ok.all()):
            pix, tri, z = pix[ok], tri[ok], z[ok]
        yield pix, tri, z


def _visibility(pos: Tensor, faces: Tensor, H: int, W: int, cull_backfaces: bool) -> Tensor:
    """Z-buffer: [B, H, W] int64 id of the nearest covering triangle, -1 if none.

    The depth test runs on one int64 key per fragment, (float32 bits of
    z + 1) << 32 | triangle id, reduced with amin per pixel: nearest wins,
    equal depths go to the lowest triangle id, whatever the processing
    order (deterministic on CPU and CUDA).
    """
    B = pos.shape[0]
    F = faces.shape[0]
    buf = torch.full((B * H * W,), _KEY_EMPTY, dtype=torch.int64, device=pos.device)
    for pix, tri, z in _fragments(pos, faces, H, W, cull_backfaces):
        # z + 1 >= 0 on covered fragments, and the IEEE bits of non-negative
        # floats sort like the floats.
        zk = (z + 1).to(torch.float32).view(torch.int32).to(torch.int64)
        key = (zk << 32) | (tri % F)
        buf.scatter_reduce_(0, pix, key, "amin")
    tri_id = torch.where(buf == _KEY_EMPTY, -1, buf & 0xFFFFFFFF)
    return tri_id.view(B, H, W)


def _coverage_count(pos: Tensor, faces: Tensor, resolution: Sequence[int], *, cull_backfaces: bool = False) -> Tensor:
    """[B, H, W] int64 number of triangles covering each pixel centre (no z test).

    A diagnostic for the fill rule (a closed mesh must give counts in {0, 2}
    without culling, {0, 1} with it); not part of the public API.
    """
    pos = _check_pos(pos)
    faces = _check_faces(faces, pos.shape[1], pos.device)
    H, W = _check_resolution(resolution)
    B = pos.shape[0]
    count = torch.zeros(B * H * W, dtype=torch.int64, device=pos.device)
    with torch.no_grad():
        for pix, _, _ in _fragments(pos.detach(), faces, H, W, cull_backfaces):
            count.index_add_(0, pix, torch.ones_like(pix))
    return count.view(B, H, W)


# --------------------------------------------------------------------------
# differentiable pass


def _bary_at(v: Tensor, x: Tensor, y: Tensor, W: int, H: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Perspective-correct barycentrics, depth and pixel derivatives.

    ``v`` [N, 3, 4] clip-space corners, ``x``, ``y`` [N] NDC sample points.
    Returns bary [N, 3], depth [N], d(bary)/d(column) [N, 3],
    d(bary)/d(row) [N, 3]. Differentiable with respect to ``v``; every
    division is guarded so that degenerate input gives finite values and
    finite gradients (the "double where" pattern).
    """
    v = v * _pow2_scale(v)[:, None, None]  # invariant: homogeneous scale
    # Corner j and k of edge i (opposite corner i), all three edges at once.
    vj = v.roll(-1, dims=1)  # roll: much cheaper than fancy indexing on CPU
    vk = v.roll(-2, dims=1)
    Xj, Yj, _, Wj = vj.unbind(-1)
    Xk, Yk, _, Wk = vk.unbind(-1)
    a = Yj * Wk - Wj * Yk  # (h_j x h_k) . (x, y, 1) = a x + b y + c
    b = Wj * Xk - Xj * Wk
    c = Xj * Yk - Yj * Xk
    e = a * x[:, None] + b * y[:, None] + c  # [N, 3]
    s = e.sum(-1)
    ok = s != 0
    s_safe = torch.where(ok, s, torch.ones_like(s))
    bary = e / s_safe[:, None]
    # d(bary_i)/dx = (a_i - bary_i * sum(a)) / sum(e), same for y with b.
    dx = (a - bary * a.sum(-1, keepdim=True)) / s_safe[:, None]
    dy = (b - bary * b.sum(-1, keepdim=True)) / s_safe[:, None]
    zn = (e * v[..., 2]).sum(-1)
    wn = (e * v[..., 3]).sum(-1)
    okw = ok & (wn != 0)
    depth = zn / torch.where(okw, wn, torch.ones_like(wn))
    zero3 = torch.zeros_like(bary)
    bary = torch.where(ok[:, None], bary, zero3)
    # NDC -> pixel units: x grows 2/W per column, y falls 2/H per row.
    dx = torch.where(ok[:, None], dx, zero3) * (2.0 / W)
    dy = torch.where(ok[:, None], dy, zero3) * (-2.0 / H)
    depth = torch.where(okw, depth, torch.zeros_like(depth))
    return bary, depth, dx, dy


def rasterize(
    pos: Tensor,
    faces: Tensor,
    resolution: Sequence[int],
    *,
    cull_backfaces: bool = False,
) -> Fragments:
    """Rasterize triangles with a z-buffer into per-pixel triangle ids and barycentrics.

    Args:
        pos: [B, V, 4] or [V, 4] clip-space positions (OpenGL style, NDC =
            xyz / w, visible where -w <= x, y, z <= w), float32 or float64.
            [V, 4] gives B = 1.
        faces: [F, 3] integer vertex indices; front faces are
            counter-clockwise in NDC (OpenGL convention).
        resolution: (H, W) in pixels. Pixel (r, c) samples NDC
            x = (c + 0.5) / W * 2 - 1, y = 1 - (r + 0.5) / H * 2 (row 0 is the
            top of the image).
        cull_backfaces: drop clockwise (back-facing) triangles.

    Returns:
        :class:`Fragments` with tri_id [B, H, W] int64 (-1 = background),
        bary [B, H, W, 3] perspective-correct, depth [B, H, W] NDC z and the
        analytic screen-space derivatives bary_dx, bary_dy [B, H, W, 3] per
        pixel column / row.

    Visibility: the nearest fragment (smallest NDC z, compared at float32
    precision) wins, equal depths go to the lowest triangle id. Pixel
    centres exactly on an edge follow a top-left style fill rule, so a
    closed mesh covers each pixel exactly once per surface layer.
    Triangles crossing w = 0 or the near / far planes are handled exactly
    (2D homogeneous rasterization plus a per-pixel depth range test);
    triangles wholly outside the view volume are culled early.

    ``bary``, ``depth``, ``bary_dx`` and ``bary_dy`` are differentiable with
    respect to ``pos`` (the perspective-correct formula); which triangle is
    visible is not. Raises TypeError on bad dtypes, ValueError naming the
    argument on bad shapes, out-of-range faces or non-finite positions.
    """
    pos = _check_pos(pos)
    faces = _check_faces(faces, pos.shape[1], pos.device)
    H, W = _check_resolution(resolution)
    B = pos.shape[0]
    with torch.no_grad():
        tri_id = _visibility(pos.detach(), faces, H, W, cull_backfaces)

    flat = tri_id.reshape(-1)
    idx = torch.nonzero(flat >= 0).squeeze(1)
    f = flat[idx]
    bi = torch.div(idx, H * W, rounding_mode="floor")
    rc = idx - bi * (H * W)
    r = torch.div(rc, W, rounding_mode="floor")
    col = rc - r * W
    xs = _pixel_centres(W, pos.dtype, pos.device, flip=False)
    ys = _pixel_centres(H, pos.dtype, pos.device, flip=True)
    # One flat gather (much faster than 2-index advanced indexing on CPU).
    vid = (bi * pos.shape[1])[:, None] + faces[f]
    v = pos.reshape(-1, 4).index_select(0, vid.reshape(-1)).view(-1, 3, 4)  # [N, 3, 4]
    bary_c, depth_c, dx_c, dy_c = _bary_at(v, xs[col], ys[r], W, H)

    # One scatter of all per-pixel values; the outputs are views into it.
    packed = torch.cat((bary_c, dx_c, dy_c, depth_c[:, None]), dim=1)
    out = packed.new_zeros((B * H * W, 10))
    out.index_put_((idx,), packed)  # in place: no copy of the zeros
    out = out.view(B, H, W, 10)
    return Fragments(
        tri_id=tri_id,
        bary=out[..., 0:3],
        depth=out[..., 9],
        bary_dx=out[..., 3:6],
        bary_dy=out[..., 6:9],
    )

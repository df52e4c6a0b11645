"""Z-buffer rasterizer with differentiable perspective-correct barycentrics.

Visibility (which triangle owns a pixel centre) is exact by construction for
every triangle whose corners are in front of the eye (w > 0) and project
within the guard band (+-2**13 pixels at 16 sub-pixel bits): the projected
corners are snapped to a fixed-point grid of 2**-16 pixel
(``SUBPIXEL_BITS``; fewer above 4096 pixels), the three edge functions of a
pixel centre are evaluated exactly in int64, and a centre exactly on an edge
goes by a top-left rule (to the triangle it enters when nudged by (d, d^2),
d -> 0+). Each centre is then inside exactly one triangle of any closed fan
or strip, also where several edges meet at it: a closed mesh leaves no hole
and covers no centre twice per surface layer.

Triangles reaching behind the eye (a corner with w <= 0) or far off screen
take the float64 2D homogeneous path (Olano & Greer, "Triangle scan
conversion using 2D homogeneous coordinates", 1997): with clip-space
vertices ``h_i = (X_i, Y_i, W_i)`` and a pixel ``p = (x, y, 1)`` in NDC, the
edge functions ``e_i = (h_j x h_k) . p`` all have the sign of
``det[h_0 h_1 h_2]`` exactly when the point of the triangle's plane that
projects onto ``p`` lies inside the triangle *and* in front of the eye, so
no clipping is needed. Shared edges get bit-for-bit opposite coefficients
(consistent), but where several edges meet at a centre rounding may leave a
hole or a double there (such meshes are rare: a floor running behind the
camera).

The depth test compares the float64 NDC z of the unsnapped triangle's plane
at the pixel centre (whatever the input dtype), so a back face does not win
over the front triangle near a silhouette; fragments outside
``-1 <= z <= 1`` are dropped, which clips at the near and far planes
exactly; equal depths go to the lowest triangle id.

On the CPU the visibility pass runs in the native kernel
(``difftex/csrc/cpu/geometry/raster.cpp``) where ``difftex.backend``
sends it, with the same rules and the same floating-point operations, so
both give identical ids; the torch path here is the reference and serves
CUDA, ``difftex.backend("reference")`` and ``DIFFTEX_NATIVE=0``.

Visibility is discrete and computed without autograd; the barycentrics, their screen-space derivatives and the depth of
the winning triangle are then recomputed from ``pos`` with differentiable
torch ops.

Conventions (DESIGN.md section 2): clip space is OpenGL style, row 0 is the
top of the image (NDC y = +1), pixel ``(r, c)`` has its centre at NDC
``x = (c + 0.5) / W * 2 - 1``, ``y = 1 - (r + 0.5) / H * 2``, depth is NDC z
(smaller is nearer) and background pixels have ``tri_id = -1``.
"""

from __future__ import annotations

import functools
import itertools

from dataclasses import dataclass, field
from typing import Callable, Iterator, Optional, Sequence, TypeVar

import torch
from torch import Tensor

from .._checks import check_index

__all__ = ["Fragments", "depth_peel", "rasterize"]

_T = TypeVar("_T")

# Candidate (triangle, pixel) pairs evaluated per chunk; bounds the memory of
# the visibility pass at a few hundred MB whatever the mesh or resolution.
_CHUNK_CANDIDATES = 1 << 20
# Largest candidate block for one triangle; bigger bounding boxes are split
# into bands of rows so that one huge triangle cannot exceed the chunk size.
_MAX_BLOCK = 1 << 16
# Bins with fewer triangles than this are merged into a bigger bin: an extra
# kernel launch per tiny bin costs more than the wasted candidates.
_MIN_BIN = 64

#: Most bytes :func:`rasterize` may allocate for its per-pixel buffers (all
#: views of the batch together) before it refuses with a ValueError naming the
#: resolution: 16 GiB by default. The estimate counts what every call holds
#: at once (the int64 z-buffer and triangle ids, bary / depth / bary_dx /
#: bary_dy), so a resolution under 2**31 pixels that cannot fit fails at once
#: with a message, not deep in the allocator. Raise it (``difftex.geometry.
#: raster.MAX_BYTES = ...``) on a machine with more memory.
MAX_BYTES = 16 << 30


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
        bary_dx: [B, H, W, 3] d(bary) / d(pixel column), analytic (2/W
            times d(bary)/d(NDC x)); None from ``rasterize(...,
            derivatives=False)``.
        bary_dy: [B, H, W, 3] d(bary) / d(pixel row), analytic (rows grow
            downwards, so this is -2/H times d(bary)/d(NDC y)); None likewise.

    ``bary``, ``depth``, ``bary_dx`` and ``bary_dy`` are differentiable with
    respect to the clip-space positions given to :func:`rasterize`.
    """

    tri_id: Tensor
    bary: Tensor
    depth: Tensor
    bary_dx: Optional[Tensor]
    bary_dy: Optional[Tensor]
    # (flat index of covered pixels, bary, bary_dx, bary_dy there (None
    # without derivatives)), set by rasterize; not an init field, so
    # dataclasses.replace() drops it.
    _compact: Optional[tuple[Tensor, Tensor, Optional[Tensor], Optional[Tensor]]] = field(
        default=None, init=False, repr=False, compare=False
    )

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


def _check_pos(pos: Tensor, name: str = "pos", finite: bool = True) -> Tensor:
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
    # One fused min / max pass (NaN propagates to both): several times
    # faster on the CPU than isfinite(...).all(), which writes a bool tensor.
    if finite and pos.numel() > 0 and not bool(torch.isfinite(torch.stack(torch.aminmax(pos.detach()))).all()):
        raise ValueError(f"{name} contains non-finite values (NaN or inf); clip-space positions must be finite")
    return pos


def _check_resolution(resolution: Sequence[int]) -> tuple[int, int]:
    try:
        h, w = resolution
    except (TypeError, ValueError):
        raise ValueError(f"resolution must be a pair (H, W), got {resolution!r}") from None
    if isinstance(h, bool) or isinstance(w, bool):
        raise TypeError(f"resolution must hold two ints, got {resolution!r}")
    try:
        hi, wi = int(h), int(w)
    except (TypeError, ValueError, OverflowError):
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


def _check_memory(B: int, H: int, W: int, dtype: torch.dtype) -> None:
    """ValueError naming resolution and batch where the per-pixel buffers exceed ``MAX_BYTES``."""
    # z-buffer + tri_id (int64 each), then bary, depth, bary_dx, bary_dy: 10 floats.
    per_pixel = 2 * 8 + 10 * torch.empty((), dtype=dtype).element_size()
    need = B * H * W * per_pixel
    if need > MAX_BYTES:
        raise ValueError(f"resolution {H}x{W} with batch {B} needs at least {need / 2**30:.1f} GiB for the "
                         f"rasterizer's per-pixel buffers ({per_pixel} bytes a pixel), over the limit "
                         f"difftex.geometry.raster.MAX_BYTES = {MAX_BYTES / 2**30:.1f} GiB: render fewer views "
                         f"at a time or smaller tiles, or raise the limit")


def pow2_normalise(x: Tensor, m: Tensor) -> Tensor:
    """``x`` times ``2^-e``, where ``frexp(m) = (f, 2^e)``, ``f`` in [0.5, 1): ``m`` scaled into [0.5, 1).

    The factor is a power of two, so the product is exact; it scales a
    homogeneous point (or all corners of a triangle) without moving it, and
    keeps huge inputs from overflowing the products taken after. ``m`` >= 0
    broadcasts against ``x``; 0 and non-finite ``m`` leave ``x`` as it is.
    The factor is applied in two halves: for a subnormal ``m`` (below 2^-126
    in float32) ``2^-e`` alone overflows to inf.
    """
    _, e = torch.frexp(m.detach())
    h = torch.div(e, 2, rounding_mode="floor")
    one = torch.ones_like(m)
    return x * torch.ldexp(one, -h) * torch.ldexp(one, h - e)


def _pixel_centres(n: int, dtype: torch.dtype, device: torch.device, flip: bool) -> Tensor:
    """NDC coordinates of pixel centres along one axis (row 0 = NDC y +1)."""
    c = (torch.arange(n, dtype=dtype, device=device) + 0.5) * (2.0 / n) - 1.0
    return -c if flip else c


def _rows(t: Tensor, idx: Tensor) -> Tensor:
    """``t[idx]`` along dim 0 through index_select, 1.5-2x faster than advanced indexing on CPU."""
    return t.index_select(0, idx.reshape(-1)).view(*idx.shape, *t.shape[1:])


def _next_pow2_exp(n: Tensor) -> Tensor:
    """ceil(log2(n)) for integer n >= 1, elementwise, as int64."""
    _, e = torch.frexp((n - 1).to(torch.float64))
    return e.to(torch.int64)


# --------------------------------------------------------------------------
# visibility

#: Sub-pixel bits of the fixed-point grid the exact path snaps projected
#: vertices to (fewer for images wider or taller than 4096 pixels, see
#: ``_subpixel_bits``). 16 bits moves an edge by at most 2**-17 pixel: far
#: below what changes the visible triangle except at pixel centres that sit
#: on an edge to that precision, where the fill rule decides anyway.
SUBPIXEL_BITS = 16
# Fixed-point coordinates of the exact path stay within +-2**29 units (the
# guard band): edge-function coefficients then stay below 2**31, products
# and sums below 2**62, exact in int64.
_GUARD = float(1 << 29)
_ID_EMPTY = torch.iinfo(torch.int64).max


def _subpixel_bits(H: int, W: int) -> int:
    """Sub-pixel bits of the exact path at this resolution; 0: no exact path (images over 2**27 pixels wide).

    Pixel centres, at odd multiples of 2**(S-1) from the image centre, must
    stay within 2**27 units: S <= 28 - ceil(log2(max(H, W))).
    """
    return max(0, min(SUBPIXEL_BITS, 28 - (max(H, W) - 1).bit_length()))


@dataclass
class _Items:
    """Work items of the visibility pass, sorted by block size.

    One item = one triangle (or one band of rows of a big triangle) and the
    pixel block it tests. Exact-path items (``edata`` set): ``edata`` [n, 12]
    int64, the sign-normalised integer edge functions E_k = a_k qx + b_k qy
    + c_k of the fixed-point pixel centre (qx, qy), as (a_0..2, b_0..2,
    c_0..2, thr_0..2) (inside: E_k >= thr_k, thr 0 where the fill rule owns
    the edge, else 1), and ``fdata`` [n, 5] float64, the NDC depth plane
    (z0, x0, y0, dz/dx, dz/dy) anchored at the first corner. Float-path items
    (``edata`` None): ``fdata`` [n, 15] float64, edge functions e_k = a_k x +
    b_k y + c_k of the NDC pixel centre as (a, b, c, thr (0 or the smallest
    subnormal)) and the depth plane (zx, zy, zc). ``idata`` [n, 5]: global
    triangle index b * F + f, first column, first row, width and height of
    the pixel block in use.
    """

    fdata: Tensor
    idata: Tensor
    groups: list[tuple[int, int, int, int]]  # (start, stop, log2 Hs, log2 Ws)
    edata: Optional[Tensor] = None
    bits: int = 0


def _bbox_clipped(v: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """NDC bounding box of the part of triangles ``v`` [m, 3, 4] in front of the near plane.

    Points with z >= -w form a convex polygon whose vertices are the kept
    corners and the edge / plane crossings. When all of them have w > 0
    (any ordinary projection) the projected polygon is their convex hull;
    otherwise the box is the whole screen, which is correct, only slower.
    Returns xmin, xmax, ymin, ymax [m] and ``any`` [m] (something is left).
    """
    d = v[..., 2] + v[..., 3]  # z + w per corner
    vj, dj = v.roll(-1, dims=1), d.roll(-1, dims=1)
    cross = (d >= 0) != (dj >= 0)
    denom = torch.where(cross, d - dj, torch.ones_like(d))
    t = (d / denom).unsqueeze(-1)
    pts = torch.cat((v, v + t * (vj - v)), dim=1)  # [m, 6, 4]
    use = torch.cat((d >= 0, cross), dim=1)
    pw = pts[..., 3]
    ok = (~use | (pw > 0)).all(1)
    pw_safe = torch.where(use & (pw > 0), pw, torch.ones_like(pw))
    px, py = pts[..., 0] / pw_safe, pts[..., 1] / pw_safe
    inf = torch.full_like(px, float("inf"))
    one = torch.ones_like(px[:, 0])
    xmin = torch.where(ok, torch.where(use, px, inf).amin(1), -one)
    xmax = torch.where(ok, torch.where(use, px, -inf).amax(1), one)
    ymin = torch.where(ok, torch.where(use, py, inf).amin(1), -one)
    ymax = torch.where(ok, torch.where(use, py, -inf).amax(1), one)
    return xmin, xmax, ymin, ymax, use.any(1)


def _fixed_vertices(pv: Tensor, H: int, W: int, S: int) -> tuple[Tensor, Tensor, Tensor]:
    """Vertices snapped to the fixed-point grid: (qx, qy int64 [N], ok bool [N]).

    ``pv`` [N, 4] float64 clip space. qx = round(x_ndc * W * 2**(S-1)) and
    qy = round(-y_ndc * H * 2**(S-1)): 2**S units a pixel, origin at the image
    centre, rows growing downwards. ``ok`` where w > 0 and both lie within
    the guard band (elsewhere qx = qy = 0). The native kernel computes the
    same values with the same operations (rasterize's two implementations
    give identical ids).
    """
    X, Y, _, Wc = pv.unbind(-1)
    front = Wc > 0
    inv = torch.where(front, Wc, torch.ones_like(Wc))
    fx = (X / inv) * float(W << (S - 1))
    fy = (Y / inv) * -float(H << (S - 1))
    ok = front & (fx.abs() <= _GUARD) & (fy.abs() <= _GUARD)
    zero = torch.zeros_like(fx)
    qx = torch.round(torch.where(ok, fx, zero)).to(torch.int64)
    qy = torch.round(torch.where(ok, fy, zero)).to(torch.int64)
    return qx, qy, ok


def _floor_div(a: Tensor, d: int) -> Tensor:
    return torch.div(a, d, rounding_mode="floor")


def _prepare_exact(tri: Tensor, vid: Tensor, pv: Tensor, qx: Tensor, qy: Tensor, H: int, W: int, S: int,
                   cull_backfaces: bool) -> _Items | None:
    """Integer edge functions and float64 depth planes of triangles whose corners all snapped."""
    x, y = _rows(qx, vid), _rows(qy, vid)  # [n, 3]
    xj, yj, xk, yk = x.roll(-1, 1), y.roll(-1, 1), x.roll(-2, 1), y.roll(-2, 1)
    # E_i(p) = (yk - yj)(px - xj) - (xk - xj)(py - yj) for edge i (corners
    # j = i + 1, k = i + 2): positive inside a counter-clockwise (in NDC,
    # y up) triangle, exact in int64 (|coefficients| < 2**31, |terms| < 2**61).
    a = yk - yj
    b = xj - xk
    c = -(a * xj + b * yj)
    area = a[:, 0] * x[:, 0] + b[:, 0] * y[:, 0] + c[:, 0]  # E_0 at corner 0: twice the signed area
    keep = area > 0 if cull_backfaces else area != 0
    # Depth plane in NDC from the unsnapped corners (all have w > 0 here).
    v = _rows(pv, vid)
    nx, ny, nz = v[..., 0] / v[..., 3], v[..., 1] / v[..., 3], v[..., 2] / v[..., 3]
    dx1, dy1, dz1 = nx[:, 1] - nx[:, 0], ny[:, 1] - ny[:, 0], nz[:, 1] - nz[:, 0]
    dx2, dy2, dz2 = nx[:, 2] - nx[:, 0], ny[:, 2] - ny[:, 0], nz[:, 2] - nz[:, 0]
    d = dx1 * dy2 - dx2 * dy1
    zx = (dz1 * dy2 - dz2 * dy1) / d
    zy = (dx1 * dz2 - dx2 * dz1) / d
    keep &= torch.isfinite(zx) & torch.isfinite(zy)  # a float64-degenerate plane covers nothing
    sgn = torch.sign(area)[:, None]
    a, b, c = a * sgn, b * sgn, c * sgn
    # Top-left rule: a centre exactly on an edge belongs to the triangle the
    # centre would enter if nudged by (d, d^2), d -> 0+ (gradient towards +x,
    # or +y in row units for a horizontal edge). The nudge is one consistent
    # perturbation of the point and the arithmetic is exact, so every centre
    # is inside exactly one triangle of a closed fan or strip: no cracks, no
    # double coverage, also where several edges meet at the centre.
    owns = (a > 0) | ((a == 0) & (b > 0))
    thr = (~owns).to(torch.int64)
    # Pixel centres covered by the snapped bounding box: centre c is at
    # (2c + 1 - W) * 2**(S-1).
    h = 1 << (S - 1)
    c0 = -_floor_div(-(x.amin(1) + (W - 1) * h), 2 * h)
    c1 = _floor_div(x.amax(1) + (W - 1) * h, 2 * h)
    r0 = -_floor_div(-(y.amin(1) + (H - 1) * h), 2 * h)
    r1 = _floor_div(y.amax(1) + (H - 1) * h, 2 * h)
    c0, r0 = c0.clamp(min=0), r0.clamp(min=0)
    c1, r1 = c1.clamp(max=W - 1), r1.clamp(max=H - 1)
    bw, bh = c1 - c0 + 1, r1 - r0 + 1
    sel = torch.nonzero(keep & (bw > 0) & (bh > 0)).squeeze(1)
    if sel.numel() == 0:
        return None
    edata = _rows(torch.cat((a, b, c, thr), 1), sel)
    fdata = _rows(torch.stack((nz[:, 0], nx[:, 0], ny[:, 0], zx, zy), 1), sel)
    return _blocks(*(_rows(t, sel) for t in (tri, c0, r0, bw, bh)), fdata, edata, S)


def _prepare_float(tri: Tensor, vid: Tensor, pv: Tensor, H: int, W: int, cull_backfaces: bool) -> _Items | None:
    """Float64 homogeneous edge functions (Olano & Greer) of triangles the exact path cannot take.

    Those with a corner at w <= 0 or outside the guard band. Consistent
    along shared edges (bit-for-bit opposite coefficients), but not exact
    where several edges meet at a pixel centre.
    """
    dtype = pv.dtype
    X, Y, Z, Wc = pv.unbind(-1)
    # Screen bounding boxes: corners in front of the near plane project
    # directly; triangles reaching behind it take the clipping path.
    front = (Z + Wc >= 0) & (Wc > 0)
    inv_w = 1 / torch.where(front, Wc, torch.ones_like(Wc))
    px, py = _rows(X * inv_w, vid), _rows(Y * inv_w, vid)  # [n, 3]
    xmin, xmax = px.amin(1), px.amax(1)
    ymin, ymax = py.amin(1), py.amax(1)
    alive = torch.ones_like(xmin, dtype=torch.bool)
    slow = torch.nonzero(~_rows(front, vid).all(1)).squeeze(1)
    if slow.numel() > 0:
        bx = _bbox_clipped(_rows(pv, _rows(vid, slow)))
        xmin[slow], xmax[slow], ymin[slow], ymax[slow] = bx[0], bx[1], bx[2], bx[3]
        alive[slow] = bx[4]
    # Pixel centres inside [min, max], widened by a small margin so rounding
    # of the projected corners never drops a pixel the edge test accepts.
    m = 1e-3
    c0 = torch.ceil((xmin.clamp(-1, 1) + 1) * (W / 2) - 0.5 - m).clamp(0, W).to(torch.int64)
    c1 = torch.floor((xmax.clamp(-1, 1) + 1) * (W / 2) - 0.5 + m).clamp(-1, W - 1).to(torch.int64)
    r0 = torch.ceil((1 - ymax.clamp(-1, 1)) * (H / 2) - 0.5 - m).clamp(0, H).to(torch.int64)
    r1 = torch.floor((1 - ymin.clamp(-1, 1)) * (H / 2) - 0.5 + m).clamp(-1, H - 1).to(torch.int64)
    bw, bh = c1 - c0 + 1, r1 - r0 + 1
    sel = torch.nonzero(alive & (bw > 0) & (bh > 0)).squeeze(1)
    tri, vid, c0, r0, bw, bh = (_rows(t, sel) for t in (tri, vid, c0, r0, bw, bh))

    # Edge functions of the survivors: e_i = (h_j x h_k) . (x, y, 1) with
    # h = (X, Y, W), written per component on [n, 3] tensors (edge i uses
    # corners j = i + 1, k = i + 2). Each product is rounded on its own (no
    # fused multiply-add), so a shared edge seen from its two triangles
    # gives bit-for-bit opposite coefficients.
    v = _rows(pv, vid)  # [n, 3, 4]
    X, Y, Z, Wc = v.unbind(-1)
    Xj, Yj, Wj = X.roll(-1, 1), Y.roll(-1, 1), Wc.roll(-1, 1)
    Xk, Yk, Wk = X.roll(-2, 1), Y.roll(-2, 1), Wc.roll(-2, 1)
    a = Yj * Wk - Wj * Yk
    b = Wj * Xk - Xj * Wk
    c = Xj * Yk - Yj * Xk
    det = X[:, 0] * a[:, 0] + Y[:, 0] * b[:, 0] + Wc[:, 0] * c[:, 0]  # det[h_0 h_1 h_2]
    keep = det > 0 if cull_backfaces else det != 0  # front faces: CCW in NDC
    sel = torch.nonzero(keep).squeeze(1)
    if sel.numel() == 0:
        return None
    if sel.numel() < keep.numel():
        tri, a, b, c, Z, det, c0, r0, bw, bh = (_rows(t, sel) for t in (tri, a, b, c, Z, det, c0, r0, bw, bh))
    # z_ndc = sum_i e_i Z_i / det, affine in NDC (x, y); the sums written out
    # in a fixed order (the native kernel's).
    inv_det = 1 / det

    def dot(u: Tensor) -> Tensor:
        return (u[:, 0] * Z[:, 0] + u[:, 1] * Z[:, 1] + u[:, 2] * Z[:, 2]) * inv_det

    zcoef = torch.stack((dot(a), dot(b), dot(c)), dim=1)
    # Orient every edge function so that the inside is e >= 0.
    sgn = torch.sign(det)[:, None]
    a, b, c = a * sgn, b * sgn, c * sgn
    # The top-left rule of the exact path, on floats.
    owns = (a > 0) | ((a == 0) & (b > 0))
    # e > 0 is written e >= smallest subnormal so that one comparison per
    # edge serves both cases (torch.set_flush_denormal(True) would turn it
    # into e >= 0 and double-cover exact ties only).
    tiny = torch.finfo(dtype).tiny * torch.finfo(dtype).eps
    thr = torch.where(owns, torch.zeros_like(a), torch.full_like(a, tiny))
    fdata = torch.cat((a, b, c, thr, zcoef), dim=1)  # [n, 15]
    return _blocks(tri, c0, r0, bw, bh, fdata, None, 0)


def _blocks(tri: Tensor, c0: Tensor, r0: Tensor, bw: Tensor, bh: Tensor, fdata: Tensor, edata: Optional[Tensor],
            bits: int) -> _Items:
    """Work items: power-of-two pixel blocks covering each bbox, sorted and grouped by size.

    Blocks bigger than _MAX_BLOCK candidates are split into bands of rows.
    """
    device = tri.device
    item_tri = torch.arange(len(tri), device=device)
    ew, eh = _next_pow2_exp(bw), _next_pow2_exp(bh)
    big = torch.nonzero(ew + eh > _MAX_BLOCK.bit_length() - 1).squeeze(1)
    if big.numel() > 0:
        band = (_MAX_BLOCK >> ew[big]).clamp(min=1)
        nb = (bh[big] + band - 1) // band
        rep = torch.repeat_interleave(torch.arange(len(big), device=device), nb)
        k = torch.arange(len(rep), device=device) - (torch.cumsum(nb, 0) - nb)[rep]
        band_r = band[rep]
        bt = big[rep]
        small = torch.ones_like(bw, dtype=torch.bool)
        small[big] = False
        small = torch.nonzero(small).squeeze(1)
        item_tri = torch.cat((small, bt))
        c0 = torch.cat((c0[small], c0[bt]))
        bw = torch.cat((bw[small], bw[bt]))
        r0 = torch.cat((r0[small], r0[bt] + k * band_r))
        bh = torch.cat((bh[small], torch.minimum(band_r, bh[bt] - k * band_r)))
        ew = torch.cat((ew[small], ew[bt]))
        eh = torch.cat((eh[small], _next_pow2_exp(bh[len(small):])))
    key, order = torch.sort(ew * 64 + eh)
    it = _rows(item_tri, order)
    idata = _rows(torch.stack((c0, r0, bw, bh), dim=1), order)
    idata = torch.cat((_rows(tri, it)[:, None], idata), dim=1)
    fdata = _rows(fdata, it)
    if edata is not None:
        edata = _rows(edata, it)

    uniq, counts = torch.unique_consecutive(key, return_counts=True)
    uniq_l, counts_l = uniq.tolist(), counts.tolist()
    # Merge sparse bins into the next bin (at most 2x bigger per axis): a
    # few wasted candidates cost less than one more pass of kernel launches.
    groups: list[tuple[int, int, int, int]] = []
    start, pending, mw, mh = 0, 0, 0, 0
    for i, (k_, c) in enumerate(zip(uniq_l, counts_l)):
        pending += c
        mw, mh = max(mw, k_ // 64), max(mh, k_ % 64)
        nxt = uniq_l[i + 1] if i + 1 < len(uniq_l) else None
        if nxt is not None and pending < _MIN_BIN and nxt // 64 - mw <= 1 and 0 <= nxt % 64 - mh <= 1:
            continue
        groups.append((start, start + pending, mh, mw))
        start, pending, mw, mh = start + pending, 0, 0, 0
    return _Items(fdata, idata, groups, edata, bits)


def _prepare(pos: Tensor, faces: Tensor, H: int, W: int, cull_backfaces: bool) -> list[_Items]:
    """Cull triangles, split them between the exact and the float path, set up their edge functions.

    ``pos`` [B, V, 4] float64.
    """
    B, V = pos.shape[0], pos.shape[1]
    F = faces.shape[0]
    device = pos.device
    raw = pos.reshape(B * V, 4)
    # Per-vertex power-of-two scale for the float path: a positive factor on
    # a homogeneous vertex does not move it, so coverage and depth are
    # unchanged, products stay exact (shared edges agree) and huge inputs
    # cannot overflow.
    pv = pow2_normalise(raw, raw.abs().amax(-1, keepdim=True))
    X, Y, Z, Wc = pv.unbind(-1)

    # Early cull with outcodes: all corners beyond the same clip plane (valid
    # for any sign of w, since the view volume -w <= x, y, z <= w is convex).
    u8 = torch.uint8
    code = (
        (X > Wc).to(u8) | ((X < -Wc).to(u8) << 1) | ((Y > Wc).to(u8) << 2)
        | ((Y < -Wc).to(u8) << 3) | ((Z > Wc).to(u8) << 4) | ((Z < -Wc).to(u8) << 5)
    )
    vid = (torch.arange(B, device=device) * V).view(B, 1, 1) + faces  # [B, F, 3]
    vid = vid.view(B * F, 3)
    cv = _rows(code, vid)
    tri = torch.nonzero((cv[:, 0] & cv[:, 1] & cv[:, 2]) == 0).squeeze(1)
    if tri.numel() == 0:
        return []
    vid = _rows(vid, tri)
    out: list[_Items | None] = []
    S = _subpixel_bits(H, W)
    if S > 0:
        qx, qy, ok = _fixed_vertices(raw, H, W, S)
        snapped = _rows(ok, vid).all(1)
        e = torch.nonzero(snapped).squeeze(1)
        out.append(_prepare_exact(_rows(tri, e), _rows(vid, e), raw, qx, qy, H, W, S, cull_backfaces))
        f = torch.nonzero(~snapped).squeeze(1)
        tri, vid = _rows(tri, f), _rows(vid, f)
    if tri.numel() > 0:
        out.append(_prepare_float(tri, vid, pv, H, W, cull_backfaces))
    return [it for it in out if it is not None]


def _fragments(
    pos: Tensor, faces: Tensor, H: int, W: int, cull_backfaces: bool
) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """Yield chunks of covered fragments: (pixel, tri, z), each [m].

    ``pos`` [B, V, 4] float64. ``pixel`` is the flat index b * H * W + r * W
    + c, ``tri`` the global triangle index b * F + f, ``z`` the float64 NDC
    depth. A fragment is covered when the pixel centre is inside the
    triangle (fill rule applied), in front of the eye and between the near
    and far planes.
    """
    device = pos.device
    F = faces.shape[0]
    if F == 0:
        return
    f64 = torch.float64
    nan = torch.tensor([float("nan")], dtype=f64, device=device)
    xs = torch.cat((_pixel_centres(W, f64, device, flip=False), nan))
    ys = torch.cat((_pixel_centres(H, f64, device, flip=True), nan))
    for items in _prepare(pos, faces, H, W, cull_backfaces):
        exact = items.edata is not None
        if exact:
            h = 1 << (items.bits - 1)
            # Fixed-point pixel centres, one past the end for the unused
            # columns / rows of a block (masked out below).
            qxs = torch.cat(((2 * torch.arange(W, device=device) + 1 - W) * h, torch.zeros(1, dtype=torch.int64,
                                                                                       device=device)))
            qys = torch.cat(((2 * torch.arange(H, device=device) + 1 - H) * h, torch.zeros(1, dtype=torch.int64,
                                                                                       device=device)))
        for g0, g1, lh, lw in items.groups:
            Hs, Ws = 1 << lh, 1 << lw
            per = max(1, _CHUNK_CANDIDATES >> (lh + lw))
            j = torch.arange(Ws, device=device)
            i = torch.arange(Hs, device=device)
            for s0 in range(g0, g1, per):
                s1 = min(g1, s0 + per)
                fd = items.fdata[s0:s1]
                tri, c0, r0, bw, bh = items.idata[s0:s1].unbind(1)
                # Columns / rows beyond the bbox read index W / H: NaN on the
                # float path, which fails every test; masked on the exact one.
                col_ok, row_ok = j < bw[:, None], i < bh[:, None]
                col = torch.where(col_ok, c0[:, None] + j, W)  # [n, Ws]
                row = torch.where(row_ok, r0[:, None] + i, H)  # [n, Hs]
                if exact:
                    ed = items.edata[s0:s1]
                    qx, qy = _rows(qxs, col), _rows(qys, row)
                    covered = row_ok[:, :, None] & col_ok[:, None, :]
                    for k in range(3):
                        axc = ed[:, k:k + 1] * qx + ed[:, 6 + k:7 + k]
                        by = ed[:, 3 + k:4 + k] * qy
                        covered &= (axc[:, None, :] + by[:, :, None]) >= ed[:, 9 + k, None, None]
                else:
                    x, y = _rows(xs, col), _rows(ys, row)
                    covered = None
                    for k in range(3):
                        # The same operation order for every triangle, ((a x) + c) + (b y),
                        # so shared edges evaluate to exact negatives of each other.
                        axc = fd[:, k:k + 1] * x + fd[:, 6 + k:7 + k]
                        by = fd[:, 3 + k:4 + k] * y
                        e = axc[:, None, :] + by[:, :, None]
                        inside = e >= fd[:, 9 + k, None, None]
                        covered = inside if covered is None else covered.logical_and_(inside)
                idx = torch.nonzero(covered.view(-1)).squeeze(1)
                if idx.numel() == 0:
                    continue
                t = idx >> (lw + lh)
                jj = idx & (Ws - 1)
                ii = (idx >> lw) & (Hs - 1)
                xt = _rows(xs, _rows(c0, t) + jj)
                yt = _rows(ys, _rows(r0, t) + ii)
                zd = _rows(fd, t)
                if exact:  # anchored at corner 0: z0 + zx (x - x0) + zy (y - y0)
                    z = (zd[:, 0] + zd[:, 3] * (xt - zd[:, 1])) + zd[:, 4] * (yt - zd[:, 2])
                else:
                    z = (zd[:, 12] * xt + zd[:, 14]) + zd[:, 13] * yt
                b = torch.div(tri, F, rounding_mode="floor")
                base = (b * H + r0) * W + c0
                pix = _rows(base, t) + ii * W + jj
                tri = _rows(tri, t)
                ok = (z >= -1) & (z <= 1)
                if not bool(ok.all()):
                    pix, tri, z = pix[ok], tri[ok], z[ok]
                yield pix, tri, z


def _visibility(pos: Tensor, faces: Tensor, H: int, W: int, cull_backfaces: bool,
                floor: Optional[tuple[Tensor, Tensor]] = None, layers: int = 1) -> tuple[Tensor, Tensor]:
    """Z-buffer: ([B, H, W] int64 id of the nearest covering triangle or -1, [B * H * W] float64 depth).

    Depths are compared in float64, nearest wins, equal depths go to the
    lowest triangle id, whatever the processing order (deterministic on CPU
    and CUDA). ``floor`` = (depth [B * H * W] float64, id [B * H * W] int64)
    keeps only fragments behind it in (depth, id) order: the next layer of
    depth peeling. The background's depth is +inf. The native kernel serves
    CPU tensors where ``difftex.backend`` sends them there; there ``layers`` >
    1 (without a floor) returns that many nearest fragments per pixel at
    once, ids [layers, B, H, W] and the last layer's depth [B * H * W] (the
    torch path returns one layer whatever ``layers`` says).
    """
    from .. import _native as native

    pos = pos.detach()
    B = pos.shape[0]
    mod = native.kernel(pos)
    if mod is not None:  # float32 is read as it is: the kernel converts each corner exactly
        empty_z = torch.empty(0, dtype=torch.float64)
        fz, fid = floor if floor is not None else (empty_z, torch.empty(0, dtype=torch.int64))
        tri_id, zbuf = mod.raster(pos.contiguous(), faces.contiguous(), H, W, cull_backfaces,
                                  _subpixel_bits(H, W), fz.contiguous(), fid.contiguous(), layers=layers)
        if tri_id.numel() == 0 and B > 0:  # the kernel found a non-finite position or a bad index: name it
            _check_pos(pos)
            check_index("faces", faces, pos.shape[1], "number of vertices", pos.device)
            raise RuntimeError("rasterize: the native kernel rejected its input")  # not reached
        if layers > 1:
            return tri_id.view(layers, B, H, W), zbuf
        return tri_id.view(B, H, W), zbuf
    pos = pos.to(torch.float64)
    F = faces.shape[0]
    zbuf = torch.full((B * H * W,), float("inf"), dtype=torch.float64, device=pos.device)
    ibuf = torch.full((B * H * W,), _ID_EMPTY, dtype=torch.int64, device=pos.device)
    for pix, tri, z in _fragments(pos, faces, H, W, cull_backfaces):
        f = torch.remainder(tri, F)
        if floor is not None:
            fz, fid = floor[0][pix], floor[1][pix]
            behind = (z > fz) | ((z == fz) & (f > fid))
            pix, f, z = pix[behind], f[behind], z[behind]
        old = zbuf[pix]
        zbuf.scatter_reduce_(0, pix, z, "amin")
        new = zbuf[pix]
        # A nearer depth voids the pixel's id; then the fragments at the new
        # minimum (several on a tie) offer theirs, the lowest wins.
        ibuf.index_fill_(0, pix[new < old], _ID_EMPTY)
        win = z == new
        ibuf.scatter_reduce_(0, pix[win], f[win], "amin")
    tri_id = torch.where(ibuf == _ID_EMPTY, -1, ibuf)
    return tri_id.view(B, H, W), zbuf


def _coverage_count(pos: Tensor, faces: Tensor, resolution: Sequence[int], *, cull_backfaces: bool = False) -> Tensor:
    """[B, H, W] int64 number of triangles covering each pixel centre (no z test; near / far planes apply).

    A diagnostic for the fill rule (a closed mesh must give counts in {0, 2}
    without culling, {0, 1} with it); not part of the public API. Runs the
    implementation ``difftex.backend`` chooses, like :func:`rasterize`.
    """
    from .. import _native as native

    pos = _check_pos(pos)
    faces = check_index("faces", faces, pos.shape[1], "number of vertices", pos.device)
    H, W = _check_resolution(resolution)
    B = pos.shape[0]
    p64 = pos.detach().to(torch.float64)
    mod = native.kernel(p64)
    if mod is not None:
        count, _ = mod.raster(p64.contiguous(), faces.contiguous(), H, W, cull_backfaces, _subpixel_bits(H, W),
                              torch.empty(0, dtype=torch.float64), torch.empty(0, dtype=torch.int64), count=True)
        return count.view(B, H, W)
    count = torch.zeros(B * H * W, dtype=torch.int64, device=pos.device)
    with torch.no_grad():
        for pix, _, _ in _fragments(p64, faces, H, W, cull_backfaces):
            count.index_add_(0, pix, torch.ones_like(pix))
    return count.view(B, H, W)


# --------------------------------------------------------------------------
# differentiable pass


def _bary_at(v: Tensor, x: Tensor, y: Tensor, W: int, H: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Perspective-correct barycentrics, depth and pixel derivatives.

    ``v`` [N, 3, 4] clip-space corners, ``x``, ``y`` [N] NDC sample points.
    Returns bary [N, 3], depth [N], d(bary)/d(column) [N, 3],
    d(bary)/d(row) [N, 3] in ``v``'s dtype. Differentiable with respect to
    ``v``; every division is guarded so that degenerate input gives finite
    values and finite gradients (the "double where" pattern).

    Computed in float64 whatever the dtype (one rounding at the end for
    float32) in the pixel-centred frame: the corners are sheared by
    ``(X, Y, W) -> (X - x W, Y - y W, W)``, which has determinant 1 and moves
    the pixel to ``(0, 0, 1)``, so the edge function ``e_i = det[h_j, h_k, p]``
    is the 2D cross product ``X'_j Y'_k - Y'_j X'_k``: on a small or distant
    triangle a product of small numbers, where the expanded ``a x + b y + c``
    cancels large terms and lost every digit on sub-pixel triangles (issue
    40). The slopes ``a_i = de_i/dx = Y_j W_k - W_j Y_k``, ``b_i = de_i/dy =
    W_j X_k - X_j W_k`` do not depend on the pixel (from float32 corners
    both products are exact in float64: one rounding). The native kernel
    (raster.cpp ``Tri``) computes the same formula.
    """
    dtype = v.dtype
    v = v.to(torch.float64)
    x, y = x.to(torch.float64), y.to(torch.float64)
    v = pow2_normalise(v, v.detach().abs().amax(dim=(-1, -2), keepdim=True))  # invariant: homogeneous scale
    X, Y, Z, Wc = v.unbind(-1)  # [N, 3] each
    Xs = X - x[:, None] * Wc
    Ys = Y - y[:, None] * Wc
    # Corner j and k of edge i (opposite corner i), all three edges at once.
    Xj, Yj, Wj = Xs.roll(-1, dims=1), Ys.roll(-1, dims=1), Wc.roll(-1, dims=1)  # roll: cheaper than fancy indexing
    Xk, Yk, Wk = Xs.roll(-2, dims=1), Ys.roll(-2, dims=1), Wc.roll(-2, dims=1)
    e = Xj * Yk - Yj * Xk  # [N, 3]
    Xuj, Yuj, Xuk, Yuk = X.roll(-1, dims=1), Y.roll(-1, dims=1), X.roll(-2, dims=1), Y.roll(-2, dims=1)
    a = Yuj * Wk - Wj * Yuk
    b = Wj * Xuk - Xuj * Wk
    s = e.sum(-1)
    ok = s != 0
    s_safe = torch.where(ok, s, torch.ones_like(s))
    bary = e / s_safe[:, None]
    # d(bary_i)/dx = (a_i - bary_i * sum(a)) / sum(e), same for y with b.
    dx = (a - bary * a.sum(-1, keepdim=True)) / s_safe[:, None]
    dy = (b - bary * b.sum(-1, keepdim=True)) / s_safe[:, None]
    zn = (e * Z).sum(-1)
    wn = (e * Wc).sum(-1)
    okw = ok & (wn != 0)
    depth = zn / torch.where(okw, wn, torch.ones_like(wn))
    zero3 = torch.zeros_like(bary)
    bary = torch.where(ok[:, None], bary, zero3)
    # NDC -> pixel units: x grows 2/W per column, y falls 2/H per row.
    dx = torch.where(ok[:, None], dx, zero3) * (2.0 / W)
    dy = torch.where(ok[:, None], dy, zero3) * (-2.0 / H)
    depth = torch.where(okw, depth, torch.zeros_like(depth))
    return bary.to(dtype), depth.to(dtype), dx.to(dtype), dy.to(dtype)


def _pixels(pos: Tensor, faces: Tensor, tri_id: Tensor, idx: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The covered pixels ``idx`` (flat over tri_id [B, H, W]): clip-space corners [N, 3, 4] of their triangles and
    NDC centres x, y [N]."""
    B, H, W = tri_id.shape
    f = tri_id.reshape(-1).index_select(0, idx)
    bi = torch.div(idx, H * W, rounding_mode="floor")
    rc = idx - bi * (H * W)
    r = torch.div(rc, W, rounding_mode="floor")
    col = rc - r * W
    # float64 centres whatever the dtype: _bary_at works in float64 (the
    # kernel likewise), and a float32 centre is off by up to 6e-8 NDC.
    xs = _pixel_centres(W, torch.float64, pos.device, flip=False)
    ys = _pixel_centres(H, torch.float64, pos.device, flip=True)
    # One flat gather (much faster than 2-index advanced indexing on CPU).
    vid = (bi * pos.shape[1])[:, None] + faces.index_select(0, f)
    v = pos.reshape(-1, 4).index_select(0, vid.reshape(-1)).view(-1, 3, 4)
    return v, xs[col], ys[r]


def _gather_rows(g: Optional[Tensor], idx: Tensor, width: int) -> Optional[Tensor]:
    return None if g is None else g.reshape(-1, width).index_select(0, idx)


class _NativeFragments(torch.autograd.Function):
    """The differentiable pass in one native call (``raster_fragments``): dense outputs and the compact form.

    Outputs (idx, bary_c, dx_c, dy_c, bary, depth, bary_dx, bary_dy), or with
    ``packed`` nvdiffrast's (idx, rast, db) (rast's depth and id take no
    gradient); without ``derivatives`` the derivative outputs are empty [0]
    tensors that nothing reads. The first-order backward is the kernel's hand-written adjoint
    of the same formula, reading the gradients where autograd leaves them;
    under create_graph the dense gradients are gathered at the covered pixels
    and the torch formula :func:`_bary_at` is differentiated there from
    ``pos`` itself (so double backward works).
    """

    @staticmethod
    def forward(ctx, pos: Tensor, faces: Tensor, tri_id: Tensor, mod, packed: bool, offset: int,
                derivatives: bool = True):
        out = mod.raster_fragments(pos.detach(), faces, tri_id, packed=packed, offset=offset,
                                   derivatives=derivatives)
        ctx.save_for_backward(pos, faces, tri_id, out[0])
        ctx.packed, ctx.mod = packed, mod
        ctx.mark_non_differentiable(out[0])
        ctx.set_materialize_grads(False)
        return tuple(out)

    @staticmethod
    def backward(ctx, _gidx: None, *grads: Optional[Tensor]):
        pos, faces, tri_id, idx = ctx.saved_tensors
        return (_fragments_grad(ctx.mod, ctx.packed, pos, faces, tri_id, idx, grads),) + (None,) * 6


def _fragments_grad(mod, packed: bool, pos: Tensor, faces: Tensor, tri_id: Tensor, idx: Tensor,
                    grads: Sequence[Optional[Tensor]]) -> Optional[Tensor]:
    """The gradient of pos from the output gradients of one layer's fragments (:class:`_NativeFragments`' outputs
    after idx), or None."""
    # The empty derivative outputs of a call without derivatives take no gradient.
    grads = tuple(None if g is None or g.numel() == 0 else g for g in grads)
    if all(g is None for g in grads):
        return None
    if not (torch.is_grad_enabled() and pos.requires_grad):
        # First order: the kernel's hand-written adjoint of the same
        # formula, reading the gradients where they are.
        empty = pos.new_empty(0)
        return mod.raster_fragments_backward(pos.detach(), faces, tri_id, idx,
                                             [empty if g is None else g for g in grads], packed)
    # Under create_graph: the torch formula differentiated from pos itself.
    B, H, W = tri_id.shape
    if packed:
        g_rast, g_db = (_gather_rows(g, idx, 4) for g in grads)
        zero = idx.new_zeros(idx.shape, dtype=pos.dtype)
        gb = None if g_rast is None else torch.stack([g_rast[:, 0], g_rast[:, 1], zero], 1)
        gdx = None if g_db is None else torch.stack([g_db[:, 0], g_db[:, 2], zero], 1)
        gdy = None if g_db is None else torch.stack([g_db[:, 1], g_db[:, 3], zero], 1)
        gz = None
    else:
        gbc, gdxc, gdyc, gb_d, gz_d, gdx_d, gdy_d = grads

        def both(compact: Optional[Tensor], dense: Optional[Tensor]) -> Optional[Tensor]:
            dense = _gather_rows(dense, idx, 3)
            return dense if compact is None else (compact if dense is None else compact + dense)

        gb, gdx, gdy = both(gbc, gb_d), both(gdxc, gdx_d), both(gdyc, gdy_d)
        gz = _gather_rows(gz_d, idx, 1)
        gz = None if gz is None else gz[:, 0]
    pairs = [(k, g) for k, g in enumerate((gb, gz, gdx, gdy)) if g is not None]
    if not pairs:
        return None
    with torch.enable_grad():
        outs = _bary_at(*_pixels(pos, faces, tri_id, idx), W, H)
        (g,) = torch.autograd.grad([outs[k] for k, _ in pairs], (pos,), [g for _, g in pairs], create_graph=True)
    return g


class _Rejected(Exception):
    """The native kernel found a non-finite position or an index out of range (the caller's checks name it)."""


class _NativeRaster(torch.autograd.Function):
    """Visibility and the differentiable pass of ``layers`` layers in one native call (``raster_fused``: each band
    of rows gets its fragments right after its z-buffer, while its pixels and triangles are in cache).

    Outputs each layer's tri_id [B, H, W], then per layer :class:`_NativeFragments`' unpacked outputs; the same
    values as the separate passes, and each layer's backward as theirs (tri_id and idx take no gradient).
    """

    @staticmethod
    def forward(ctx, pos: Tensor, faces: Tensor, spec: tuple[int, int, bool, int, int], mod, derivatives: bool):
        H, W, cull, bits, layers = spec
        out = mod.raster_fused(pos.detach(), faces, H, W, cull, bits, derivatives=derivatives, layers=layers)
        if len(out) == 2:
            raise _Rejected()
        tri_id = [t.view(pos.shape[0], H, W) for t in out[:layers]]
        frags = out[layers + 1:]
        idxs = frags[0::8]
        ctx.save_for_backward(pos, faces, *tri_id, *idxs)
        ctx.mod, ctx.layers = mod, layers
        ctx.mark_non_differentiable(*tri_id, *idxs)
        ctx.set_materialize_grads(False)
        return (*tri_id, *frags)

    @staticmethod
    def backward(ctx, *grads: Optional[Tensor]):
        pos, faces, *saved = ctx.saved_tensors
        tri_id, idxs, grads = saved[:ctx.layers], saved[ctx.layers:], grads[ctx.layers:]
        total = None
        for k, idx in enumerate(idxs):
            g = _fragments_grad(ctx.mod, False, pos, faces, tri_id[k], idx, grads[8 * k + 1:8 * k + 8])
            if g is not None:
                total = g if total is None else total + g
        return total, None, None, None, None


def _rasterize_fused(pos: Tensor, faces: Tensor, resolution: Sequence[int], cull_backfaces: bool,
                     derivatives: bool, mod, layers: int = 1) -> list[Fragments]:
    """:func:`rasterize` (one layer) or :func:`depth_peel` on the native kernel in one call (the checks as
    :func:`visible_layers` makes them)."""
    pos = _check_pos(pos, finite=False)
    faces = check_index("faces", faces, pos.shape[1], "number of vertices", pos.device, check_range=False)
    H, W = _check_resolution(resolution)
    _check_memory(pos.shape[0], H, W, pos.dtype)
    try:
        out = _NativeRaster.apply(pos, faces.contiguous(), (H, W, cull_backfaces, _subpixel_bits(H, W), layers),
                                  mod, derivatives)
    except _Rejected:
        _check_pos(pos)
        check_index("faces", faces, pos.shape[1], "number of vertices", pos.device)
        raise RuntimeError("rasterize: the native kernel rejected its input") from None  # not reached
    tri_id, out = out[:layers], out[layers:]
    result = []
    for k in range(layers):
        idx, bary_c, dx_c, dy_c, bary, depth, bary_dx, bary_dy = out[8 * k:8 * k + 8]
        if not derivatives:
            dx_c = dy_c = bary_dx = bary_dy = None
        frags = Fragments(tri_id=tri_id[k], bary=bary, depth=depth, bary_dx=bary_dx, bary_dy=bary_dy)
        object.__setattr__(frags, "_compact", (idx, bary_c, dx_c, dy_c))
        result.append(frags)
    return result


def rasterize(
    pos: Tensor,
    faces: Tensor,
    resolution: Sequence[int],
    *,
    cull_backfaces: bool = False,
    derivatives: bool = True,
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
        derivatives: compute the screen-space derivatives bary_dx, bary_dy
            (default). False leaves them None and skips their work and
            memory (a quarter of the pass's output bytes each): for renders
            that interpolate no minified texture coordinates (nvdiffrast
            computes them only on request too).

    Returns:
        :class:`Fragments` with tri_id [B, H, W] int64 (-1 = background),
        bary [B, H, W, 3] perspective-correct, depth [B, H, W] NDC z and the
        analytic screen-space derivatives bary_dx, bary_dy [B, H, W, 3] per
        pixel column / row (None with ``derivatives=False``).

    Visibility: the nearest fragment (smallest NDC z, compared in float64
    whatever the input dtype) wins, equal depths go to the lowest triangle
    id. Coverage uses corners snapped to 2**-16 pixel and exact integer edge
    functions with a top-left rule: a closed mesh in front of the camera
    covers each pixel centre exactly once per surface layer, also where
    edges meet at the centre (see the module notes for triangles reaching
    behind the eye, which take a float64 path). Triangles crossing w = 0 or
    the near / far planes are handled exactly (2D homogeneous rasterization
    plus a per-pixel depth range test); triangles wholly outside the view
    volume are culled early. On CPU tensors the native kernel computes the
    same ids where ``difftex.backend`` chooses it (:func:`depth_peel` peels
    further layers).

    ``bary``, ``depth``, ``bary_dx`` and ``bary_dy`` are computed in float64
    whatever the dtype, from edge functions of the corners sheared to a
    pixel-centred frame (no cancellation on small or distant triangles), so
    float32 values are the exact ones of the given corners rounded once
    (|bary - exact| <= 6e-8 for barycentrics within [0, 1]). They are
    differentiable with respect to ``pos`` (the perspective-correct formula);
    which triangle is visible is not. Their gradients scale as 1 / |corner|: where every corner
    of a visible triangle is subnormal (below 1.2e-38 in float32), the
    values are still exact but the position gradients overflow the dtype
    (inf, or NaN where two overflows meet). Raises TypeError on bad dtypes, ValueError naming the
    argument on bad shapes, out-of-range faces or non-finite positions, and
    ValueError naming ``resolution`` and the batch where the per-pixel
    buffers would exceed :data:`MAX_BYTES` (16 GiB by default).
    """
    if not isinstance(derivatives, bool):
        raise TypeError(f"rasterize: derivatives must be a bool, got {type(derivatives).__name__}")
    from .. import _native as native

    # One layer on the native kernel: visibility and fragments in one pass, no depth buffer kept (the floor
    # of depth peeling's next layer, which rasterize does not peel).
    mod = native.kernel(pos) if isinstance(pos, Tensor) else None
    if mod is not None:
        return _rasterize_fused(pos, faces, resolution, cull_backfaces, derivatives, mod)[0]
    return next(visible_layers(pos, faces, resolution, cull_backfaces, functools.partial(
        fragments_of, derivatives=derivatives)))


def depth_peel(
    pos: Tensor,
    faces: Tensor,
    resolution: Sequence[int],
    layers: int,
    *,
    cull_backfaces: bool = False,
    derivatives: bool = True,
) -> list[Fragments]:
    """Depth peeling: the first ``layers`` surfaces along every pixel's ray, nearest first.

    Layer 0 is :func:`rasterize`'s output; layer k holds, per pixel, the
    (k + 1)-th covering fragment in (NDC depth, triangle id) order, so
    coplanar fragments come one per layer, lowest id first, and no fragment
    appears twice. Pixels with fewer than k + 1 fragments are background
    (``tri_id = -1``) in layer k. Each pass keeps the previous layer's float64
    depth and id per pixel as a floor (the torch path; the native kernel keeps
    each pixel's ``layers`` nearest fragments in one pass, a k-buffer, with
    the same result, and every layer's fragments in that pass too); every layer
    costs about one rasterization, less with the kernel.

    Args:
        pos, faces, resolution, cull_backfaces, derivatives: as for
            :func:`rasterize` (``derivatives=False``: every layer's bary_dx
            and bary_dy are None and not computed).
        layers: number of layers (>= 1).

    Returns:
        A list of ``layers`` :class:`Fragments`, nearest first; ``bary``,
        ``depth``, ``bary_dx`` and ``bary_dy`` of each are differentiable with
        respect to ``pos`` as in :func:`rasterize`.

    Raises what :func:`rasterize` raises, and TypeError / ValueError naming
    ``layers`` unless it is an int >= 1.
    """
    if isinstance(layers, bool) or not isinstance(layers, int):
        raise TypeError(f"depth_peel: layers must be an int, got {type(layers).__name__}")
    if layers < 1:
        raise ValueError(f"depth_peel: layers must be >= 1, got {layers}")
    if not isinstance(derivatives, bool):
        raise TypeError(f"depth_peel: derivatives must be a bool, got {type(derivatives).__name__}")
    from .. import _native as native

    # On the native kernel: the k-buffer and every layer's fragments in one pass.
    mod = native.kernel(pos) if isinstance(pos, Tensor) else None
    if mod is not None:
        return _rasterize_fused(pos, faces, resolution, cull_backfaces, derivatives, mod, layers)
    return list(itertools.islice(visible_layers(pos, faces, resolution, cull_backfaces, functools.partial(
        fragments_of, derivatives=derivatives), at_once=layers), layers))


def peel(pos: Tensor, faces: Tensor, resolution: Sequence[int], *, cull_backfaces: bool = False,
         derivatives: bool = True) -> Iterator[Fragments]:
    """Depth layers one at a time, nearest first, without end: :func:`depth_peel` as a lazy iterator.

    Each ``next()`` costs about one rasterization (the previous layer's
    float64 depth and id per pixel are kept as the floor); past the last
    surface every layer is background. Arguments, gradients and errors as
    :func:`depth_peel` (the errors are raised at the first ``next()``, but a
    ``derivatives`` that is not a bool at once).
    """
    if not isinstance(derivatives, bool):
        raise TypeError(f"peel: derivatives must be a bool, got {type(derivatives).__name__}")
    return visible_layers(pos, faces, resolution, cull_backfaces, functools.partial(
        fragments_of, derivatives=derivatives))


def visible_layers(pos: Tensor, faces: Tensor, resolution: Sequence[int], cull_backfaces: bool,
                   emit: Callable[[Tensor, Tensor, Tensor], _T], at_once: int = 1) -> Iterator[_T]:
    """Depth layers nearest first, without end, each as ``emit(pos, faces, tri_id)``: the building block of
    :func:`rasterize`, :func:`depth_peel`, :func:`peel` and ``difftex.nvdiffrast``.

    Args:
        pos, faces, resolution, cull_backfaces: as for :func:`rasterize`
            (checked here, at the first ``next()``).
        emit: called with the checked ``pos`` [B, V, 4], ``faces`` and one
            layer's visible triangle ids [B, H, W] (-1 background), e.g.
            :func:`fragments_of`.
        at_once: the first visibility pass finds this many layers where the
            native kernel serves (its k-buffer); later layers take one pass
            each, behind the previous layer as a floor.

    Yields what ``emit`` returns. The ids are not differentiable; ``emit``
    decides what is. Raises what :func:`rasterize` raises.
    """
    from .. import _native as native

    # The native kernel tests finiteness and the index range in passes over
    # every vertex and triangle it makes anyway (on 1.3M triangles the
    # separate passes here cost about a tenth of rasterize); elsewhere here.
    on_kernel = isinstance(pos, Tensor) and native.kernel(pos) is not None
    pos = _check_pos(pos, finite=not on_kernel)
    faces = check_index("faces", faces, pos.shape[1], "number of vertices", pos.device, check_range=not on_kernel)
    H, W = _check_resolution(resolution)
    _check_memory(pos.shape[0], H, W, pos.dtype)
    floor = None
    while True:
        with torch.no_grad():
            tri_id, zbuf = _visibility(pos, faces, H, W, cull_backfaces, floor, at_once if floor is None else 1)
        if tri_id.dim() == 3:
            tri_id = tri_id[None]
        for k in range(tri_id.shape[0]):
            yield emit(pos, faces, tri_id[k])
        # A background pixel's floor depth is +inf: no finite depth passes it,
        # whatever its id (-1).
        floor = (zbuf, tri_id[-1].reshape(-1))


def fragments_of(pos: Tensor, faces: Tensor, tri_id: Tensor, derivatives: bool = True) -> Fragments:
    """The differentiable pass: :class:`Fragments` of the triangles ``tri_id`` [B, H, W] names (-1 background).

    ``pos`` [B, V, 4] and ``faces`` [F, 3] as checked by :func:`visible_layers`
    (no checks here). bary, depth, bary_dx and bary_dy are differentiable
    with respect to ``pos`` (native forward and first-order backward on the
    CPU, the torch formula elsewhere and for double backward); without
    ``derivatives`` bary_dx and bary_dy are None and not computed.
    """
    from .. import _native as native

    mod = native.kernel(pos)
    if mod is not None:
        idx, bary_c, dx_c, dy_c, bary, depth, bary_dx, bary_dy = _NativeFragments.apply(
            pos, faces, tri_id, mod, False, 0, derivatives)
    else:
        B, H, W = tri_id.shape
        idx = torch.nonzero(tri_id.reshape(-1) >= 0).squeeze(1)
        bary_c, depth_c, dx_c, dy_c = _bary_at(*_pixels(pos, faces, tri_id, idx), W, H)

        # Separate dense outputs (not views of one packed tensor): the
        # backward of a view would allocate a zero gradient of the whole
        # packed buffer.
        def dense(vals: Tensor) -> Tensor:
            k = vals.shape[1:]
            out = vals.new_zeros((B * H * W, *k))
            out.index_put_((idx,), vals)  # in place on fresh zeros: no copy
            return out.view(B, H, W, *k)

        bary, depth = dense(bary_c), dense(depth_c)
        bary_dx, bary_dy = (dense(dx_c), dense(dy_c)) if derivatives else (None, None)
    if not derivatives:
        dx_c = dy_c = bary_dx = bary_dy = None
    frags = Fragments(tri_id=tri_id, bary=bary, depth=depth, bary_dx=bary_dx, bary_dy=bary_dy)
    # Covered pixels in compact form for interpolate(): gathering from the
    # dense tensors would cost a dense zero gradient per tensor in backward.
    object.__setattr__(frags, "_compact", (idx, bary_c, dx_c, dy_c))
    return frags


def packed_fragments(pos: Tensor, faces: Tensor, tri_id: Tensor, offset: int,
                     derivatives: bool = True) -> Optional[tuple[Tensor, Tensor, Tensor]]:
    """nvdiffrast's (rast, rast_db) of ``tri_id`` [B, H, W] straight from the native kernel (difftex.nvdiffrast's
    fast path), or None where the kernel does not serve ``pos``.

    rast [B, H, W, 4] = (b0, b1, depth, id + 1 + offset), rast_db [B, H, W, 4]
    = (db0/dx, db0/dy, db1/dx, db1/dy) per column / row, zeros on background;
    the third tensor is the flat index [N] of the covered pixels.
    b0, b1 and rast_db are differentiable with respect to ``pos``; the depth
    and id columns are not. Without ``derivatives`` rast_db is an empty [0]
    tensor (not computed).
    """
    from .. import _native as native

    mod = native.kernel(pos)
    if mod is None:
        return None
    idx, rast, db = _NativeFragments.apply(pos, faces, tri_id, mod, True, offset, derivatives)
    return rast, db, idx

"""Analytic antialiasing of silhouette edges, differentiable with respect to vertex positions.

Written from the description in Laine et al. 2020, "Modular Primitives for
High-Performance Differentiable Rendering" (the antialiasing section). A
rasterized image is piecewise constant in the vertex positions: moving a
silhouette changes which pixels it covers, a step with no gradient. This
op approximates the pixel-box coverage of silhouette edges and blends the
colours on both sides accordingly, which makes the image continuous in the
positions of the edge's vertices.

For every pair of neighbouring pixels A, B (left / right, or top /
bottom) with different triangle ids, the nearer of the two triangles
(background is farthest) is the candidate occluder; if one of its
silhouette edges (or, beyond the paper, a silhouette edge of a face in
its rings of edge neighbours: see below) crosses the segment between the
two pixel centres at ``t`` (0 at A's centre, 1 at B's), the boundary
between the surfaces lies there instead of at the pixels' common side
(t = 0.5), and the pixel on whose half the crossing lies takes the other
pixel's colour with weight ``|t - 0.5|``:

    t < 0.5:  A += (0.5 - t) (B - A)        t > 0.5:  B += (t - 0.5) (A - B)

For a straight edge that enters and leaves the pixel box through its top
and bottom sides (left and right sides for a flat edge) this is exactly the
box-filtered coverage of that pixel; near the edge's ends and where it
cuts a corner of the box it is an approximation. It is continuous as the
edge passes a pixel centre (weight 0.5 on either side). ``t`` is a
rational function of the edge's clip-space endpoints, which is where the
gradient to the positions comes from.

Each edge is handled by one direction only, by its slope in pixels: edges
steeper than 45 degrees by left / right pairs, flatter ones by top / bottom
pairs, so that no edge blends twice. A silhouette edge is a mesh edge with
one triangle (a boundary) or two whose clip-space orientations differ (one
front-, one back-facing), or more than two; edges between two triangles
facing the same way are interior and are not blended (their colours meet
without a depth discontinuity). Triangles' corners at w <= 0 give no
blend on their edges.

Small triangles: near a smooth silhouette the faces turn edge-on and
project to slivers that rarely hold a pixel centre, so the silhouette edge
that crosses a pixel segment often belongs to a sliver next to the pixel's
triangle. Testing the occluder's own edges only (the paper's test) then
finds few edges: on spot at 128x128 (triangles 2-3 pixels wide) the mean
error of edge pixels against 8x8 supersampled coverage goes 0.233 ->
0.183. Testing also the faces within two edge-neighbour rings (the
default ``rings=2``: about 10 faces) gives 0.093 (three rings: 0.065 at 2x
the cost); on a cube 0.242 ->
0.013. Pairs whose rings hold no silhouette edge are skipped first. Cost on
spot at 512x512, forward and backward, one thread: 46 / 56 / 115 / 237 ms
for rings 0 / 1 / 2 / 3 (rasterize: 104 ms), measured on a loaded machine.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .._checks import check_float, check_index, describe
from .raster import Fragments, pow2_normalise

__all__ = ["antialias", "silhouette_edges", "RINGS"]

#: Default ``rings`` of :func:`antialias`: the pixel's triangle and two rings
#: of edge neighbours (10 distinct faces, 30 edges per pixel pair on a mesh
#: of valence 6).
RINGS = 2


def _edge_partner(faces: Tensor, num_vertices: int) -> Tensor:
    """[F, 3] flat index f' * 3 + k' of the other corner-slot sharing edge k of face f, -1 if none or many.

    Edge k of a face joins its corners k + 1 and k + 2 (the edge opposite
    corner k). Only edges shared by exactly two faces get a partner.
    """
    F = faces.shape[0]
    a, b = faces.roll(-1, 1), faces.roll(-2, 1)
    key = (torch.minimum(a, b) * num_vertices + torch.maximum(a, b)).reshape(-1)
    sk, order = torch.sort(key)
    _, inverse, counts = torch.unique_consecutive(sk, return_inverse=True, return_counts=True)
    start = (torch.cumsum(counts, 0) - counts)[inverse]
    pos = torch.arange(3 * F, device=faces.device)
    partner_sorted = torch.where(pos == start, pos + 1, pos - 1).clamp(0, max(3 * F - 1, 0))
    partner_sorted = torch.where(counts[inverse] == 2, order[partner_sorted], torch.full_like(pos, -1))
    partner = torch.empty_like(partner_sorted)
    partner[order] = partner_sorted
    return partner.view(F, 3)


def _det_sign(v: Tensor) -> Tensor:
    """Sign of det[h_0 h_1 h_2] with h = (X, Y, W) of corners ``v`` [..., 3, 4]: the facing in clip space."""
    h = v[..., [0, 1, 3]]
    return torch.sign(torch.linalg.det(h))


def silhouette_edges(pos: Tensor, faces: Tensor) -> Tensor:
    """Which triangle edges are silhouette edges in each view.

    Args:
        pos: [B, V, 4] or [V, 4] clip-space positions.
        faces: [F, 3] integer vertex indices.

    Returns:
        [B, F, 3] bool: edge k of face f (the edge opposite corner k,
        joining corners k + 1 and k + 2) lies on one triangle only, on more
        than two, or on two that face opposite ways (or one degenerate) in
        clip space. Not differentiable (a discrete property). Raises what
        :func:`antialias` raises on bad ``pos`` / ``faces``.
    """
    pos = _check_pos(pos)
    faces = check_index("faces", faces, pos.shape[1], "number of vertices", pos.device)
    return _silhouettes(pos.detach(), faces)


def _silhouettes(pos: Tensor, faces: Tensor) -> Tensor:
    return _topology(pos, faces)[0]


def _topology(pos: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """([B, F, 3] silhouette flags, [F, 3] the face across each edge or -1)."""
    F = faces.shape[0]
    if F == 0:
        empty = torch.zeros((0, 3), dtype=torch.int64, device=pos.device)
        return torch.zeros((pos.shape[0], 0, 3), dtype=torch.bool, device=pos.device), empty
    partner = _edge_partner(faces, pos.shape[1])
    v = pos[:, faces].to(torch.float64)  # the sign of a det: float64 keeps near-degenerate faces honest
    facing = _det_sign(v)  # [B, F]
    pf = torch.div(partner.clamp_min(0), 3, rounding_mode="floor")
    other = facing[:, pf]  # [B, F, 3]
    sil = (partner < 0)[None] | (other != facing[:, :, None])
    return sil, torch.where(partner < 0, -1, pf)


def _unique_rows(ring: Tensor) -> Tensor:
    """Each row's distinct entries >= 0 in first-seen order, padded with -1, as narrow as the widest row."""
    R = ring.shape[1]
    earlier = torch.ones(R, R, dtype=torch.bool, device=ring.device).triu(1)  # [i, j]: i < j
    dup = ((ring[:, :, None] == ring[:, None, :]) & earlier).any(1)
    ring = ring.masked_fill(dup, -1)
    order = torch.argsort((ring < 0).to(torch.int8), dim=1, stable=True)
    ring = ring.gather(1, order)
    width = max(1, int((ring >= 0).sum(1).max())) if ring.shape[0] > 0 else 1
    return ring[:, :width]


def _check_pos(pos: object) -> Tensor:
    check_float("pos", pos, (2, 3), last=4, shape_doc="[B, V, 4] or [V, 4]")
    if pos.dim() == 2:
        pos = pos.unsqueeze(0)
    if not bool(torch.isfinite(pos.detach()).all()):
        raise ValueError(f"pos: expected finite clip-space positions, got NaN or inf ({describe(pos)})")
    return pos


def _pairs(color: Tensor, frags: Fragments, pos: Tensor, faces: Tensor, sil: Tensor, ring: Tensor,
           near: Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """Colour deltas of one direction of pixel pairs: (flat pixel index [2N], delta [2N, C])."""
    B, C, H, W = color.shape
    tri, depth = frags.tri_id, frags.depth
    n_a = [slice(None)] * 3
    n_b = [slice(None)] * 3
    n_a[dim], n_b[dim] = slice(None, -1), slice(1, None)
    ida, idb = tri[tuple(n_a)], tri[tuple(n_b)]
    diff = ida != idb
    pix = torch.arange(B * H * W, device=color.device).view(B, H, W)
    step = W if dim == 1 else 1  # flat offset from A to B
    flat_a = pix[tuple(n_a)][diff]
    if flat_a.numel() == 0:
        return flat_a, color.new_zeros((0, C))
    inf = torch.tensor(float("inf"), dtype=depth.dtype, device=depth.device)
    za = torch.where(ida >= 0, depth[tuple(n_a)], inf)[diff]
    zb = torch.where(idb >= 0, depth[tuple(n_b)], inf)[diff]
    fa, fb = ida[diff], idb[diff]
    a_front = za <= zb
    f = torch.where(a_front, fa, fb)  # >= 0: the two ids differ, so not both are background
    b = torch.div(flat_a, H * W, rounding_mode="floor")
    # Most pairs with different ids lie inside a surface, far from any
    # silhouette: drop them before the per-edge work.
    keep = torch.nonzero(near[b if near.shape[0] > 1 else torch.zeros_like(b), f]).squeeze(1)
    flat_a, f, b = flat_a[keep], f[keep], b[keep]
    rc = flat_a - b * (H * W)
    r = torch.div(rc, W, rounding_mode="floor")
    c = rc - r * W
    dtype = pos.dtype
    # NDC of A's and B's centres (DESIGN.md: row 0 is NDC y = +1).
    xa = (c.to(dtype) + 0.5) * (2.0 / W) - 1
    ya = 1 - (r.to(dtype) + 0.5) * (2.0 / H)
    xb = xa + (2.0 / W if dim == 2 else 0.0)
    yb = ya - (2.0 / H if dim == 1 else 0.0)

    pb = b if pos.shape[0] > 1 else torch.zeros_like(b)
    cand = ring[f]  # [N, R], -1 = none
    has = cand >= 0
    cand = cand.clamp_min(0)
    n_c = cand.shape[1]
    vid = pb[:, None, None] * pos.shape[1] + faces[cand]  # [N, 4, 3]
    v = pos.reshape(-1, 4).index_select(0, vid.reshape(-1)).view(-1, 3, 4)  # [N * 4, 3, 4]
    # A positive factor per triangle leaves every homogeneous line and
    # crossing unchanged and keeps the products below from overflowing.
    v = pow2_normalise(v, v.detach().abs().amax(dim=(1, 2), keepdim=True))
    h1, h2 = v.roll(-1, 1), v.roll(-2, 1)  # edge k joins corners k + 1, k + 2
    h1, h2 = h1.reshape(-1, n_c * 3, 4), h2.reshape(-1, n_c * 3, 4)  # [N, 12, 4]
    X1, Y1, W1 = h1[..., 0], h1[..., 1], h1[..., 3]
    X2, Y2, W2 = h2[..., 0], h2[..., 1], h2[..., 3]
    # The edge's line l = h1 x h2 in 2D homogeneous coordinates; l . (x, y, 1)
    # is linear along the pixel segment, so its root gives the crossing.
    lx, ly, lw = Y1 * W2 - W1 * Y2, W1 * X2 - X1 * W2, X1 * Y2 - Y1 * X2
    ea = lx * xa[:, None] + ly * ya[:, None] + lw
    eb = lx * xb[:, None] + ly * yb[:, None] + lw
    with torch.no_grad():
        cross = (ea > 0) != (eb > 0)
        front = (W1 > 0) & (W2 > 0)
        W1s, W2s = torch.where(front, W1, 1), torch.where(front, W2, 1)
        # The crossing lies between the edge's ends: they are on opposite
        # sides of the line through the two pixel centres.
        if dim == 2:
            s1, s2 = Y1 / W1s - ya[:, None], Y2 / W2s - ya[:, None]
        else:
            s1, s2 = X1 / W1s - xa[:, None], X2 / W2s - xa[:, None]
        within = (s1 > 0) != (s2 > 0)
        dxp = (X2 / W2s - X1 / W1s) * (W / 2)
        dyp = (Y2 / W2s - Y1 / W1s) * (H / 2)
        steep = dyp.abs() > dxp.abs()
        mine = steep if dim == 2 else ~steep
        pf = pb if sil.shape[0] > 1 else torch.zeros_like(pb)
        is_sil = (sil[pf[:, None], cand] & has[..., None]).reshape(-1, n_c * 3)
        ok = cross & front & within & mine & is_sil
        any_ok = ok.any(1)
        k = torch.argmax(ok.to(torch.int32), dim=1)  # the first edge that qualifies (argmax returns the first)
    sel = torch.nonzero(any_ok).squeeze(1)
    if sel.numel() == 0:
        return flat_a[:0], color.new_zeros((0, C))
    k = k[sel]
    ea = ea[sel].gather(1, k[:, None]).squeeze(1)
    eb = eb[sel].gather(1, k[:, None]).squeeze(1)
    t = ea / (ea - eb)  # ea, eb differ in sign (or one is 0): the difference is not 0
    flat_a = flat_a[sel]
    flat_b = flat_a + step
    rows = color.permute(0, 2, 3, 1).reshape(-1, C)
    out_dtype = torch.promote_types(color.dtype, dtype)
    ca = rows.index_select(0, flat_a).to(out_dtype)
    cb = rows.index_select(0, flat_b).to(out_dtype)
    t = t.to(out_dtype)[:, None]
    zero = torch.zeros_like(t)
    near_a = t < 0.5
    da = torch.where(near_a, 0.5 - t, zero) * (cb - ca)
    db = torch.where(near_a, zero, t - 0.5) * (ca - cb)
    return torch.cat((flat_a, flat_b)), torch.cat((da, db))


def antialias(color: Tensor, fragments: Fragments, pos: Tensor, faces: Tensor, *, rings: int = RINGS) -> Tensor:
    """Blend colours across silhouette edges by their coverage, with gradients to the vertex positions.

    Args:
        color: [B, C, H, W] shaded image of the fragments (background
            already filled in: it is blended like any colour).
        fragments: :class:`difftex.Fragments` of ``pos`` / ``faces`` from
            :func:`difftex.rasterize` (ids and depths are read; its batch
            and resolution must match ``color``).
        pos: [B, V, 4] or [V, 4] clip-space positions given to rasterize
            (B = 1 serves every image).
        faces: [F, 3] the faces given to rasterize.
        rings: how many rings of edge neighbours of the nearer pixel's
            triangle have their silhouette edges tested too; 0 is the
            paper's test (the triangle's own edges). More rings find more
            silhouettes of finely tessellated meshes, at up to 3x the edge tests
            per ring (see the module docs for measurements).

    Returns:
        [B, C, H, W], ``color`` with every silhouette edge's coverage
        blended into the two pixels it separates (see the module docs), in
        the promoted dtype of ``color`` and ``pos``. Pixels away from
        silhouettes are ``color`` unchanged.

    Differentiable with respect to ``color`` and ``pos`` (through the
    position where each edge crosses the segment between two pixel
    centres); ids and depths of ``fragments`` are not. Degenerate edges
    (zero length, through the eye, w <= 0) blend nothing and give finite
    gradients. Raises TypeError on non-float ``color`` / ``pos`` or a
    ``fragments`` of another type, ValueError naming the argument on bad
    shapes, batch or resolution mismatches, non-finite ``pos``,
    out-of-range ``faces`` and a negative ``rings``.
    """
    check_float("color", color, 4, shape_doc="[B, C, H, W]")
    if isinstance(rings, bool) or not isinstance(rings, int) or rings < 0:
        raise ValueError(f"rings: expected an int >= 0, got {rings!r}")
    if not isinstance(fragments, Fragments):
        raise TypeError(f"fragments: expected a difftex.Fragments, got {type(fragments).__name__}")
    pos = _check_pos(pos)
    faces = check_index("faces", faces, pos.shape[1], "number of vertices", pos.device)
    B, C, H, W = color.shape
    if tuple(fragments.tri_id.shape) != (B, H, W):
        raise ValueError(f"fragments: expected tri_id of shape {(B, H, W)} to match color ({describe(color)}), "
                         f"got {tuple(fragments.tri_id.shape)}")
    if pos.shape[0] not in (1, B):
        raise ValueError(f"pos: expected batch 1 or {B} like color, got {describe(pos)}")
    if color.device != pos.device or fragments.tri_id.device != pos.device:
        raise ValueError(f"color, fragments and pos must share a device, got {color.device}, "
                         f"{fragments.tri_id.device} and {pos.device}")
    tri = fragments.tri_id
    if bool((tri >= faces.shape[0]).any()):
        raise ValueError(f"fragments: tri_id refers to face {int(tri.max())} but faces has {faces.shape[0]} rows; "
                         "pass the faces given to rasterize")
    out_dtype = torch.promote_types(color.dtype, pos.dtype)
    out = color.to(out_dtype)
    if faces.shape[0] == 0:
        return out
    sil, nbr = _topology(pos.detach(), faces)
    # Candidate faces per occluder: itself, then its edge neighbours and
    # theirs (duplicates are harmless). Near a smooth silhouette the faces
    # turn edge-on and project to slivers that rarely hold a pixel centre,
    # so the edge that crosses a pixel segment often belongs to a sliver
    # next to the pixel's triangle, not to the triangle itself.
    F = faces.shape[0]
    ring = torch.arange(F, device=pos.device)[:, None]
    for _ in range(rings):
        step = nbr[ring.clamp_min(0)].masked_fill((ring < 0)[..., None], -1).reshape(F, -1)
        ring = _unique_rows(torch.cat((ring, step), 1))
    near = (sil[:, ring.clamp_min(0)] & (ring >= 0)[None, :, :, None]).flatten(2).any(2)  # [B, F]
    idx, deltas = [], []
    for dim in (2, 1):  # left / right pairs, then top / bottom pairs
        i, d = _pairs(color, fragments, pos, faces, sil, ring, near, dim)
        idx.append(i)
        deltas.append(d)
    idx_all = torch.cat(idx)
    if idx_all.numel() == 0:
        return out
    acc = torch.zeros((B * H * W, C), dtype=out_dtype, device=color.device)
    acc = acc.index_add(0, idx_all, torch.cat(deltas))
    return out + acc.view(B, H, W, C).permute(0, 3, 1, 2)

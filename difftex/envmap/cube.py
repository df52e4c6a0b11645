"""Seamless cube-map sampling: ``cubemap`` reads six faces as one continuous sphere of texels.

Mechanism. Every level read is turned into an *atlas*: the six faces, each
framed by a gutter of ``g`` texels holding the neighbouring faces' texels,
stacked in one ``[B, C, 6 (S_k + 2g), S_k + 2g]`` image. A point of face f
at face uv (u, v) reads the atlas at
``((u S_k + g) / P, (f P + v S_k + g) / (6 P))``, ``P = S_k + 2g``, with
difftex's own single-level sampler (``wrap="clamp"``): the filter's taps
that leave the face land in the gutter, i.e. on the neighbouring face's
texels, so the result is continuous across the 12 cube edges. One atlas
serves all six faces, so a level costs one sampler call whatever the faces
the points fall on.

The gutter is built with one differentiable gather (``index_select`` and a
3-term weighted sum) from the faces, through an index table per
``(S_k, g)`` (cached). An edge gutter texel at depth d beyond the edge is
the neighbour's texel at depth d - 1 inside it, at the same place along the
edge: the cube folded flat across that edge (the exact topological
neighbour, not a reprojection, which would shrink the along-edge
coordinate). A corner gutter texel (beyond a cube corner, where no texel
exists) is the mean of three texels: the face's own corner texel and the two
folded edge texels nearest to it. At depth 1 (bilinear) this makes the
three faces agree exactly at the cube corner ((a + b + c) / 3 from each).

Filters:

* "nearest", "bilinear": g = 1; "bicubic": g = 2.
* "trilinear", "nearest-mip": the level D is difftex's (``log2`` of the
  longer footprint vector in face texels, face size S), computed from the
  face-uv derivatives of the direction's projection, which are analytic.
  The texel grids of two faces are sheared against each other at their
  edge, so a per-face level jumps there (on GPUs too); within ``EDGE_BAND``
  of an edge the footprint length is blended with the one measured on the
  neighbouring face, which makes D continuous across edges and corners
  (``_log2_length``). Each level k is read on its own atlas (g = 1, built
  from the faces' level k: a padded pyramid is not the pyramid of a padded
  base) and the levels blended by difftex's ``mip_blend``.
* "anisotropic", "auto": difftex's taps along the footprint's major axis,
  laid out in the point's face plane; a tap that leaves the face is
  *reprojected* (face plane point -> direction -> its own face and uv), so
  the taps follow the great circle of the major axis across any number of
  edges, and every tap reads its own face with a 1-texel gutter.
* "ewa": the footprint ellipse of ``difftex.sample``'s EWA (``lod.ellipse``,
  minor axis grown to ``major / max_aniso``, level ``D = log2(minor) +
  lod_bias`` from the face-uv derivatives, blended across edges as
  trilinear's) is covered by a lattice of taps, ``n_a x n_b`` along its axes
  (``n = ceil(2 r + 1/2)`` for a half-axis of r level-D face texels: taps at
  most a texel apart), each weighted by pbrt's Gaussian ``exp(-ALPHA r^2) -
  exp(-ALPHA)`` of its place in the ellipse, normalised, and read
  bilinearly at level D (two levels blended) on the face its direction
  falls on. The lattice is laid out on the sphere: in the tangent plane of
  the direction, along the axes of the same ellipse measured there (from
  the derivatives of the unit direction, in radians), so no face enters
  the taps' places and they cross any number of edges and corners with a
  1-texel gutter per level. This is design (b), EWA as a weighted sum of
  reprojected bilinear taps, chosen over (a), per-face texel windows read
  from an atlas whose gutter is as wide as the window: a window reaches
  ``max_aniso * MAX_MINOR`` texels, wider than the coarse faces themselves
  (the fold onto a neighbour is defined one face deep), the corners would
  read the 3-texel-mean gutter over a whole window, and the ellipse,
  projected on each face, would still change at the edges (laid out in the
  face plane, as anisotropic's taps are, the largest jump at a face change
  was 4x the largest inside a face; in the tangent plane it is at most a
  third).
* "ripmap" and "sat" are not supported (ValueError): their boxes are
  aligned with one face's axes.

Approximations (measured in tests/envmap/test_cube.py):

* A folded gutter texel stands O(h) away from where the neighbour's texel
  projects on the face's extended plane, so near edges bilinear is O(h)
  accurate (0.2 / S on a smooth function), O(h^2) elsewhere (1.9 / S^2).
* The gutter corners (beyond a cube corner, where no texel exists) are
  3-texel means. Bilinear is exactly continuous at the corners; bicubic's
  4 x 4 stencil is continuous across edges but not within 2 texels of a
  corner (jump 0.028 on uniform [0, 1) texels at S = 8).
* "anisotropic" / "auto": the level is blended across edges as trilinear's
  (``_edge_blend``: along great circles the largest jump at a face change
  drops from 0.079 to 0.045 on S = 8 noise), and within the edge band the
  tap count is the largest of the faces' (the same on both sides of an
  edge; per-face counts differed at 13-14 of 24 pairs of directions
  straddling the edges), but the axis (the taps' extent and direction) is
  the centre face's, so the spacing may still jump where the point crosses
  an edge, and past an edge the taps keep the centre face's spacing
  (along great circles with a 4 x 1.5-texel footprint the largest jump at
  a face change is 0.105 against 0.034 inside faces; with 1.5 x 4 it is
  0.045 against 0.086).
* A NaN in a direction derivative is a zero footprint (lod's rule: level
  0, one tap) on every backend, so it stays in its pixel: a NaN footprint
  gives no NaN value and no NaN gradient to the cube.
* "ewa" differs from ``difftex.sample``'s EWA even inside a face: the
  texels of the ellipse are replaced by bilinear taps, whose tent is the
  reconstruction (so, unlike pbrt, the ellipse gets no unit-texel padding,
  and a vanishing footprint is exactly bilinear; with the padding the mean
  differences below grew about 2x, measured with face-plane taps), and the tangent plane is not the face
  plane. Mean difference from ``sample``'s EWA on uniform noise 0.021
  (footprints of ~0.6 texel) and 0.009 (~3 texels), where anisotropic's is
  0.014 and 0.029. Along great circles on S = 8 noise the largest jump at a
  face change against inside a face is 0.0041 / 0.020 (footprint 2.5 x 1.5
  texels) and 0.0057 / 0.019 (4 x 1); what jumps, inside faces too, is the
  tap count. Against box-filtered supersampling it follows ``sample``'s
  EWA: its Gaussian reaches a pixel step out, wider than a pixel's box, so
  on the reflective sphere (tests/envmap/test_cube_minify.py) it scores
  25.7 dB, above trilinear (25.5), below anisotropic (27.8). Work: up to
  ``ceil(2 max_aniso MAX_MINOR + 1/2) x 5`` taps per point (where the level
  is clamped the ellipse is shrunk, shape kept, to a minor axis of
  ``MAX_MINOR`` level-D texels, as ``sample``'s EWA on its coarsest level,
  and its major axis capped at ``max_aniso MAX_MINOR``).
* The pyramid's box filter is per face: a coarse texel next to an edge
  averages only its own face's texels. For even sizes this is exact (each
  coarse texel is the mean of the 4 texels it covers, and the coarse faces
  meet along the same edges as the fine ones); odd sizes use difftex's
  area-weighted box within each face, which drops no texel (every face's
  mean is kept, and every base texel weighs (S_k / S)^2 in level k's sum).

Native path. On the CPU, "bilinear", "trilinear" and "nearest-mip" of one
cube (B = 1 in the cube; the directions may be batched) run the native
kernel (``csrc/cube.cpp``, where ``difftex.backend`` allows it) in two
passes over the points: the front end (face, face uv and the edge-blended
level from the directions and their derivatives, with a hand-written
backward that recomputes each point) and the read (the bilinear taps of one
or two levels straight from the faces; a tap past an edge reads the same
gutter as the atlas, through the ring tables of ``_ring_tables``, so no
atlas is built; the backward scatters into the levels' gradients by bands,
as ``sample``'s kernels do). The torch path (atlas + ``mip_blend``) stays
the reference the tests hold it to (tests/envmap/test_cube_native.py), and
runs everything else: the other filters, CUDA, a batch of cubes, double
backward (the native nodes hand it to the torch path).

Cost (``experiments/bench/bench_cubemap.py``: 6 x 256^2 cube, 512^2
directions, against ``difftex.sample`` on a 2D texture of as many texels in
the same run): the native path reads as fast as ``sample``'s kernels; what
is left is the front end (the projection and the level measured on up to
three faces near edges), so bilinear and trilinear, forward and forward +
backward, measured 1.25-1.41x on a loaded machine (the README's speed
section has the figures). EWA (the torch path) is about 5x.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Optional, Sequence, Union

import torch
from torch import Tensor

from .._checks import broadcast_batch, check_float, check_same, describe
from ..mapping.common import cube_tables, dir_floor, pick
from ..texture.filters.separable import separable_sample
from ..texture.filters.trilinear import mip_blend, per_level, spread_taps
from ..texture.options import (DEFAULT_TOLERANCE, MAX_ANISO, MIP_FILTERS, SEPARABLE, check_bias, check_filter,
                               check_number)
from ..texture.filters.ewa import ALPHA, MAX_MINOR, covariance
from ..texture.lod import ellipse, footprint, level, log2_length
from ..texture.pyramid.mipmap import Pyramid, level_count, mipmap
from ..texture.sample import sample
from ..texture.taps import taps
from ..backend import single_level
from .. import _native as native
from .directions import _face_coords, check_dirs_derivs, cube_to_direction, direction_to_cube

#: Width, in [-1, 1] face coordinates, of the band along each edge over which the trilinear level
#: blends with the neighbouring face's (see ``_log2_length``).
EDGE_BAND = 0.25

#: Filters of ``difftex.sample`` that cubemap rejects (module docstring).
_UNSUPPORTED = ("ripmap", "sat")
#: Gutter width (texels) each single-level filter needs: its taps reach this far past a face edge.
GUTTER = {"nearest": 1, "bilinear": 1, "bicubic": 2}


class CubeMipmap(Pyramid):
    """The mip pyramids of the six faces of a cube map: levels ``[B, 6, C, S_k, S_k]``, level 0 the faces.

    Build one with :func:`cube_mipmap`; :func:`cubemap` accepts it in place of
    the faces. The levels are ordinary tensors in the autograd graph.
    """

    __slots__ = ("_atlases",)

    def __init__(self, levels: Sequence[Tensor]):
        super().__init__(levels)
        self._atlases: dict = {}

    def atlas(self, k: int, g: int) -> Tensor:
        """Level k as the gutter atlas [B, C, 6 P, P] of gutter g; built once and kept while no gradient is
        recorded through it (a level that requires grad under grad mode is rebuilt each call, in the graph)."""
        level = self.levels[k]
        if torch.is_grad_enabled() and level.requires_grad:
            return _atlas(level, g)
        key = (k, g)
        hit = self._atlases.get(key)
        # The level itself (so a replaced level is noticed) and its version (so an in-place change is).
        if hit is None or hit[0] is not level or hit[1] != level._version:
            with torch.no_grad():
                hit = self._atlases[key] = (level, level._version, _atlas(level, g))
        return hit[2]

    def __repr__(self) -> str:
        B, _, C = self.levels[0].shape[:3]
        sizes = ", ".join(str(t.shape[-1]) for t in self.levels)
        return f"CubeMipmap(B={B}, C={C}, sizes=[{sizes}], dtype={self.levels[0].dtype})"


def _check_cube(cube: object) -> Tensor:
    check_float("cube", cube, 5, shape_doc="[B, 6, C, S, S]")
    assert isinstance(cube, Tensor)
    B, F, C, H, W = cube.shape
    if F != 6:
        raise ValueError(f"cube: expected 6 faces (+x, -x, +y, -y, +z, -z) in dim 1 of [B, 6, C, S, S], "
                         f"got {describe(cube)}")
    if H != W:
        raise ValueError(f"cube: expected square faces [B, 6, C, S, S], got {H}x{W} faces, {describe(cube)}")
    if min(B, C, H) < 1:
        raise ValueError(f"cube: expected B, C, S >= 1, got {describe(cube)}")
    return cube


def cube_mipmap(cube: Tensor) -> CubeMipmap:
    """The mip pyramid of each face of a cube map (``difftex.mipmap`` on the six faces as a batch).

    Args:
        cube: [B, 6, C, S, S] float faces in OpenGL order (+x, -x, +y, -y,
            +z, -z), any S >= 1 (odd sizes use difftex's odd-side filter).

    Returns:
        CubeMipmap with levels [B, 6, C, ceil(S / 2^k), ceil(S / 2^k)] down to 1 x 1.

    Differentiable: gradients of anything read from any level reach ``cube``.
    Raises TypeError for a non-float tensor, ValueError naming ``cube`` for a
    wrong shape, face count or non-square faces.
    """
    cube = _check_cube(cube)
    B, _, C, S, _ = cube.shape
    levels = mipmap(cube.reshape(B * 6, C, S, S)).levels
    return CubeMipmap([lv.view(B, 6, C, *lv.shape[-2:]) for lv in levels])


# --------------------------------------------------------------------------
# the gutter tables and the atlas
# --------------------------------------------------------------------------


def _fold(face: Tensor, s: Tensor, t: Tensor, n: int) -> Tensor:
    """Flat texel index (face, row, col) of the point (s, t) in [-1, 1]-face coordinates, folded across an edge.

    At most one of s, t lies outside [-1, 1]; the excess e is carried onto the
    neighbouring face as the same distance from the shared edge.
    """
    es, et = (s.abs() - 1).clamp_min(0), (t.abs() - 1).clamp_min(0)
    sc_ax, sc_sg, tc_ax, tc_sg, ma_ax, ma_sg = cube_tables(face)
    uv = torch.stack([(s.clamp(-1, 1) + 1) / 2, (t.clamp(-1, 1) + 1) / 2], -1)
    p = cube_to_direction(face, uv)
    normal = torch.nn.functional.one_hot(ma_ax, 3).to(p.dtype) * ma_sg.to(p.dtype)[..., None]
    p = p - (es + et)[..., None] * normal
    f2, uv2 = direction_to_cube(p)
    col = torch.floor(uv2[..., 0] * n).long().clamp(0, n - 1)
    row = torch.floor(uv2[..., 1] * n).long().clamp(0, n - 1)
    return (f2 * n + row) * n + col


@lru_cache(maxsize=64)
def _gutter_table(n: int, g: int) -> tuple[Tensor, Tensor, Tensor]:
    """The gutter texels of the padded faces (P = n + 2g), flat in [6, P, P]: positions [K], and per
    position 3 indices into the flat faces [6, n, n] with their weights (float64), [K, 3] each."""
    P = n + 2 * g
    f = torch.arange(6).view(6, 1, 1).expand(6, P, P)
    r = torch.arange(P, dtype=torch.float64)
    # texel centres in [-1, 1] face coordinates
    s = ((2 * (r - g + 0.5) / n) - 1).view(1, 1, P).expand(6, P, P)
    t = ((2 * (r - g + 0.5) / n) - 1).view(1, P, 1).expand(6, P, P)
    out_s, out_t = s.abs() > 1, t.abs() > 1
    gutter = (out_s | out_t).reshape(-1)
    pos = gutter.nonzero().squeeze(1)
    f, s, t, out_s, out_t = (x.reshape(-1)[pos] for x in (f, s, t, out_s, out_t))
    lim = 1 - 1 / n  # the outermost texel centre
    sc, tcl = s.clamp(-lim, lim), t.clamp(-lim, lim)
    a = _fold(f, s, tcl, n)     # across the left / right edge
    b = _fold(f, sc, t, n)      # across the top / bottom edge
    c = _fold(f, sc, tcl, n)    # the face's own corner texel (weight 0 off the corners)
    both = (out_s & out_t).double()
    w = torch.stack([(out_s & ~out_t).double() + both / 3, (out_t & ~out_s).double() + both / 3, both / 3], -1)
    return pos, torch.stack([a, b, c], -1), w


@lru_cache(maxsize=64)
def _gutter_gather(n: int, g: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``_gutter_table`` as indices straight into a level's layout: (positions [K] in the flat [6, P, P]
    atlas; face, row, col [K, 3] of the 3 texels read; their flat index [3 K] in [6, n, n]; weights [K, 3])."""
    pos, idx, w = _gutter_table(n, g)
    face, rc = idx // (n * n), idx % (n * n)
    return pos, face, rc // n, rc % n, idx.reshape(-1), w


class _Atlas(torch.autograd.Function):
    """[B, 6, C, n, n] -> [B, C, 6 P, P]: the faces with their gutters, stacked along the rows.

    The faces are copied in once and only the gutter texels (about 4 g n per
    face) are gathered, 3 weighted texels each; the backward is the adjoint
    (the gradient's face interiors plus the gutter gradients added back to
    the texels they came from), in torch ops, so double backward works.
    Padding and index_add under autograd cost several times more on the CPU
    (measured at n = 256: transposed copies and zero fills each way).
    """

    @staticmethod
    def forward(ctx, level: Tensor, g: int) -> Tensor:
        B, _, C, n, _ = level.shape
        P = n + 2 * g
        pos, face, row, col, lin, w = (t.to(level.device) for t in _gutter_gather(n, g))
        w = w.to(level.dtype)
        ctx.args = (n, g, pos, lin, w)
        atlas = level.new_empty((B, C, 6, P, P))
        faces = level.transpose(1, 2)
        atlas[..., g:g + n, g:g + n] = faces
        gutter = (faces[:, :, face, row, col] * w).sum(-1)  # [B, C, K]
        atlas.view(B, C, 6 * P * P).index_copy_(2, pos, gutter)
        return atlas.view(B, C, 6 * P, P)

    @staticmethod
    def backward(ctx, grad: Tensor):
        n, g, pos, lin, w = ctx.args
        B, C = grad.shape[:2]
        P = n + 2 * g
        planes = grad.reshape(B, C, 6, P, P)[..., g:g + n, g:g + n].reshape(B, C, 6 * n * n)  # a fresh copy
        gutter = grad.reshape(B, C, 6 * P * P).index_select(2, pos)  # [B, C, K]
        planes = planes.index_add(2, lin, (gutter.unsqueeze(-1) * w).reshape(B, C, -1))
        return planes.view(B, C, 6, n, n).transpose(1, 2), None


def _atlas(level: Tensor, g: int) -> Tensor:
    """[B, 6, C, n, n] -> [B, C, 6 P, P], P = n + 2 g: the faces with their gutters (``_Atlas``)."""
    return _Atlas.apply(level, g)


@lru_cache(maxsize=64)
def _ring_tables(n: int) -> tuple[Tensor, Tensor]:
    """``_gutter_table(n, 1)`` in the ring order of the native read (``csrc/cube.cpp``): per face (P = n + 2)
    4 P - 4 slots, row 0 (x), row P - 1 (P + x), column 0 (2 P + y - 1), column P - 1 (3 P - 2 + y - 1);
    [6 (4 P - 4), 3] source indices flat in [6, n, n] (int64) and weights (float64)."""
    P = n + 2
    pos, idx, w = _gutter_table(n, 1)
    f, rc = pos // (P * P), pos % (P * P)
    y, x = rc // P, rc % P
    slot = torch.where(y == 0, x, torch.where(y == P - 1, P + x, torch.where(x == 0, 2 * P + y - 1, 3 * P - 3 + y)))
    slot = f * (4 * P - 4) + slot
    ri, rw = torch.empty_like(idx), torch.empty_like(w)
    ri[slot], rw[slot] = idx, w
    return ri.contiguous(), rw.contiguous()


def _atlas_uv(face: Tensor, uv: Tensor, n: int, g: int) -> Tensor:
    """Face uv [..., 2] of faces [...] (any dtype) -> uv in the atlas of faces of n texels with gutter g."""
    P = n + 2 * g
    u = (uv[..., 0] * n + g) / P
    v = (face.to(uv.dtype) * P + uv[..., 1] * n + g) / (6 * P)
    return torch.stack([u, v], -1)


# --------------------------------------------------------------------------
# the public sampler
# --------------------------------------------------------------------------


def cubemap(
    cube: Union[Tensor, CubeMipmap],
    dirs: Tensor,
    *,
    filter: str = "bilinear",
    dirs_dx: Optional[Tensor] = None,
    dirs_dy: Optional[Tensor] = None,
    lod_bias: Union[float, Tensor] = 0.0,
    max_aniso: float = 16,
    tolerance: float = DEFAULT_TOLERANCE,
) -> Tensor:
    """Sample a cube map seamlessly in the given directions.

    Args:
        cube: [B, 6, C, S, S] float faces in OpenGL order (+x, -x, +y, -y,
            +z, -z) and the orientation of :func:`direction_to_cube` (row 0
            of a face is t = 0); or a :class:`CubeMipmap` (``cube_mipmap``).
            B = 1 broadcasts over the directions' batch.
        dirs: [B, H, W, 3] directions of any length from 1e-18 (float32;
            1e-100 in float64) up: only the direction matters. B = 1
            broadcasts.
        filter: "nearest", "bilinear", "bicubic", or the mip filters
            "trilinear", "nearest-mip", "anisotropic", "auto", "ewa" (as in
            ``difftex.sample``; "ripmap" and "sat" are not supported;
            "ewa" is Gaussian-weighted bilinear taps laid out on the sphere). See the module
            docstring for how each crosses the cube edges.
        dirs_dx, dirs_dy: [B, H, W, 3] d(dirs) / d(pixel column / row), in
            the units of ``dirs`` (the length of dirs may vary; only the
            projection's derivative is used). Required by the mip filters.
        lod_bias: added to the level (face texels, log2); a number or [B, H, W].
        max_aniso, tolerance: as in ``difftex.sample``.

    Returns:
        [B, C, H, W], the dtype and device of the inputs.

    Differentiable w.r.t. the cube (through the pyramid to the faces), dirs
    (not for "nearest"), and for the mip filters dirs_dx, dirs_dy and
    lod_bias. A zero direction gives 0 and passes no gradient (as
    nvdiffrast); a NaN / infinite direction gives NaN in its own pixel only;
    a NaN in dirs_dx / dirs_dy is a zero footprint there (level 0, one tap).
    On the CPU "bilinear", "trilinear" and "nearest-mip" of one cube run the
    native kernel (module docstring), the same values as the torch path.

    Raises ValueError naming the argument for a wrong cube shape, face count,
    non-square faces, dirs whose last dimension is not 3, mismatched
    batches, an unknown or unsupported filter, a mip filter without
    dirs_dx / dirs_dy; TypeError for non-float tensors or mixed dtypes.
    """
    pyramid = None
    if isinstance(cube, CubeMipmap):
        pyramid = cube
        base = _check_cube(cube.levels[0])
    else:
        base = _check_cube(cube)
    check_float("dirs", dirs, 4, last=3, shape_doc="[B, H, W, 3]")
    check_same("dirs", dirs, "cube", base)
    check_filter(filter)
    if filter in _UNSUPPORTED:
        # The ripmap's and the summed-area table's face-aligned boxes cannot cross cube edges.
        ok = tuple(SEPARABLE) + tuple(f for f in MIP_FILTERS if f not in _UNSUPPORTED)
        raise ValueError(f"filter: {filter!r} is not supported by cubemap (its face-aligned boxes cannot cross "
                         f"cube edges); expected one of {ok}")
    max_aniso = check_number("max_aniso", max_aniso, 1, MAX_ANISO)
    tolerance = check_number("tolerance", tolerance, 0)
    Bt, _, C, S, _ = base.shape
    Bd, H, W, _ = dirs.shape
    mip = filter in MIP_FILTERS
    derivs = check_dirs_derivs(dirs_dx, dirs_dy, dirs, filter, mip, "cube", base)
    bias = check_bias(lod_bias, dirs, "dirs", base, "cube", dims="H, W")
    if isinstance(cube, CubeMipmap):
        _check_levels(cube)
    sizes = [Bt, Bd] + [d.shape[0] for d in derivs]
    names = ["cube", "dirs", "dirs_dx", "dirs_dy"][:len(sizes)]
    if isinstance(bias, Tensor) and bias.dim() == 3:
        sizes.append(bias.shape[0])
        names.append("lod_bias")
    B = broadcast_batch(names, sizes)
    if B * H * W == 0:
        parts = [t for t in (base, dirs, *derivs, bias) if isinstance(t, Tensor)]
        return sum(t.reshape(-1)[:0].reshape(B, C, H, W) for t in parts)

    if _native_kernel(base, dirs, filter) is not None:
        return _native_lookup(base if pyramid is None else pyramid, dirs, derivs, filter, bias, B)
    # Zero and non-finite directions read a safe direction (no NaN in any
    # backward, no gradient from them) and get their value put back at the end.
    # One sum and one max say whether there is any (no per-point masks then).
    clean = bool(torch.isfinite(dirs.detach().sum())) and bool(dirs.detach().abs().amax(-1).min() > 0)
    if clean:
        safe = dirs
    else:
        ok = torch.isfinite(dirs).all(-1)
        zero = (dirs == 0).all(-1)
        good = (ok & ~zero).unsqueeze(-1)
        safe = torch.where(good, dirs, torch.tensor([1.0, 0.0, 0.0], dtype=dirs.dtype, device=dirs.device))
        derivs = [torch.where(good, d, 0.0) for d in derivs]
    if filter == "bilinear" and single_level() == "grid_sample":
        out = _bilinear(base if pyramid is None else pyramid, safe, B)
        return out if clean else _put_back(out, ok, zero, B, H, W)
    if derivs:
        face, uv, uv_dx, uv_dy = direction_to_cube(safe, dirs_dx=derivs[0], dirs_dy=derivs[1])
    else:
        face, uv = direction_to_cube(safe)
    if mip:
        log2_len = _log2_length(safe, derivs, face, uv, uv_dx, uv_dy, S) if filter in ("trilinear", "nearest-mip") else None
        out = _mip(pyramid if pyramid is not None else base, face, uv, uv_dx, uv_dy, log2_len, bias, B, filter,
                   max_aniso, tolerance, safe, derivs)
    else:
        g = GUTTER[filter]
        atlas = _atlas(base, g) if pyramid is None else pyramid.atlas(0, g)
        out = sample(atlas, _atlas_uv(face, uv, S, g), filter=filter, wrap="clamp")
    return out if clean else _put_back(out, ok, zero, B, H, W)


# --------------------------------------------------------------------------
# the native path (csrc/cube.cpp): front end and read in one pass each
# --------------------------------------------------------------------------

#: Filters the native path runs (the others take the torch path).
_NATIVE = ("bilinear", "trilinear", "nearest-mip")


def _native_kernel(base: Tensor, dirs: Tensor, filter: str):
    """The native module where it serves this lookup (CPU, float32 / float64, one cube, a filter of
    ``_NATIVE``, ``difftex.backend`` allowing it), else None."""
    if filter not in _NATIVE or base.shape[0] != 1 or base.dtype not in (torch.float32, torch.float64):
        return None
    kernel = native.kernel(dirs)
    return kernel if kernel is not None and hasattr(kernel, "cube_read") else None


def _torch_front(dirs: Tensor, dx: Optional[Tensor], dy: Optional[Tensor], bias: Union[float, Tensor], S: int,
                 L: int) -> tuple[Tensor, Tensor, Tensor]:
    """The torch reference of ``cube_front`` on flat [M, 3] inputs: (face, uv, level D; zeros without dx, dy).
    A zero or non-finite direction reads +x with zero derivatives (its face is not -1 / -2 here, and not read)."""
    good = (torch.isfinite(dirs).all(-1) & (dirs != 0).any(-1)).unsqueeze(-1)
    dirs = torch.where(good, dirs, torch.tensor([1.0, 0.0, 0.0], dtype=dirs.dtype, device=dirs.device))
    if dx is None:
        face, uv = direction_to_cube(dirs)
        return face, uv, torch.zeros_like(uv[:, 0])
    dx, dy = torch.where(good, dx, 0.0), torch.where(good, dy, 0.0)
    face, uv, uv_dx, uv_dy = direction_to_cube(dirs, dirs_dx=dx, dirs_dy=dy)
    return face, uv, level(_log2_length(dirs, [dx, dy], face, uv, uv_dx, uv_dy, S), bias, L)


class _NativeFront(torch.autograd.Function):
    """dirs, dx, dy [M, 3] (dx, dy None: bilinear, D empty), bias [M] (None: the number bias0) -> face [M]
    int8 (-1 / -2 for a zero / non-finite direction), face uv [M, 2], level D [M] of a pyramid of L levels,
    as ``_torch_front``, in one native pass; the backward recomputes each point (no graph)."""

    @staticmethod
    def forward(ctx, dirs: Tensor, dx: Optional[Tensor], dy: Optional[Tensor], bias: Optional[Tensor], bias0: float,
                S: int, L: int):
        none = dirs.new_empty(0)
        ctx.args = (bias0, S, L)
        face, uv, D = native.load().cube_front(dirs, none if dx is None else dx, none if dy is None else dy,
                                               none if bias is None else bias, bias0=bias0, S=S, levels=L,
                                               band=EDGE_BAND)
        ctx.save_for_backward(dirs, dx, dy, bias)
        ctx.mark_non_differentiable(face)
        return face, uv, D

    @staticmethod
    def backward(ctx, _gface, guv: Optional[Tensor], gD: Optional[Tensor]):
        dirs, dx, dy, bias = ctx.saved_tensors
        bias0, S, L = ctx.args
        need = ctx.needs_input_grad
        guv = torch.zeros_like(dirs[:, :2]) if guv is None else guv
        if dx is None or gD is None:
            gD = dirs.new_empty(0)
        if torch.is_grad_enabled():  # double backward: the differentiable torch path
            def recompute() -> Tensor:
                _, uv, D = _torch_front(dirs, dx, dy, bias0 if bias is None else bias, S, L)
                return torch.cat([uv, D.unsqueeze(-1)], -1)
            grad = torch.cat([guv, gD.unsqueeze(-1) if gD.numel() else torch.zeros_like(guv[:, :1])], -1)
            return (*native.double_backward(recompute, (dirs, dx, dy, bias), need[:4], grad), None, None, None)
        none = dirs.new_empty(0)
        gd, gx, gy, gb = native.load().cube_front_backward(
            dirs, none if dx is None else dx, none if dy is None else dy, none if bias is None else bias,
            bias0=bias0, S=S, levels=L, band=EDGE_BAND, guv=guv, gD=gD, need_derivs=need[1] or need[2],
            need_bias=need[3])
        return (gd if need[0] else None, gx if need[1] else None, gy if need[2] else None, gb if need[3] else None,
                None, None, None)


def _torch_read(levels: Sequence[Tensor], face: Tensor, uv: Tensor, D: Tensor, nearest: bool) -> Tensor:
    """The torch reference of ``cube_read``: levels [1, 6, C, n_k, n_k], face [M] (-1: 0, -2: NaN, no
    gradient), uv [M, 2], D [M] -> [C, M], each level read on its 1-texel gutter atlas, blended by
    ``mip_blend``."""
    ok = face >= 0
    D = D if D.numel() else uv.new_zeros(uv.shape[0])
    x = torch.cat([uv, torch.where(ok, face, 0).to(uv.dtype).unsqueeze(-1)], -1)

    def read_one(k: int, xs: list[Tensor]) -> Tensor:
        at = _atlas_uv(xs[0][:, 2], xs[0][:, :2], levels[k].shape[-1], 1)
        return separable_sample(_atlas(levels[k], 1), at.unsqueeze(0), "linear", "clamp", "clamp")[0]

    out = mip_blend(D, len(levels), [x], per_level(read_one), nearest=nearest)
    return torch.where(ok, out, torch.where(face == -1, 0.0, float("nan")).to(out.dtype))


class _NativeRead(torch.autograd.Function):
    """``_torch_read`` in one native pass over the points (D empty: level 0): the taps read the faces and,
    past an edge, the gutter through ``_ring_tables`` (no atlas is built); the backward scatters straight
    into the levels."""

    @staticmethod
    def forward(ctx, face: Tensor, uv: Tensor, D: Tensor, nearest: bool, *levels: Tensor) -> Tensor:
        ctx.d_grad = ctx.needs_input_grad[2] and not nearest
        ctx.nearest = nearest
        ctx.save_for_backward(face, uv, D, *levels)
        rings = [_ring_tables(lv.shape[-1]) for lv in levels]
        ctx.rings = ([r[0] for r in rings], [r[1] for r in rings])
        return native.load().cube_read([lv[0].contiguous() for lv in levels], *ctx.rings, face, uv, D, nearest,
                                       ctx.d_grad)

    @staticmethod
    def backward(ctx, grad: Tensor):
        face, uv, D, *levels = ctx.saved_tensors
        need = ctx.needs_input_grad
        if torch.is_grad_enabled():
            return native.double_backward(lambda: _torch_read(levels, face, uv, D, ctx.nearest),
                                          (None, uv, D, None, *levels), need, grad)
        need_levels = need[4:]
        gl, guv, gD = native.load().cube_read_backward(
            [lv[0].contiguous() for lv in levels], *ctx.rings, face, uv, D, grad, ctx.nearest, ctx.d_grad,
            need_levels=any(need_levels), need_uv=need[1], need_D=need[2] and not ctx.nearest)
        if need[2] and gD is None:
            gD = torch.zeros_like(D)
        return (None, guv if need[1] else None, gD if need[2] else None, None,
                *native.level_grads(gl, need_levels, levels))


def _native_lookup(cube: Union[Tensor, CubeMipmap], dirs: Tensor, derivs: list[Tensor], filter: str,
                   bias: Union[float, Tensor], B: int) -> Tensor:
    """``cubemap`` for the filters of ``_NATIVE`` on the native path: [B, C, H, W]. Zero and non-finite
    directions are the kernel's to handle (0 / NaN, no gradient)."""
    base = cube.levels[0] if isinstance(cube, CubeMipmap) else cube
    C, S = base.shape[2], base.shape[-1]
    _, H, W, _ = dirs.shape
    flat = lambda t: t.expand(B, H, W, 3).reshape(-1, 3).contiguous()
    if filter == "bilinear":
        levels, L, dx, dy = [base], 1, None, None
    else:
        levels = (cube if isinstance(cube, CubeMipmap) else cube_mipmap(cube)).levels
        L = min(len(levels), level_count(S, S))
        levels, dx, dy = levels[:L], flat(derivs[0]), flat(derivs[1])
    b = bias.expand(B, H, W).reshape(-1).contiguous() if isinstance(bias, Tensor) and dx is not None else None
    face, uv, D = _NativeFront.apply(flat(dirs), dx, dy, b, bias if isinstance(bias, float) else 0.0, S, L)
    out = _NativeRead.apply(face, uv, D, filter == "nearest-mip", *levels)
    return out.view(C, B, H, W).transpose(0, 1)


def _put_back(out: Tensor, ok: Tensor, zero: Tensor, B: int, H: int, W: int) -> Tensor:
    """0 at the zero directions, NaN at the non-finite ones."""
    ok = ok.expand(B, H, W).unsqueeze(1)
    zero = zero.expand(B, H, W).unsqueeze(1)
    return torch.where(zero, 0.0, torch.where(ok, out, float("nan")))


def _bilinear(cube: Union[Tensor, CubeMipmap], dirs: Tensor, B: int) -> Tensor:
    """Bilinear on the atlas in one ``grid_sample`` (the grid_sample backend), from the face coordinates.

    The atlas point of face f, (s, t) = (s_c, t_c) / m_a in [-1, 1], is
    grid_sample's ``((n / P) s, (2 f + 1) / 6 - 1 + (n / 6 P) t)`` (P = n + 2g):
    a few passes over the points where the face uv, the atlas uv and
    ``sample``'s own wrap / finiteness passes took about five times as many
    (on the CPU at 512^2 directions they cost more than the bilinear read).
    ``sample(atlas, _atlas_uv(...), wrap="clamp")`` is the same read
    (grid_sample's "border" padding is difftex's clamp), which the
    reference backend runs.
    """
    n = cube.levels[0].shape[-1] if isinstance(cube, CubeMipmap) else cube.shape[-1]
    P = n + 2
    atlas = cube.atlas(0, 1) if isinstance(cube, CubeMipmap) else _atlas(cube, 1)
    face, sc, tc, ma, _, _, _ = _face_coords(dirs, [])
    inv = 1.0 / torch.where(ma >= dir_floor(ma.dtype), ma, torch.inf)  # below the floor: the face centre
    grid = torch.stack([sc * inv * (n / P), tc * inv * (n / (6 * P)) + (face.to(sc.dtype) / 3 - 5 / 6)], -1)
    grid = grid.expand(B, *grid.shape[1:])
    if atlas.shape[0] != B:
        atlas = atlas.expand(B, *atlas.shape[1:])
    return torch.nn.functional.grid_sample(atlas, grid.to(atlas.dtype), mode="bilinear", padding_mode="border",
                                           align_corners=False)


def cube_to_equirect(
    cube: Union[Tensor, CubeMipmap],
    size: Sequence[int],
    *,
    filter: str = "anisotropic",
    lod_bias: float = 0.0,
    max_aniso: float = 16,
) -> Tensor:
    """Resample a cube map into a latitude-longitude (equirectangular) map.

    Every pixel centre of the map (``difftex.envmap.equirect_uv_to_direction``'s
    convention, row 0 straight up) is looked up with :func:`cubemap`, with the
    analytic derivatives of its direction per map column / row, so a map
    smaller than the cube is filtered by its footprint rather than aliased.

    Args:
        cube: [B, 6, C, S, S] faces or a :class:`CubeMipmap`, as for :func:`cubemap`.
        size: (H, W) of the map, ints >= 1 (2:1 for square texels).
        filter: any filter :func:`cubemap` takes. The default "anisotropic"
            follows the map's stretch towards the poles (a row there covers
            a thin ring of directions).
        lod_bias, max_aniso: as for :func:`cubemap` (lod_bias a number).

    Returns:
        [B, C, H, W], the cube's dtype and device.

    Differentiable w.r.t. the cube. Raises ValueError / TypeError naming
    ``size`` for anything but two ints >= 1, and what :func:`cubemap` raises.
    """
    if (not isinstance(size, (tuple, list)) or len(size) != 2
            or any(isinstance(n, bool) or not isinstance(n, int) for n in size)):
        raise TypeError(f"size: expected (H, W) ints >= 1, got {size!r}")
    H, W = size
    if H < 1 or W < 1:
        raise ValueError(f"size: expected (H, W) ints >= 1, got {tuple(size)}")
    base = cube.levels[0] if isinstance(cube, CubeMipmap) else _check_cube(cube)
    kw = dict(dtype=base.dtype, device=base.device)
    v, u = torch.meshgrid((torch.arange(H, **kw) + 0.5) / H, (torch.arange(W, **kw) + 0.5) / W, indexing="ij")
    # dirs = (sin t sin p, cos t, -sin t cos p), p = 2 pi u - pi, t = pi v: its derivatives per column / row.
    phi, theta = u * (2 * math.pi) - math.pi, v * math.pi
    st, ct, sp, cp = theta.sin(), theta.cos(), phi.sin(), phi.cos()
    dirs = torch.stack((st * sp, ct, -st * cp), -1).unsqueeze(0)
    dx = torch.stack((st * cp, torch.zeros_like(st), st * sp), -1).unsqueeze(0) * (2 * math.pi / W)
    dy = torch.stack((ct * sp, -st, -ct * cp), -1).unsqueeze(0) * (math.pi / H)
    return cubemap(cube, dirs, filter=filter, dirs_dx=dx, dirs_dy=dy, lod_bias=lod_bias, max_aniso=max_aniso)


def _face_derivs(dirs: Tensor, dds: list[Tensor], face: Tensor, use: Tensor) -> list[Tensor]:
    """d(face uv) of ``dirs`` projected on the given (not necessarily major) faces, where ``use``; finite elsewhere."""
    sc_ax, sc_sg, tc_ax, tc_sg, ma_ax, ma_sg = cube_tables(face)
    sc_sg, tc_sg, ma_sg = (t.to(dirs.dtype) for t in (sc_sg, tc_sg, ma_sg))
    sc, tc = sc_sg * pick(dirs, sc_ax), tc_sg * pick(dirs, tc_ax)
    # Unused entries (a face the direction may be orthogonal to) compute with m_a = 1: no inf, no NaN gradient.
    ma = torch.where(use, ma_sg * pick(dirs, ma_ax), 1.0).clamp_min(dir_floor(dirs.dtype))
    s, t = sc / ma, tc / ma
    out = []
    for dd in dds:
        dsc, dtc, dma = sc_sg * pick(dd, sc_ax), tc_sg * pick(dd, tc_ax), ma_sg * pick(dd, ma_ax)
        out.append(torch.stack([0.5 * (dsc - s * dma) / ma, 0.5 * (dtc - t * dma) / ma], dim=-1))
    return out


def _edge_blend(own: Tensor, dirs: Tensor, dds: list[Tensor], face: Tensor, uv: Tensor, measure) -> Tensor:
    """``own`` [M] (a per-face footprint measure: log2 length, or a level) blended with the neighbouring faces'.

    Each face measures a footprint on its own texel grid, and the grids of
    two faces are sheared against each other at their edge, so per-face
    levels jump there (as on GPUs). Within ``EDGE_BAND`` of an edge the
    value is blended with ``measure(uv_dx, uv_dy, idx)``, the same measure of
    the footprint projected on the neighbouring face, at the points ``idx``
    (weights 1 at the edge, 0 at the band's inner side, the own face weight
    1, normalised): at an edge both faces give the mean of their two values,
    at a corner all three give the mean of three, so the value is
    continuous everywhere. Flat inputs: dirs, dds [M, 3], face [M], uv [M, 2].
    Only the points in a band (about a quarter per axis) measure twice.
    """
    num, den = own, torch.ones_like(own)
    for axis in (0, 1):
        c = 2 * uv[:, axis] - 1
        w = (1 - (1 - c.abs()) / EDGE_BAND).clamp(0, 1)
        idx = (w.detach() > 0).nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        tabs = cube_tables(face.index_select(0, idx))
        ax, sg = tabs[2 * axis], tabs[2 * axis + 1]
        nface = 2 * ax + ((c.index_select(0, idx) * sg.to(c.dtype)) < 0).long()
        # On the band the neighbour's axis component is > 0.75 m_a: its projection is finite.
        nd = _face_derivs(dirs.index_select(0, idx), [d.index_select(0, idx) for d in dds], nface,
                          torch.ones_like(nface, dtype=torch.bool))
        wi = w.index_select(0, idx)
        num = num.index_add(0, idx, wi * measure(nd[0], nd[1], idx))
        den = den.index_add(0, idx, wi)
    return num / den


def _log2_length(dirs: Tensor, dds: list[Tensor], face: Tensor, uv: Tensor, uv_dx: Tensor, uv_dy: Tensor,
                 S: int) -> Tensor:
    """[B, H, W] trilinear ``log2 L`` (face texels), continuous across the cube edges (``_edge_blend``)."""
    shape = torch.broadcast_shapes(dirs.shape, *(d.shape for d in dds))  # dirs and derivatives may broadcast
    flat3 = lambda t: t.expand(shape).reshape(-1, 3)
    flat2 = lambda t: t.expand(*shape[:-1], 2).reshape(-1, 2)
    own = log2_length(flat2(uv_dx), flat2(uv_dy), S, S)
    out = _edge_blend(own, flat3(dirs), [flat3(d) for d in dds], face.expand(shape[:-1]).reshape(-1), flat2(uv),
                      lambda dx, dy, idx: log2_length(dx, dy, S, S))
    return out.view(shape[:-1])


def _check_levels(pyramid: CubeMipmap) -> None:
    """A user-built CubeMipmap: every level [B, 6, C, ceil(S / 2^k), ceil(S / 2^k)] like the base."""
    base = pyramid.levels[0]
    B, _, C, S, _ = base.shape
    if len(pyramid.levels) > level_count(S, S):
        raise ValueError(f"cube: {len(pyramid.levels)} levels given but {S}x{S} faces have only "
                         f"{level_count(S, S)} (down to 1x1)")
    for k, lv in enumerate(pyramid.levels[1:], 1):
        n = -(-S // (1 << k))
        check_float(f"cube[{k}]", lv, 5, shape_doc="[B, 6, C, S_k, S_k]")
        check_same(f"cube[{k}]", lv, "cube[0]", base)
        if tuple(lv.shape) != (B, 6, C, n, n):
            raise ValueError(f"cube[{k}]: expected shape {(B, 6, C, n, n)} (ceil(S / 2^k)), got {describe(lv)}")


def _mip(cube: Union[Tensor, CubeMipmap], face: Tensor, uv: Tensor, uv_dx: Tensor, uv_dy: Tensor,
         log2_len: Optional[Tensor], bias: Union[float, Tensor], B: int, filter: str, max_aniso: float, tolerance: float,
         dirs: Tensor, dds: list[Tensor]) -> Tensor:
    """The mip filters on flat point lists: difftex's level front end, one atlas per level read."""
    pyramid = cube if isinstance(cube, CubeMipmap) else cube_mipmap(cube)
    levels = pyramid.levels
    Bt, _, C, S, _ = levels[0].shape
    _, H, W, _ = uv.shape
    P = H * W
    flat = lambda t: t.expand(B, H, W, *t.shape[3:]).reshape(B * P, *t.shape[3:])
    pts, dx, dy, fc = flat(uv), flat(uv_dx), flat(uv_dy), flat(face)
    # A NaN derivative is a zero footprint (lod's rule: level 0, one tap) on every backend; the native
    # footprint front end would spread the anisotropic taps along a NaN axis (NaN in the pixel).
    nan = dx.isnan().any(-1) | dy.isnan().any(-1)
    if bool(nan.any()):
        dx, dy = torch.where(nan[:, None], 0.0, dx), torch.where(nan[:, None], 0.0, dy)
    if isinstance(bias, Tensor):
        bias = flat(bias) if bias.dim() == 3 else bias
    L = min(len(levels), level_count(S, S))
    weight = point = None
    if log2_len is not None:
        D, axis, count = level(flat(log2_len.unsqueeze(-1)).squeeze(-1), bias, L), None, None
    elif filter == "ewa":
        sub = lambda t, idx: t.index_select(0, idx) if isinstance(t, Tensor) and t.dim() == 1 else t
        D = _ewa_lod(dx, dy, bias, S, L, max_aniso)
        # The level, continuous across edges as trilinear's; the taps are laid out on the sphere.
        D = _edge_blend(D, flat(dirs), [flat(d) for d in dds], fc, pts,
                        lambda a, b, idx: _ewa_lod(a, b, sub(bias, idx), S, L, max_aniso))
        point, tap, weight, count = _ewa_taps(dx, dy, D, S, max_aniso, flat(dirs), [flat(d) for d in dds])
    else:
        D, axis, count = taps(filter, dx, dy, bias, S, S, L, max_aniso, tolerance)
        # The level, continuous across edges as trilinear's. The axis stays the own face's; within the band the
        # tap count is the largest of the faces' (the same on both sides of an edge, so it does not jump there).
        sub = lambda t, idx: t.index_select(0, idx) if isinstance(t, Tensor) and t.dim() == 1 else t
        counts = []

        def measure(a: Tensor, b: Tensor, idx: Tensor) -> Tensor:
            Dn, _, cn = taps(filter, a, b, sub(bias, idx), S, S, L, max_aniso, tolerance)
            counts.append((idx, cn))
            return Dn

        D = _edge_blend(D, flat(dirs), [flat(d) for d in dds], fc, pts, measure)
        if count is not None:
            for idx, cn in counts:
                if cn is not None:
                    count = count.scatter_reduce(0, idx, cn, "amax")
    nearest = filter == "nearest-mip"
    if weight is not None:
        fc, tap = direction_to_cube(tap)
        pts, D = tap, D.index_select(0, point)
    elif count is not None:
        # One entry per tap, at the tap's own face: a tap past an edge is
        # reprojected (face plane -> direction -> face), so taps follow the
        # great circle of the major axis onto the neighbouring faces.
        point, tap, nt = spread_taps(pts, axis, count)
        fc = fc.index_select(0, point)
        fc, tap = direction_to_cube(cube_to_direction(fc, tap))
        pts, D = tap, D.index_select(0, point)
    x = torch.cat([pts, fc.to(pts.dtype).unsqueeze(-1)], -1)

    def run(b: Optional[int], sl: slice) -> Tensor:
        def read_one(k: int, xs: list[Tensor]) -> Tensor:
            n = levels[k].shape[-1]
            at = _atlas_uv(xs[0][:, 2], xs[0][:, :2], n, 1)
            atlas = pyramid.atlas(k, 1) if b is None else _atlas(levels[k][b:b + 1], 1)
            return separable_sample(atlas, at.unsqueeze(0), "linear", "clamp", "clamp")[0]
        return mip_blend(D[sl], L, [x[sl]], per_level(read_one), nearest=nearest)

    if Bt == 1:
        vals = run(None, slice(None))
    else:
        # One cube per batch row (B = Bt): entries are in point order, so row b's are one contiguous block.
        ends = (list(range(P, B * P + 1, P)) if point is None
                else torch.cumsum(count.view(B, P).sum(1), 0).tolist())
        starts = [0] + ends[:-1]
        vals = torch.cat([run(b, slice(s, e)) for b, (s, e) in enumerate(zip(starts, ends))], 1)
    if weight is not None:
        vals = vals.new_zeros((C, B * P)).index_add(1, point, vals * weight)
    elif point is not None:
        vals = vals.new_zeros((C, B * P)).index_add(1, point, vals / nt)
    return vals.view(C, B, H, W).transpose(0, 1)


def _ewa_lod(dx: Tensor, dy: Tensor, bias: Union[float, Tensor], S: int, L: int, max_aniso: float) -> Tensor:
    """EWA's level on faces of S texels: ``log2`` of the minor axis grown to ``major / max_aniso`` (as ``sample``)."""
    fp = footprint(dx, dy, S, S)
    return level(covariance(fp, ellipse(fp), max_aniso)[2], bias, L)


def _ewa_taps(dx: Tensor, dy: Tensor, D: Tensor, S: int, max_aniso: float, dirs: Tensor,
              dds: list[Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """EWA's Gaussian as a lattice of taps in the tangent plane of each direction (module docstring).

    dx, dy: [M, 2] face-uv derivatives (they size the lattice in level-D
    texels); D: [M] the (edge-blended) level; dirs, dds: [M, 3] the
    directions and their derivatives (they place it). Returns (point [T]
    int64, tap directions [T, 3], normalised weights [T], count [M]), taps
    ordered by point; differentiable in dx, dy, D, dirs and dds.
    """
    fp = footprint(dx, dy, S, S)
    ell = ellipse(fp)
    _, minor, _ = covariance(fp, ell, max_aniso)
    scale = torch.exp2(fp.log2_scale)
    texel = torch.exp2(D)  # a level-D texel, in level-0 texels
    # Half-axes in level-D texels; where the level is clamped (finest or coarsest) the minor axis may leave
    # [1, 2): beyond MAX_MINOR it is shrunk, shape kept, as sample's EWA does on its coarsest level, and the
    # major axis is capped at max_aniso MAX_MINOR (factors without gradient, as sample's shrink).
    a, b = ell.major * scale / texel, minor * scale / texel
    with torch.no_grad():
        fb = MAX_MINOR / b.clamp_min(MAX_MINOR)
        fa = fb * (max_aniso * MAX_MINOR) / (a * fb).clamp_min(max_aniso * MAX_MINOR)
        # No pbrt unit-texel padding: the bilinear taps are the reconstruction (module docstring). Taps at most
        # a texel apart; the + 0.5 keeps the counts' steps off the common half-axes (1 and 2 level-D texels,
        # exactly, wherever the level is not clamped) so that rounding does not flip them.
        na = torch.ceil(2 * a * fa + 0.5).long()
        nb = torch.ceil(2 * b * fb + 0.5).long()
        count = na * nb
        point = torch.repeat_interleave(torch.arange(D.shape[0], device=D.device), count)
        i = torch.arange(point.numel(), device=D.device) - (torch.cumsum(count, 0) - count).index_select(0, point)
        nbp = nb.index_select(0, point)
        xi = ((i // nbp).to(D.dtype) + 0.5) / na.index_select(0, point).to(D.dtype) * 2 - 1
        eta = ((i % nbp).to(D.dtype) + 0.5) / nbp.to(D.dtype) * 2 - 1
        w = (torch.exp(-ALPHA * (xi * xi + eta * eta)) - math.exp(-ALPHA)).clamp_min(0)
        w = w / w.new_zeros(D.shape[0]).index_add(0, point, w).index_select(0, point)
    # The same ellipse on the sphere: the derivatives of the unit direction n, in an orthonormal tangent basis
    # that follows d(n)/dx (any basis where that vanishes), give its half-axes in radians.
    length = torch.sqrt((dirs * dirs).sum(-1, keepdim=True))
    n = dirs / length
    tx, ty = ((dd - (dd * n).sum(-1, keepdim=True) * n) / length for dd in dds)
    helper = torch.where(n[:, :1].abs() < 0.9, n.new_tensor([1.0, 0.0, 0.0]), n.new_tensor([0.0, 1.0, 0.0]))
    e1 = torch.where((tx * tx).sum(-1, keepdim=True) > 1e-30, tx, torch.linalg.cross(n, helper))
    e1 = e1 / torch.sqrt((e1 * e1).sum(-1, keepdim=True))
    e2 = torch.linalg.cross(n, e1)
    tan = lambda t: torch.stack([(t * e1).sum(-1), (t * e2).sum(-1)], -1)
    fs = footprint(tan(tx), tan(ty), 1, 1)
    es = ellipse(fs)
    _, minor_s, _ = covariance(fs, es, max_aniso)
    sc = torch.exp2(fs.log2_scale)
    major = es.direction[:, :1] * e1 + es.direction[:, 1:] * e2
    across = torch.linalg.cross(n, major)
    pick = lambda t: t.index_select(0, point)
    off = (pick(es.major * sc * fa) * xi).unsqueeze(-1) * pick(major) \
        + (pick(minor_s * sc * fb) * eta).unsqueeze(-1) * pick(across)
    return point, pick(n) + off, w, count

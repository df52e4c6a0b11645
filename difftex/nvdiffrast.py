"""nvdiffrast's PyTorch API on difftex: ``import difftex.nvdiffrast as dr`` runs nvdiffrast scripts on any device.

The names, signatures, defaults, tensor layouts and semantics are those of
``nvdiffrast.torch`` as its documentation states them
(https://nvlabs.github.io/nvdiffrast, "PyTorch API reference" and "Beyond the
basics"); this module is written from that documentation, with no
nvdiffrast code. Every convention is converted here, at the boundary:

=====================  ==========================================  ===============================================
thing                  nvdiffrast                                  difftex
=====================  ==========================================  ===============================================
images, textures       NHWC; image row 0 is the bottom (NDC y=-1)  NCHW; image row 0 is the top (NDC y=+1)
``rast``               (u, v, z/w, triangle_id + 1), 0 = empty     ``Fragments`` (tri_id, bary, depth), -1 = empty
barycentrics           vertex 0 -> (1, 0), 1 -> (0, 1), 2 -> (0, 0)  bary = (u, v, 1 - u - v)
``rast_db``            (du/dX, du/dY, dv/dX, dv/dY), Y upwards     ``bary_dx``, ``bary_dy`` per column / row (down)
texture uv             (s, t), origin at texel row 0's corner      the same uv on the same tensor rows
``uv_da``              (ds/dX, ds/dY, dt/dX, dt/dY)                ``uv_dx`` = (ds/dX, dt/dX), ``uv_dy`` = (ds/dY, dt/dY)
cube maps              [B, 6, S, S, C], OpenGL faces, row 0 = t=0  [B, 6, C, S, S], the same faces and rows
boundary_mode          'wrap' | 'clamp' | 'zero' | 'cube'          "repeat" | "clamp" | "border" (0) | cubemap()
filter_mode            'nearest' | 'linear' | 'linear-mipmap-      "nearest" | "bilinear" | "nearest-mip" |
                       nearest' | 'linear-mipmap-linear' | 'auto'  "trilinear"
=====================  ==========================================  ===============================================

The row order is converted without flipping images: the ops work on clip
space mirrored in y, whose top-first rows are nvdiffrast's bottom-first rows
(and whose per-row derivatives are nvdiffrast's d/dY).

Where the documentation leaves a choice open, this module decides so:

- ``pos`` and attributes may be float64 as well as float32 (for gradcheck);
  ``tri`` and ``ranges`` must be int32, as nvdiffrast requires.
- Any device torch supports works; the contexts are accepted and only hold
  a device.
- In range mode the reported triangle id indexes the whole ``tri`` tensor
  (the range start is added), as ``interpolate`` needs with the same ``tri``.
- Textures of any size build mipmaps (difftex's odd-side filter), where
  nvdiffrast raises without ``max_mip_level``; for power-of-two sides the
  levels are the same 2 x 2 box averages.
- A mip filter with ``mip_level_bias`` and no ``uv_da`` reads level
  ``clamp(bias, 0, top)`` directly, as the documentation says.
- "nearest" rounds a texel coordinate exactly on a texel edge to even
  (difftex's rule); elsewhere it reads the texel the point lies in.

Extensions that nvdiffrast code never passes: ``filter_mode="anisotropic"``
or ``"ewa"`` with ``max_aniso``; ``boundary_mode="mirror"`` and a
``(mode_u, mode_v)`` pair for per-axis wrap.
"""
from __future__ import annotations

import numbers
from typing import Any, Callable, Iterator, Optional, Sequence, Union

import torch
from torch import Tensor

from ._checks import check_float, check_same, describe
from .envmap.cube import CubeMipmap, cubemap
from .geometry.antialias import antialias as _antialias
from .geometry.raster import Fragments, fragments_of, packed_fragments, visible_layers
from .texture.lod import level
from .texture.options import MAX_ANISO, check_number
from .texture.pyramid.mipmap import Mipmap, level_size, mipmap
from .texture.sample import sample

__all__ = [
    "RasterizeCudaContext", "RasterizeGLContext", "rasterize", "DepthPeeler", "interpolate", "texture",
    "texture_construct_mip", "antialias", "antialias_construct_topology_hash", "get_log_level", "set_log_level",
]

_FILTERS = {"nearest": "nearest", "linear": "bilinear", "linear-mipmap-nearest": "nearest-mip",
            "linear-mipmap-linear": "trilinear", "anisotropic": "anisotropic", "ewa": "ewa"}
_MIP_MODES = ("linear-mipmap-nearest", "linear-mipmap-linear", "anisotropic", "ewa")
_BOUNDARIES = {"wrap": "repeat", "clamp": "clamp", "zero": "border", "mirror": "mirror"}
_FLOATS = (torch.float32, torch.float64)


# --------------------------------------------------------------------------
# contexts and logging


class RasterizeCudaContext:
    """Stands in for nvdiffrast's CUDA rasterizer context; difftex needs no context.

    Args:
        device: accepted for compatibility and kept as ``self.device``; the
            ops run on the device of their input tensors.
    """

    output_db = True

    def __init__(self, device: Union[torch.device, str, int, None] = None):
        self.device = None if device is None else torch.device(device)


class RasterizeGLContext(RasterizeCudaContext):
    """Stands in for nvdiffrast's OpenGL rasterizer context.

    Args:
        output_db: as nvdiffrast: with False, ``rasterize`` returns an empty
            [B, H, W, 0] tensor in place of the barycentric derivatives.
        mode: "automatic" or "manual"; ``set_context`` / ``release_context``
            are accepted and do nothing.
        device: kept as ``self.device``.
    """

    def __init__(self, output_db: bool = True, mode: str = "automatic",
                 device: Union[torch.device, str, int, None] = None):
        if mode not in ("automatic", "manual"):
            raise ValueError(f"mode: expected 'automatic' or 'manual', got {mode!r}")
        super().__init__(device)
        self.output_db = bool(output_db)
        self.mode = mode

    def set_context(self) -> None:
        """No-op (there is no OpenGL context)."""

    def release_context(self) -> None:
        """No-op (there is no OpenGL context)."""


_log_level = 1


def get_log_level() -> int:
    """The current log level (0 info, 1 warning, 2 error, 3 fatal); difftex logs nothing itself."""
    return _log_level


def set_log_level(level: int) -> None:
    """Set the log level returned by :func:`get_log_level` (an int, as nvdiffrast takes)."""
    global _log_level
    if isinstance(level, bool) or not isinstance(level, numbers.Integral):
        raise TypeError(f"level: expected an int, got {type(level).__name__}")
    _log_level = int(level)


# --------------------------------------------------------------------------
# checks


def _check_ctx(glctx: object) -> RasterizeCudaContext:
    if not isinstance(glctx, RasterizeCudaContext):
        raise TypeError(f"glctx: expected a RasterizeCudaContext or RasterizeGLContext of difftex.nvdiffrast, "
                        f"got {type(glctx).__name__}")
    return glctx


def _check_pos(name: str, t: object, ndim: Sequence[int], shape_doc: str) -> Tensor:
    t = check_float(name, t, ndim, shape_doc=shape_doc)
    if t.dtype not in _FLOATS:
        raise TypeError(f"{name}: expected float32 (or float64){' ' + shape_doc}, got {describe(t)}")
    return t


def _check_int32(name: str, t: object, shape_doc: str) -> Tensor:
    if not isinstance(t, Tensor):
        raise TypeError(f"{name}: expected an int32 tensor {shape_doc}, got {type(t).__name__}")
    if t.dtype != torch.int32:
        raise TypeError(f"{name}: expected dtype torch.int32 {shape_doc} (as nvdiffrast), got {describe(t)}")
    if t.dim() != 2:
        raise ValueError(f"{name}: expected a 2-D tensor {shape_doc}, got {describe(t)}")
    return t


def _check_tri(tri: object, num_vertices: int, device: torch.device) -> Tensor:
    tri = _check_int32("tri", tri, "[num_triangles, 3]")
    if tri.shape[1] != 3:
        raise ValueError(f"tri: expected shape [num_triangles, 3], got {describe(tri)}")
    if tri.device != device:
        raise ValueError(f"tri: expected device {device} like pos, got {describe(tri)}")
    if tri.numel() and (int(tri.min()) < 0 or int(tri.max()) >= num_vertices):
        raise ValueError(f"tri: indices must lie in [0, {num_vertices - 1}] (the vertices of pos), "
                         f"got values in [{int(tri.min())}, {int(tri.max())}]")
    return tri.long()


def _check_rast(rast: object) -> Tensor:
    rast = check_float("rast", rast, 4, last=4, shape_doc="[minibatch_size, height, width, 4]")
    return rast


# --------------------------------------------------------------------------
# rasterize


_FLIP_Y = (1.0, -1.0, 1.0, 1.0)


def _flip_y(pos: Tensor) -> Tensor:
    """Clip space mirrored in y: difftex's row r of it is nvdiffrast's row r (bottom first), with no image flip."""
    return pos * pos.new_tensor(_FLIP_Y)


def _packer(offset: int, output_db: bool, grad_db: bool) -> Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]:
    """The ``emit`` of geometry.raster's layers: nvdiffrast's (rast, rast_db) of one layer of the y-mirrored
    positions, ids + 1 (+ range offset), from the native kernel in that layout or from difftex fragments."""

    def emit(pos: Tensor, faces: Tensor, tri_id: Tensor) -> tuple[Tensor, Tensor]:
        # Without output_db the derivatives are neither computed nor stored.
        packed = packed_fragments(pos, faces, tri_id, offset, derivatives=output_db)
        if packed is not None:
            rast, db, idx = packed
        else:
            frags = fragments_of(pos, faces, tri_id, derivatives=output_db)
            idx = frags._compact[0]
            ids = frags.tri_id + 1  # background -1 -> 0
            if offset:
                ids = torch.where(ids > 0, ids + offset, 0)
            # z/w passes no gradient to pos (nvdiffrast's documentation).
            rast = torch.stack([frags.bary[..., 0], frags.bary[..., 1], frags.depth.detach(),
                                ids.to(frags.bary.dtype)], -1)
            # Rows of the mirrored image run up the real one: d/d(row) there is nvdiffrast's d/dY.
            dx, dy = frags.bary_dx, frags.bary_dy
            db = None if dx is None else torch.stack([dx[..., 0], dy[..., 0], dx[..., 1], dy[..., 1]], -1)
        # interpolate() reads the covered pixels from here while rast is
        # unchanged (same object, same version counter) instead of searching
        # rast's ids again.
        if not rast.is_inference():  # inference tensors have no version counter
            rast._difftex_covered = (idx, rast._version)
        if not output_db:
            return rast, rast.new_zeros(rast.shape[:3] + (0,))
        return rast, (db if grad_db else db.detach())

    return emit


def _check_resolution(resolution: object) -> tuple[int, int]:
    if (not isinstance(resolution, (tuple, list)) or len(resolution) != 2
            or not all(isinstance(r, numbers.Integral) and not isinstance(r, bool) for r in resolution)):
        raise TypeError(f"resolution: expected an integer tuple (height, width), got {resolution!r}")
    return int(resolution[0]), int(resolution[1])


def _raster_layers(glctx: object, pos: object, tri: object, resolution: object, ranges: object,
                   grad_db: bool) -> list[Iterator[tuple[Tensor, Tensor]]]:
    """Per minibatch piece (instanced: one piece; range mode: one per range) an iterator of its depth layers as
    nvdiffrast's (rast, rast_db), nearest first."""
    ctx = _check_ctx(glctx)
    pos = _check_pos("pos", pos, (2, 3), "[num_vertices, 4] (range mode) or [minibatch_size, num_vertices, 4]")
    if pos.shape[-1] != 4:
        raise ValueError(f"pos: expected last dimension 4 (clip-space x, y, z, w), got {describe(pos)}")
    faces = _check_tri(tri, pos.shape[-2], pos.device)
    hw = _check_resolution(resolution)
    pos = _flip_y(pos)
    if pos.dim() == 3:
        return [visible_layers(pos, faces, hw, False, _packer(0, ctx.output_db, grad_db))]
    if ranges is None:
        raise ValueError("ranges: required in range mode (pos [num_vertices, 4]): expected an int32 CPU tensor "
                         "[minibatch_size, 2] of (start, count), got None")
    ranges = _check_int32("ranges", ranges, "[minibatch_size, 2]")
    if ranges.shape[1] != 2 or ranges.device.type != "cpu":
        raise ValueError(f"ranges: expected an int32 CPU tensor [minibatch_size, 2] of (start, count), "
                         f"got {describe(ranges)}")
    if ranges.shape[0] == 0:  # an empty minibatch: as instanced mode with none
        return [visible_layers(pos[None][:0], faces, hw, False, _packer(0, ctx.output_db, grad_db))]
    pieces = []
    for start, count in ranges.tolist():
        if start < 0 or count < 0 or start + count > faces.shape[0]:
            raise ValueError(f"ranges: range (start {start}, count {count}) lies outside tri's "
                             f"{faces.shape[0]} triangles")
        pieces.append(visible_layers(pos, faces[start:start + count], hw, False,
                                     _packer(start, ctx.output_db, grad_db)))
    return pieces


def _next_layer(pieces: list[Iterator[tuple[Tensor, Tensor]]]) -> tuple[Tensor, Tensor]:
    """The next layer of every piece, joined along the minibatch."""
    layer = [next(p) for p in pieces]
    if len(layer) == 1:
        return layer[0]
    return torch.cat([r for r, _ in layer]), torch.cat([d for _, d in layer])


def rasterize(glctx: RasterizeCudaContext, pos: Tensor, tri: Tensor, resolution: Sequence[int],
              ranges: Optional[Tensor] = None, grad_db: bool = True) -> tuple[Tensor, Tensor]:
    """Rasterize triangles (nvdiffrast's ``rasterize``) with difftex's exact z-buffer rasterizer.

    Args:
        glctx: a :class:`RasterizeCudaContext` or :class:`RasterizeGLContext`.
        pos: clip-space positions, float32 (or float64): [minibatch_size,
            num_vertices, 4] (instanced mode) or [num_vertices, 4] (range mode).
        tri: [num_triangles, 3] int32.
        resolution: (height, width).
        ranges: range mode only: [minibatch_size, 2] int32 on the CPU, (start,
            count) into ``tri`` per minibatch index; ignored in instanced mode.
        grad_db: propagate gradients of ``rast_db`` into ``pos``.

    Returns:
        ``(rast, rast_db)``, both [minibatch_size, height, width, 4] with row 0
        at the bottom of the image: rast = (u, v, z/w, triangle_id + 1), all
        zero where no triangle is; rast_db = (du/dX, du/dY, dv/dX, dv/dY) in
        per-pixel units (X right, Y up), or [.., 0] when the context was made
        with ``output_db=False``.

    u, v and rast_db are differentiable w.r.t. ``pos``; z/w and the ids are
    not. Raises TypeError for a wrong context, dtype (``tri`` and ``ranges``
    must be int32) or resolution type, ValueError naming the argument for a
    wrong shape, out-of-range index or range.
    """
    return _next_layer(_raster_layers(glctx, pos, tri, resolution, ranges, grad_db))


class DepthPeeler:
    """Depth peeling (nvdiffrast's ``DepthPeeler``): a context manager whose
    :meth:`rasterize_next_layer` returns the nearest, then the next nearest,
    ... surface per pixel. Arguments as :func:`rasterize`; the first layer
    equals :func:`rasterize`'s output and each further layer costs about one
    rasterization (:func:`difftex.geometry.peel`).

    One difference: nvdiffrast culls every surface point at the same or a
    closer depth than the layers already reported, so of two exactly
    coplanar triangles it reports one; difftex reports both, one per layer,
    lowest triangle id first.
    """

    def __init__(self, glctx: RasterizeCudaContext, pos: Tensor, tri: Tensor, resolution: Sequence[int],
                 ranges: Optional[Tensor] = None, grad_db: bool = True):
        self._args = (glctx, pos, tri, resolution, ranges)
        self._grad_db = grad_db
        self._layers: Optional[list] = None

    def __enter__(self) -> "DepthPeeler":
        glctx, pos, tri, resolution, ranges = self._args
        self._layers = _raster_layers(glctx, pos, tri, resolution, ranges, self._grad_db)
        return self

    def __exit__(self, *exc: object) -> None:
        self._layers = None

    def rasterize_next_layer(self) -> tuple[Tensor, Tensor]:
        """The next depth layer as ``(rast, rast_db)`` like :func:`rasterize`; all zero past the last one.

        Raises RuntimeError outside the ``with`` block.
        """
        if self._layers is None:
            raise RuntimeError("DepthPeeler.rasterize_next_layer: call it inside `with DepthPeeler(...) as peeler:`")
        return _next_layer(self._layers)


# --------------------------------------------------------------------------
# interpolate


def _corner_values(attr: Tensor, corners: Tensor, batch: Tensor) -> Tensor:
    """Attributes at covered pixels' triangle corners [N, 3, A], from attr [V, A] or [B | 1, V, A]."""
    A = attr.shape[-1]
    if attr.dim() == 3 and attr.shape[0] > 1:
        corners = corners + (batch * attr.shape[1])[:, None]
    return attr.reshape(-1, A).index_select(0, corners.reshape(-1)).view(-1, 3, A)


def interpolate(attr: Tensor, rast: Tensor, tri: Tensor, rast_db: Optional[Tensor] = None,
                diff_attrs: Union[None, str, Sequence[int]] = None) -> tuple[Tensor, Tensor]:
    """Interpolate vertex attributes (nvdiffrast's ``interpolate``).

    Args:
        attr: float32 (or float64) [num_vertices, num_attributes] (range mode)
            or [minibatch_size | 1, num_vertices, num_attributes] (instanced).
        rast: [minibatch_size, height, width, 4] from :func:`rasterize`.
        tri: [num_triangles, 3] int32, the ``tri`` given to rasterize.
        rast_db: optional [minibatch_size, height, width, 4] from rasterize.
        diff_attrs: with ``rast_db``, the attribute indices whose image-space
            derivatives to return, or "all".

    Returns:
        ``(out, out_da)``: out [minibatch_size, height, width, num_attributes]
        = u a0 + v a1 + (1 - u - v) a2, zero where ``rast``'s id is 0; out_da
        [minibatch_size, height, width, 2 * len(diff_attrs)] = (dA/dX, dA/dY)
        per selected attribute, or an empty [..., 0] tensor.

    Differentiable w.r.t. attr, rast's (u, v) and rast_db. Raises TypeError on
    bad dtypes (``tri`` must be int32), ValueError naming the argument on bad
    shapes, ids past ``tri`` or attribute indices out of range.
    """
    rast = _check_rast(rast)
    attr = _check_pos("attr", attr, (2, 3), "[num_vertices, num_attributes] or "
                      "[minibatch_size, num_vertices, num_attributes]")
    check_same("attr", attr, "rast", rast)
    B, H, W, _ = rast.shape
    if attr.dim() == 3 and attr.shape[0] not in (1, B):
        raise ValueError(f"attr: expected minibatch size 1 or {B} like rast, got {describe(attr)}")
    faces = _check_tri(tri, attr.shape[-2], attr.device)
    # Covered pixels only, scattered into zeros: background pixels get exact
    # zeros and no gradient, and the cost follows the coverage.
    covered = None if rast.is_inference() else getattr(rast, "_difftex_covered", None)  # see _packer
    if covered is not None and covered[1] == rast._version:
        idx = covered[0]
    else:
        idx = torch.nonzero((rast[..., 3].detach() > 0).view(-1)).squeeze(1)
    uvc = rast.reshape(-1, 4).index_select(0, idx)  # (u, v, z, id + 1) of the covered pixels
    ids = uvc[:, 3].detach().round().long() - 1
    if ids.numel() and int(ids.max()) >= faces.shape[0]:
        raise ValueError(f"rast: triangle id {int(ids.max()) + 1} exceeds tri's {faces.shape[0]} triangles; "
                         "pass the tri given to rasterize")
    a0, a1, a2 = _corner_values(attr, faces.index_select(0, ids), torch.div(idx, H * W, rounding_mode="floor")
                                ).unbind(1)
    d0, d1 = a0 - a2, a1 - a2

    def dense(vals: Tensor) -> Tensor:
        out = vals.new_zeros((B * H * W, vals.shape[1]))
        out.index_copy_(0, idx, vals)  # in place on fresh zeros: no second copy
        return out.view(B, H, W, -1)

    out = dense(torch.addcmul(a2, uvc[:, 0:1], d0).addcmul_(uvc[:, 1:2], d1))
    if rast_db is None or diff_attrs is None:
        return out, out.new_zeros((B, H, W, 0))
    rast_db = check_float("rast_db", rast_db, 4, last=4, shape_doc="[minibatch_size, height, width, 4]")
    check_same("rast_db", rast_db, "rast", rast)
    if rast_db.shape != rast.shape:
        raise ValueError(f"rast_db: expected the shape of rast {tuple(rast.shape)}, got {describe(rast_db)}")
    A = attr.shape[-1]
    if isinstance(diff_attrs, str):
        if diff_attrs != "all":
            raise ValueError(f"diff_attrs: expected 'all' or a list of attribute indices, got {diff_attrs!r}")
        sel = list(range(A))
    else:
        sel = [int(i) for i in diff_attrs]
        if any(i < 0 or i >= A for i in sel):
            raise ValueError(f"diff_attrs: indices must lie in [0, {A - 1}], got {list(diff_attrs)}")
    if not sel:  # nothing to differentiate (nvdiffrast takes an empty list as None)
        return out, out.new_zeros((B, H, W, 0))
    if sel != list(range(A)):  # advanced indexing copies: only for a true subset
        d0, d1 = d0[:, sel], d1[:, sel]
    db = rast_db.reshape(-1, 4).index_select(0, idx)
    dX = (db[:, 0:1] * d0).addcmul_(db[:, 2:3], d1)
    dY = (db[:, 1:2] * d0).addcmul_(db[:, 3:4], d1)
    return out, dense(torch.stack([dX, dY], -1).reshape(-1, 2 * len(sel)))


# --------------------------------------------------------------------------
# texture


class _MipStack:
    """The opaque result of :func:`texture_construct_mip`: a difftex pyramid (NCHW levels)."""

    __slots__ = ("pyramid", "cube")

    def __init__(self, pyramid: Union[Mipmap, CubeMipmap], cube: bool):
        self.pyramid = pyramid
        self.cube = cube


def _to_nchw(tex: Tensor, cube: bool) -> Tensor:
    return tex.permute(0, 1, 4, 2, 3) if cube else tex.permute(0, 3, 1, 2)


def _check_tex(tex: object, cube: bool) -> Tensor:
    if cube:
        tex = _check_pos("tex", tex, 5, "[minibatch_size, 6, tex_height, tex_width, tex_channels] "
                         "(boundary_mode='cube')")
        if tex.shape[1] != 6 or tex.shape[2] != tex.shape[3]:
            raise ValueError(f"tex: a cube map needs 6 square faces [minibatch_size, 6, S, S, C], got {describe(tex)}")
    else:
        tex = _check_pos("tex", tex, 4, "[minibatch_size, tex_height, tex_width, tex_channels] "
                         "(5-D cube maps need boundary_mode='cube')")
    return tex


def _pyramid(tex: Tensor, cube: bool, max_mip_level: Optional[int]) -> Union[Mipmap, CubeMipmap]:
    levels = None if max_mip_level is None else max_mip_level + 1
    if cube:
        B, _, S, _, C = tex.shape
        flat = mipmap(tex.reshape(B * 6, S, S, C).permute(0, 3, 1, 2), max_levels=levels).levels
        return CubeMipmap([lv.view(B, 6, C, *lv.shape[-2:]) for lv in flat])
    return mipmap(_to_nchw(tex, False), max_levels=levels)


def _check_max_level(max_mip_level: object) -> Optional[int]:
    if max_mip_level is None:
        return None
    if isinstance(max_mip_level, bool) or not isinstance(max_mip_level, numbers.Integral) or max_mip_level < 0:
        raise ValueError(f"max_mip_level: expected None or an int >= 0, got {max_mip_level!r}")
    return int(max_mip_level)


def texture_construct_mip(tex: Tensor, max_mip_level: Optional[int] = None, cube_mode: bool = False) -> _MipStack:
    """Build a mipmap stack once for a constant texture (nvdiffrast's ``texture_construct_mip``).

    Args:
        tex: as :func:`texture`'s (5-D with ``cube_mode=True``).
        max_mip_level: keep levels 0 .. max_mip_level (default: down to 1 x 1).
        cube_mode: True for a cube map.

    Returns:
        An opaque object for :func:`texture`'s ``mip``. Its levels are
        differentiable functions of ``tex``.
    """
    cube = bool(cube_mode)
    return _MipStack(_pyramid(_check_tex(tex, cube), cube, _check_max_level(max_mip_level)), cube)


def _custom_stack(tex: Tensor, mip: object, cube: bool, max_mip_level: Optional[int]) -> Union[Mipmap, CubeMipmap]:
    """The pyramid of ``tex`` with the levels of ``mip`` (a construct_mip result or a list of NHWC levels)."""
    if isinstance(mip, _MipStack):
        if mip.cube != cube:
            raise ValueError(f"mip: built with cube_mode={mip.cube}, but boundary_mode is "
                             f"{'cube' if cube else 'not cube'}")
        rest = mip.pyramid.levels[1:]
    elif isinstance(mip, (list, tuple)):
        rest = []
        for k, lv in enumerate(mip):
            lv = _check_pos(f"mip[{k}]", lv, 5 if cube else 4, "in the layout of tex")
            check_same(f"mip[{k}]", lv, "tex", tex)
            rest.append(_to_nchw(lv, cube))
    else:
        raise TypeError(f"mip: expected None, the result of texture_construct_mip or a list of tensors, "
                        f"got {type(mip).__name__}")
    if max_mip_level is not None:
        rest = rest[:max_mip_level]
    base = _to_nchw(tex, cube)
    if cube:
        B, _, C, S, _ = base.shape
        for k, lv in enumerate(rest, 1):
            want = (6, C) + level_size(S, S, k)
            if tuple(lv.shape[1:]) != want:
                raise ValueError(f"mip: level {k} must be [B, 6, {want[2]}, {want[3]}, {C}], got {describe(lv)}")
        return CubeMipmap([base] + list(rest))
    B, C, H, W = base.shape
    for k, lv in enumerate(rest, 1):  # named and shaped as given (NHWC), before mipmap() checks them as NCHW
        want = (B, C) + level_size(H, W, k)
        if tuple(lv.shape) != want:
            raise ValueError(f"mip[{k - 1}]: level {k} must be [{B}, {want[2]}, {want[3]}, {C}] (the layout of tex), "
                             f"got shape {tuple(lv.permute(0, 2, 3, 1).shape)}")
    return mipmap([base] + list(rest))


def _unit_footprint(uv: Tensor, shape_hw: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """2D derivatives whose footprint is exactly one texel, so that the level is the bias alone."""
    th, tw = shape_hw
    dx = uv.new_tensor([1.0 / tw, 0.0]).expand(uv.shape)
    dy = uv.new_tensor([0.0, 1.0 / th]).expand(uv.shape)
    return dx, dy


def _cube_at_level(pyramid: CubeMipmap, dirs: Tensor, bias: Tensor, nearest: bool) -> Tensor:
    """A cube map read at the level ``D = clamp(bias, 0, top)`` itself: bilinear per level, blended between
    the two levels around D (or the nearest level, halves rounded up as ``mip_blend`` rounds them for the 2D
    textures).

    Synthetic derivatives cannot fix the level on a cube: near an edge the
    cube's level blends with the neighbouring face's footprint. The gradient
    in the bias is DESIGN.md's derivative from below, as the 2D read gives it:
    ``v_k - v_(k-1)`` at an integer level ``k > 0``, 0 at level 0.
    """
    top = len(pyramid.levels) - 1
    D = level(torch.zeros_like(bias), bias, top + 1)
    if nearest:
        k0, t = torch.floor(D.detach() + 0.5), None
    else:
        # The lower of the two levels blended: ceil(D) - 1, so that an integer level k > 0 is the pair
        # (k - 1, k) at weight 1 on k, whose derivative is the one from below.
        k0 = (torch.ceil(D.detach()) - 1).clamp_(min=0)
        t = D - k0
    out = None
    for k, lv in enumerate(pyramid.levels):
        if t is None:
            w = (k0 == k).to(D.dtype)
        else:
            w = torch.where(k0 == k, 1 - t, torch.where(k0 + 1 == k, t, torch.zeros_like(t)))
        # A level is read where it has weight, or (with a gradient to the bias) where it is one of the pair.
        read = ((k0 == k) | (k0 + 1 == k)) if D.requires_grad and t is not None else w != 0
        if not bool(read.any()):
            continue
        term = cubemap(lv, dirs, filter="bilinear") * w.unsqueeze(1)
        out = term if out is None else out + term
    return out


def texture(tex: Tensor, uv: Tensor, uv_da: Optional[Tensor] = None, mip_level_bias: Optional[Tensor] = None,
            mip: object = None, filter_mode: str = "auto", boundary_mode: Union[str, Sequence[str]] = "wrap",
            max_mip_level: Optional[int] = None, *, max_aniso: float = 16) -> Tensor:
    """Sample a texture (nvdiffrast's ``texture``) with difftex's filters.

    Args:
        tex: [minibatch_size | 1, tex_height, tex_width, C] float32 (or
            float64); with ``boundary_mode='cube'`` a cube map
            [minibatch_size | 1, 6, S, S, C] in OpenGL face order.
        uv: [minibatch_size, height, width, 2] texture coordinates (s, t),
            or [..., 3] directions for a cube map.
        uv_da: optional [..., 4] (ds/dX, ds/dY, dt/dX, dt/dY), or [..., 6]
            for a cube map: the derivatives that choose the mip level.
        mip_level_bias: optional [minibatch_size, height, width]; added to the
            level, or the level itself when ``uv_da`` is None.
        mip: the result of :func:`texture_construct_mip`, or a list of NHWC
            levels 1, 2, ... (a custom stack whose tensors get their own
            gradients); built from ``tex`` when None.
        filter_mode: 'auto' | 'nearest' | 'linear' | 'linear-mipmap-nearest'
            | 'linear-mipmap-linear'; extensions 'anisotropic', 'ewa'.
            'auto' is 'linear-mipmap-linear' when uv_da or mip_level_bias is
            given, else 'linear'.
        boundary_mode: 'wrap' | 'clamp' | 'zero' | 'cube'; extensions
            'mirror' and a (mode_u, mode_v) pair of the 2D modes.
        max_mip_level: use levels 0 .. max_mip_level only.
        max_aniso: extension, for 'anisotropic' and 'ewa' (as difftex.sample).

    Returns:
        [minibatch_size, height, width, C]. Cube lookups in a zero direction
        give 0 and pass no gradient.

    Differentiable w.r.t. tex (through the built mipmap), the custom mip
    levels, uv (not for 'nearest'), uv_da and mip_level_bias (mip filters).
    Raises TypeError / ValueError naming the argument on bad dtypes, shapes
    or modes, and for a mip filter given neither uv_da nor mip_level_bias.
    """
    if not isinstance(filter_mode, str) or (filter_mode != "auto" and filter_mode not in _FILTERS):
        raise ValueError(f"filter_mode: expected one of {('auto',) + tuple(_FILTERS)}, got {filter_mode!r}")
    cube = boundary_mode == "cube"
    if not cube:
        pair = (boundary_mode, boundary_mode) if isinstance(boundary_mode, str) else tuple(boundary_mode)
        if len(pair) != 2 or any(not isinstance(b, str) or b not in _BOUNDARIES for b in pair):
            raise ValueError(f"boundary_mode: expected 'wrap', 'clamp', 'zero', 'cube' (or 'mirror', or a "
                             f"(u, v) pair of the 2D modes), got {boundary_mode!r}")
        wrap = (_BOUNDARIES[pair[0]], _BOUNDARIES[pair[1]])
    tex = _check_tex(tex, cube)
    k = 3 if cube else 2
    uv = _check_pos("uv", uv, 4, f"[minibatch_size, height, width, {k}]")
    if uv.shape[-1] != k:
        raise ValueError(f"uv: expected last dimension {k} for a {'cube map' if cube else '2D texture'}, "
                         f"got {describe(uv)}")
    check_same("uv", uv, "tex", tex)
    max_level = _check_max_level(max_mip_level)
    max_aniso = check_number("max_aniso", max_aniso, 1, MAX_ANISO)
    mode = filter_mode
    if mode == "auto":
        mode = "linear-mipmap-linear" if (uv_da is not None or mip_level_bias is not None) else "linear"
    B, H, W, _ = uv.shape
    if uv_da is not None:
        uv_da = _check_pos("uv_da", uv_da, 4, f"[minibatch_size, height, width, {2 * k}]")
        check_same("uv_da", uv_da, "uv", uv)
        if tuple(uv_da.shape) != (B, H, W, 2 * k):
            raise ValueError(f"uv_da: expected shape {[B, H, W, 2 * k]} (uv's with a last dimension twice as "
                             f"long), got {describe(uv_da)}")
    bias: Union[float, Tensor] = 0.0
    if mip_level_bias is not None:
        mip_level_bias = _check_pos("mip_level_bias", mip_level_bias, 3, "[minibatch_size, height, width]")
        check_same("mip_level_bias", mip_level_bias, "uv", uv)
        if tuple(mip_level_bias.shape) != (B, H, W):
            raise ValueError(f"mip_level_bias: expected shape {[B, H, W]} like uv, got {describe(mip_level_bias)}")
        bias = mip_level_bias
    filt = _FILTERS[mode]
    mipped = mode in _MIP_MODES
    if mipped and uv_da is None and mip_level_bias is None:
        raise ValueError(f"uv_da: filter_mode {filter_mode!r} needs uv_da or mip_level_bias to choose the mip "
                         "level, got neither")
    source: Union[Tensor, Mipmap, CubeMipmap]
    if mipped and mip is not None:
        source = _custom_stack(tex, mip, cube, max_level)
    elif mipped and max_level is not None:
        source = _pyramid(tex, cube, max_level)
    else:
        source = _to_nchw(tex, cube)
    dx = dy = None
    if mipped and uv_da is not None:
        d = uv_da.view(B, H, W, k, 2)
        dx, dy = d[..., 0], d[..., 1]
    elif mipped and cube:
        pyramid = source if isinstance(source, CubeMipmap) else _pyramid(tex, True, None)
        out = _cube_at_level(pyramid, uv, mip_level_bias, mode == "linear-mipmap-nearest")
        return out.permute(0, 2, 3, 1)
    elif mipped:
        dx, dy = _unit_footprint(uv, (tex.shape[1], tex.shape[2]))
    if cube:
        out = cubemap(source, uv, filter=filt, dirs_dx=dx, dirs_dy=dy, lod_bias=bias, max_aniso=max_aniso)
    else:
        out = sample(source, uv, filter=filt, wrap=wrap, uv_dx=dx, uv_dy=dy, lod_bias=bias, max_aniso=max_aniso)
    return out.permute(0, 2, 3, 1)


# --------------------------------------------------------------------------
# antialias


class _TopologyHash:
    """The opaque result of :func:`antialias_construct_topology_hash`: the int64 triangles."""

    __slots__ = ("faces",)

    def __init__(self, faces: Tensor):
        self.faces = faces


def antialias_construct_topology_hash(tri: Tensor) -> _TopologyHash:
    """Prepare ``tri`` once for repeated :func:`antialias` calls (nvdiffrast's topology hash).

    Args:
        tri: [num_triangles, 3] int32.

    Returns:
        An opaque object for ``antialias``'s ``topology_hash``.
    """
    tri = _check_int32("tri", tri, "[num_triangles, 3]")
    if tri.shape[1] != 3:
        raise ValueError(f"tri: expected shape [num_triangles, 3], got {describe(tri)}")
    return _TopologyHash(tri.long())


def antialias(color: Tensor, rast: Tensor, pos: Tensor, tri: Tensor, topology_hash: Optional[_TopologyHash] = None,
              pos_gradient_boost: float = 1.0) -> Tensor:
    """Antialias silhouette edges (nvdiffrast's ``antialias``) with difftex's analytic edge antialiasing.

    Args:
        color: [minibatch_size, height, width, C] image (row 0 at the bottom).
        rast: the ``rast`` that :func:`rasterize` returned for ``pos``, ``tri``.
        pos: the clip-space positions given to rasterize (instanced mode).
        tri: [num_triangles, 3] int32.
        topology_hash: optional result of :func:`antialias_construct_topology_hash`.
        pos_gradient_boost: multiplies the gradient that reaches ``pos``.

    Returns:
        [minibatch_size, height, width, C]; differentiable w.r.t. color and pos.
    """
    color = _check_pos("color", color, 4, "[minibatch_size, height, width, num_channels]")
    rast = _check_rast(rast)
    pos = _check_pos("pos", pos, (2, 3), "[minibatch_size, num_vertices, 4]")
    faces = (_check_tri(tri, pos.shape[-2], pos.device) if topology_hash is None
             else topology_hash.faces.to(pos.device))
    boost = check_number("pos_gradient_boost", pos_gradient_boost, 0)
    if pos.dim() == 2:
        pos = pos.unsqueeze(0).expand(rast.shape[0], -1, -1)
    if boost != 1.0:
        pos = _scale_grad(pos, boost)
    # The Fragments of the y-mirrored clip space that rasterize used: rows as in rast.
    tri_id = rast[..., 3].detach().round().long() - 1
    u, v = rast[..., 0], rast[..., 1]
    bary = torch.stack([u, v, 1 - u - v], -1) * (tri_id >= 0)[..., None]
    zeros = torch.zeros_like(bary)
    frags = Fragments(tri_id=tri_id, bary=bary, depth=rast[..., 2], bary_dx=zeros, bary_dy=zeros)
    return _antialias(color.permute(0, 3, 1, 2), frags, _flip_y(pos), faces).permute(0, 2, 3, 1)


class _ScaleGrad(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: Tensor, s: float) -> Tensor:
        ctx.s = s
        return x.view_as(x)

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor, None]:
        return g * ctx.s, None


def _scale_grad(x: Tensor, s: float) -> Tensor:
    return _ScaleGrad.apply(x, s)

"""Barycentric interpolation of vertex attributes, with analytic screen-space derivatives."""

from __future__ import annotations

import torch
from torch import Tensor

from .._checks import check_index
from .raster import Fragments

__all__ = ["interpolate"]


def interpolate(
    attr: Tensor,
    faces: Tensor,
    frags: Fragments,
    *,
    derivatives: bool = False,
    attr_faces: Tensor | None = None,
) -> Tensor | tuple[Tensor, Tensor, Tensor]:
    """Interpolate per-vertex attributes at every pixel with the rasterized barycentrics.

    Args:
        attr: [V, A] or [B, V, A] float attributes (uv, normals, colours...);
            [V, A] is shared by the batch, B must match the fragments' batch
            (or either may be 1 and broadcasts).
        faces: [F, 3] integer rows of ``attr`` per triangle corner; the same
            ``faces`` given to :func:`difftex.rasterize` for per-vertex
            attributes.
        frags: :class:`difftex.Fragments` from :func:`difftex.rasterize`.
        derivatives: also return the screen-space derivatives.
        attr_faces: optional [F, 3] index into ``attr`` replacing ``faces``
            for face-varying attributes, e.g. the uv indices of an OBJ file
            whose uv seams split vertices (``faces`` then only fixes F).

    Returns:
        [B, H, W, A] attribute per pixel; with ``derivatives=True`` a tuple
        ``(value, attr_dx, attr_dy)`` where ``attr_dx`` / ``attr_dy``
        [B, H, W, A] are d(attr)/d(pixel column) and d(attr)/d(pixel row)
        (rows grow downwards), computed analytically from the
        perspective-correct barycentric Jacobian. For uv they are the
        ``uv_dx``, ``uv_dy`` that choose the mip level. Background pixels
        are zero.

    Gradients reach ``attr`` and, through ``frags.bary`` / ``bary_dx`` /
    ``bary_dy``, the clip-space positions given to rasterize; background
    pixels contribute zero gradient. Raises TypeError on bad dtypes,
    ValueError naming the argument on bad shapes or out-of-range indices,
    and ValueError with ``derivatives=True`` on fragments rasterized with
    ``derivatives=False``.
    """
    if not isinstance(frags, Fragments):
        raise TypeError(f"frags must be a difftex.Fragments, got {type(frags).__name__}")
    if derivatives and (frags.bary_dx is None or frags.bary_dy is None):
        raise ValueError("interpolate(derivatives=True) needs frags with bary_dx and bary_dy: rasterize with "
                         "derivatives=True (the default)")
    if not isinstance(attr, Tensor):
        raise TypeError(f"attr must be a torch.Tensor, got {type(attr).__name__}")
    if not attr.dtype.is_floating_point:
        raise TypeError(f"attr must be a floating point tensor, got dtype {attr.dtype}")
    if attr.dim() == 2:
        attr = attr.unsqueeze(0)
    if attr.dim() != 3:
        raise ValueError(f"attr must have shape [V, A] or [B, V, A], got {tuple(attr.shape)}")
    device = frags.tri_id.device
    attr = attr.to(device)
    index_name = "faces" if attr_faces is None else "attr_faces"
    faces = check_index("faces", faces, attr.shape[1] if attr_faces is None else 2**62, "rows of attr", device)
    if attr_faces is not None:
        attr_faces = check_index("attr_faces", attr_faces, attr.shape[1], "rows of attr", device)
        if attr_faces.shape[0] != faces.shape[0]:
            raise ValueError(
                f"attr_faces must have one row per face of faces ({faces.shape[0]}), got {attr_faces.shape[0]}"
            )
        index = attr_faces
    else:
        index = faces
    tri_id = frags.tri_id
    B, H, W = tri_id.shape
    Ba = attr.shape[0]
    if Ba != B and Ba != 1 and B != 1:
        raise ValueError(f"attr batch {Ba} does not match the fragments' batch {B} (either may be 1)")
    Bo = max(B, Ba)
    F = index.shape[0]
    top = int(tri_id.max()) if tri_id.numel() else -1  # background is -1
    if top >= F:
        raise ValueError(
            f"{index_name} has {F} faces but frags.tri_id refers to face {top}; pass the faces given to rasterize"
        )

    dtype = torch.promote_types(attr.dtype, frags.bary.dtype)
    attr = attr.to(dtype)
    A = attr.shape[-1]
    V = attr.shape[1]
    # Work on covered pixels only and scatter into zeros: background pixels
    # get exact zeros and no gradient, and the cost follows the coverage.
    HW = H * W
    compact = frags._compact
    if compact is not None:  # straight from rasterize: per covered pixel
        idx, w_bary, w_dx, w_dy = compact
    else:
        idx = torch.nonzero(tri_id.reshape(-1) >= 0).squeeze(1)  # flat over [B, H, W]
        w_bary, w_dx, w_dy = (None if w is None else w.reshape(-1, 3).index_select(0, idx)
                              for w in (frags.bary, frags.bary_dx, frags.bary_dy))
    corner = index.index_select(0, tri_id.reshape(-1).index_select(0, idx))  # [N, 3]
    if Ba == 1:
        vals = attr[0].index_select(0, corner.reshape(-1)).view(1, -1, 3, A)
    elif B == Bo:  # one attribute set per fragment batch
        b = torch.div(idx, HW, rounding_mode="floor")
        rows = (b[:, None] * V + corner).reshape(-1)
        vals = attr.reshape(-1, A).index_select(0, rows).view(1, -1, 3, A)
    else:  # B == 1 < Ba: every attribute set on the same fragments
        vals = attr.index_select(1, corner.reshape(-1)).view(Ba, -1, 3, A)
    out_rows = Bo * HW if vals.shape[0] == 1 else HW
    # A non-finite attribute (a degenerate triangle's NaN normal, say) on a fragment that the loss does not
    # see (hidden behind an opaque layer: composite passes it an exact zero gradient) would still send
    # 0 * NaN = NaN to the barycentrics and the positions through the product's backward; _Blend passes an
    # exact zero there instead. Only where some attribute is not finite (one check of the small attr
    # tensor), so the common path stays as it was.
    guard = (torch.is_grad_enabled() and (attr.requires_grad or frags.bary.requires_grad)
             and not bool(torch.isfinite(attr).all()))

    def weigh(wc: Tensor) -> Tensor:
        wc = wc.to(dtype)[None, :, :, None]
        if guard:
            vc = _Blend.apply(vals, wc)
        else:
            # Three products summed explicitly: a reduction over the size-3 axis
            # is several times slower on CPU (measured).
            vc = vals[:, :, 0] * wc[:, :, 0]  # [Bv, N, A]
            vc = vc.addcmul_(vals[:, :, 1], wc[:, :, 1]).addcmul_(vals[:, :, 2], wc[:, :, 2])
        out = torch.zeros((vals.shape[0], out_rows, A), dtype=dtype, device=device)
        out.index_copy_(1, idx, vc)  # in place on fresh zeros: no extra copy
        return out.view(Bo, H, W, A)

    value = weigh(w_bary)
    if not derivatives:
        return value
    return value, weigh(w_dx), weigh(w_dy)


class _Blend(torch.autograd.Function):
    """``sum_k vals[:, :, k] * w[:, :, k]``: vals [Bv, N, 3, A], w [1, N, 3, 1] -> [Bv, N, A].

    The same values as the explicit products; the backward passes an exact zero to ``w`` wherever the
    upstream gradient is zero, rather than ``0 * vals``, which is NaN for a non-finite attribute. A
    non-zero upstream gradient meets the attribute as before (NaN stays in its own pixel). The backward
    is made of differentiable ops, so double backward works.
    """

    @staticmethod
    def forward(ctx, vals: Tensor, w: Tensor) -> Tensor:
        ctx.save_for_backward(vals, w)
        vc = vals[:, :, 0] * w[:, :, 0]
        return vc.addcmul_(vals[:, :, 1], w[:, :, 1]).addcmul_(vals[:, :, 2], w[:, :, 2])

    @staticmethod
    def backward(ctx, g: Tensor):
        vals, w = ctx.saved_tensors
        g3 = g.unsqueeze(2)  # [Bv, N, 1, A]
        g_vals = g3 * w if ctx.needs_input_grad[0] else None
        g_w = None
        if ctx.needs_input_grad[1]:
            g_w = torch.where(g3 == 0, torch.zeros_like(vals), g3 * vals).sum(-1, keepdim=True).sum(0, keepdim=True)
        return g_vals, g_w

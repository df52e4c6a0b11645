"""Barycentric interpolation of vertex attributes, with analytic screen-space derivatives."""

from __future__ import annotations

import torch
from torch import Tensor

from .raster import Fragments

__all__ = ["interpolate"]


def _check_index(faces: Tensor, name: str, num_rows: int, device: torch.device) -> Tensor:
    if not isinstance(faces, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(faces).__name__}")
    if faces.dtype.is_floating_point or faces.dtype.is_complex or faces.dtype == torch.bool:
        raise TypeError(f"{name} must be an integer tensor, got dtype {faces.dtype}")
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"{name} must have shape [F, 3], got {tuple(faces.shape)}")
    faces = faces.to(device=device, dtype=torch.int64)
    if faces.numel() > 0:
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0 or hi >= num_rows:
            raise ValueError(
                f"{name} indices must lie in [0, {num_rows - 1}] (rows of attr), got values in [{lo}, {hi}]"
            )
    return faces


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
    ValueError naming the argument on bad shapes or out-of-range indices.
    """
    if not isinstance(frags, Fragments):
        raise TypeError(f"frags must be a difftex.Fragments, got {type(frags).__name__}")
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
    faces = _check_index(faces, "faces", attr.shape[1] if attr_faces is None else 2**62, device)
    if attr_faces is not None:
        attr_faces = _check_index(attr_faces, "attr_faces", attr.shape[1], device)
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
    mask = tri_id >= 0
    if bool(mask.any()) and int(tri_id.max()) >= F:
        raise ValueError(
            f"{index_name} has {F} faces but frags.tri_id refers to face {int(tri_id.max())}; "
            "pass the faces given to rasterize"
        )

    dtype = torch.promote_types(attr.dtype, frags.bary.dtype)
    attr = attr.to(dtype)
    # Background pixels read face 0 and are then zeroed with a where, which
    # also gives them zero gradient.
    corner = index[tri_id.clamp(min=0)]  # [B, H, W, 3]
    if Ba == 1:
        vals = attr[0][corner]  # [B, H, W, 3, A]
    else:
        bidx = torch.arange(Ba, device=device).view(Ba, 1, 1, 1)
        vals = attr[bidx, corner.expand(Bo, H, W, 3)]
    m = mask[..., None]

    def weigh(w: Tensor) -> Tensor:
        out = (w.to(dtype)[..., :, None] * vals).sum(-2)
        out = torch.where(m, out, torch.zeros((), dtype=dtype, device=device))
        return out.expand(Bo, H, W, attr.shape[-1]) if out.shape[0] != Bo else out

    value = weigh(frags.bary)
    if not derivatives:
        return value
    return value, weigh(frags.bary_dx), weigh(frags.bary_dy)

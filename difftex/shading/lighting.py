"""Blinn-Phong shading with several lights, ambient occlusion, and the texture modes (replace / modulate / decal)."""
from __future__ import annotations

import math
from typing import Optional

import torch
from torch import Tensor

from .._checks import check_float, describe
from .common import Operand, broadcast, check_vectors, dot, operand, unit

MODES = ("replace", "modulate", "decal")


def _positive_power(x: Tensor, s: Tensor) -> Tensor:
    """``max(x, 0) ** s`` for s > 0 with finite gradients everywhere.

    ``torch.pow`` differentiates ``0 ** s`` as ``s * 0 ** (s - 1)`` (infinite
    for fractional s < 1) times 0 = NaN, and its gradient to ``s`` as
    ``0 ** s * log 0`` = NaN; the masked form takes the value 0 and a zero
    gradient where x <= 0 and reads log(1) = 0 there instead.
    """
    pos = x > 0
    safe = torch.where(pos, x, torch.ones_like(x))
    return torch.where(pos, torch.exp(s * torch.log(safe)), torch.zeros_like(x))


def blinn_phong(
    normals: Tensor,
    view_dirs: Tensor,
    light_dirs: Tensor,
    kd: Operand,
    ks: Operand = 0.0,
    shininess: Operand = 32.0,
    *,
    ambient: Operand = 0.0,
    light_colors: Optional[Operand] = None,
    occlusion: Optional[Operand] = None,
    normalized: bool = False,
) -> Tensor:
    """Blinn-Phong shading of points under one or several directional lights.

    Per light ``l`` with colour ``c_l`` and the half vector
    ``h = normalize(l + v)``::

        colour = ambient * kd * occlusion
                 + sum_l c_l * (kd * max(n.l, 0) + ks * max(n.h, 0) ** shininess)

    (the hand formula: no cosine on the specular term and no 1/pi). With
    ``normalized=True`` the energy-normalised form is used instead:
    ``c_l * (kd / pi + ks * (shininess + 8) / (8 pi) * max(n.h, 0) ** shininess) * max(n.l, 0)``,
    whose diffuse lobe reflects at most ``kd`` of the incoming light
    (Akenine-Moller et al., Real-Time Rendering, normalised Blinn-Phong).

    Args:
        normals: [..., 3] surface normals (normalised here; need not be unit).
        view_dirs: [..., 3] directions from the surface to the eye.
        light_dirs: [..., L, 3] directions from the surface to each of L
            lights (dimension -2 is always the light axis: one light is
            [..., 1, 3]); a 1-D [3] is one light for every point. Normalised
            here. ``...`` broadcasts with the normals' and view_dirs' ``...``.
        kd: diffuse albedo [..., C] (e.g. a sampled texture moved to
            channels-last: ``sample(...).movedim(1, -1)``) or a number.
        ks: specular colour [..., C] (a specular map) or a number.
        shininess: Blinn-Phong exponent > 0, a number or a tensor
            broadcasting like ``ks`` (e.g. [..., 1]); fractional values are safe.
        ambient: ambient light colour, a number or [..., C].
        light_colors: [..., L, C] (or [L, C], [L, 1]) colour / intensity of
            each light; None is white (1).
        occlusion: ambient-occlusion factor [..., 1] or [..., C] (a baked AO
            map sampled at the points) multiplying the ambient term; None is 1.
            A baked light map that darkens everything is applied with
            :func:`combine` (``"modulate"``) instead.
        normalized: use the energy-normalised form above.

    Returns:
        [..., C] colour, the broadcast of every operand without the light
        axis (C = 1 where every colour is a number). Same dtype and device as
        ``normals``.

    Differentiable with respect to every tensor argument. The power is
    evaluated as ``where(x > 0, exp(s log x), 0)``, so ``n.h <= 0`` gives an
    exact 0 and a zero gradient, never NaN, even for fractional shininess; a
    light exactly opposite the view (``l + v = 0``) has a zero half vector
    and no specular.

    Raises TypeError naming the argument for a non-float tensor, a dtype
    other than the normals' or a value that is neither number nor tensor;
    ValueError for a last dimension other than 3 on a direction, shapes that
    do not broadcast, a device mismatch, or a shininess that is not > 0.
    """
    check_vectors("normals", normals)
    check_vectors("view_dirs", view_dirs, normals)
    check_vectors("light_dirs", light_dirs, normals)
    if not isinstance(normalized, bool):
        raise TypeError(f"normalized: expected a bool, got {type(normalized).__name__}")
    if light_dirs.dim() == 1:
        light_dirs = light_dirs.unsqueeze(0)
    kd = operand("kd", kd, normals, "[..., C]")
    ks = operand("ks", ks, normals, "[..., C]")
    shininess = operand("shininess", shininess, normals, "[..., C] or [..., 1]")
    ambient = operand("ambient", ambient, normals, "[..., C]")
    if not bool((shininess > 0).all()):
        raise ValueError(f"shininess: expected values > 0, got minimum {float(shininess.min())} ({describe(shininess)})")
    colors = None if light_colors is None else operand("light_colors", light_colors, normals, "[..., L, C]")
    occ = None if occlusion is None else operand("occlusion", occlusion, normals, "[..., 1] or [..., C]")
    if colors is not None and colors.dim() < 2:
        raise ValueError(f"light_colors: expected [..., L, C] with the light axis at -2, got {describe(colors)}")
    L = light_dirs.shape[-2]
    if colors is not None and colors.shape[-2] not in (1, L):
        raise ValueError(f"light_colors: expected {L} lights on dimension -2 like light_dirs "
                         f"{tuple(light_dirs.shape)}, got {describe(colors)}")
    # The point shape (without channel / light axes) every operand must broadcast to.
    point_shapes = {"normals": normals.shape[:-1], "view_dirs": view_dirs.shape[:-1],
                    "light_dirs": light_dirs.shape[:-2]}
    channel_ops = {"kd": kd, "ks": ks, "shininess": shininess, "ambient": ambient}
    if occ is not None:
        channel_ops["occlusion"] = occ
    for k, t in channel_ops.items():
        if t.dim() > 0:
            point_shapes[k] = t.shape[:-1]
    if colors is not None:
        point_shapes["light_colors"] = colors.shape[:-2]
    broadcast(point_shapes)
    channels = {k: t.shape[-1:] for k, t in channel_ops.items() if t.dim() > 0}
    if colors is not None:
        channels["light_colors"] = colors.shape[-1:]
    broadcast(channels)  # every colour has C or 1 channels

    n = unit(normals)
    v = unit(view_dirs)
    lights = unit(light_dirs)
    n_l = dot(n.unsqueeze(-2), lights)  # [..., L, 1]
    h = unit(lights + v.unsqueeze(-2))
    n_h = dot(n.unsqueeze(-2), h)
    per = lambda t: t.unsqueeze(-2) if t.dim() > 0 else t  # a colour operand against [..., L, C]
    spec = _positive_power(n_h, per(shininess))
    diffuse = n_l.clamp_min(0)
    if normalized:
        s = per(shininess)
        lobe = (per(kd) / math.pi + per(ks) * (s + 8) / (8 * math.pi) * spec) * diffuse
    else:
        lobe = per(kd) * diffuse + per(ks) * spec
    if colors is not None:
        lobe = lobe * colors
    out = lobe.sum(-2)
    amb = ambient * kd
    if occ is not None:
        amb = amb * occ
    out = out + amb
    return out


def combine(texture: Tensor, shading: Operand, mode: str = "modulate") -> Tensor:
    """Combine a sampled texture with a shading colour (the fixed-function texture modes).

    * ``"replace"``: ``colour = texture`` (the shading is ignored; the result
      still has the broadcast shape);
    * ``"modulate"``: ``colour = texture * shading``;
    * ``"decal"``: the texture's last channel is its alpha a, the rest its
      colour t: ``colour = a * t + (1 - a) * shading`` (OpenGL's GL_DECAL);
      the texture has one channel more than the shading (or the shading 1).

    Args:
        texture: [..., C] channels-last texture values (``sample(...).movedim(1, -1)``),
            [..., C + 1] with alpha last for "decal".
        shading: [..., C] or [..., 1] shading (e.g. :func:`blinn_phong` with
            ``kd=1``, or a sampled light map), or a number.
        mode: "replace" | "modulate" | "decal".

    Returns:
        [..., C], the broadcast of both (for "decal" without the alpha).

    Differentiable with respect to both (replace: texture only). Raises
    ValueError for an unknown mode, shapes that do not broadcast, a decal
    texture with fewer than 2 channels; TypeError for non-float tensors or
    mixed dtypes.
    """
    check_float("texture", texture, shape_doc="[..., C]")
    if texture.dim() < 1:
        raise ValueError(f"texture: expected [..., C] channels-last, got {describe(texture)}")
    if not isinstance(mode, str) or mode not in MODES:
        raise ValueError(f"mode: unknown mode {mode!r}; expected one of {MODES}")
    shading = operand("shading", shading, texture, "[..., C] or [..., 1]", "texture")
    if mode == "decal":
        if texture.shape[-1] < 2:
            raise ValueError(f"texture: 'decal' needs colour and alpha channels [..., C + 1], got {describe(texture)}")
        colour, alpha = texture[..., :-1], texture[..., -1:]
        broadcast({"texture colour": colour.shape, "shading": shading.shape})
        return alpha * colour + (1 - alpha) * shading
    shape = broadcast({"texture": texture.shape, "shading": shading.shape})
    if mode == "replace":
        return texture.expand(shape)
    return texture * shading

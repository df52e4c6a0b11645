"""Where texture filters fail: sweeps of every difftex filter into the hard cases, with bounds.

Sweeps (each a function returning plain numbers, shared by this script and
tests/experiments/test_stability.py, which runs them at small sizes and asserts the
bounds stated in docs/stability.md):

* :func:`sweep_view_angle`: the grazing plane (:func:`difftex.testing.grazing_plane`)
  from head-on to 89.9 degrees off the normal, PSNR against 16x16
  supersampled bilinear;
* :func:`sweep_minification`: a head-on plane minified 0.5x to 1000x, error
  against the exact box filter of the bilinear texture (:func:`box_mean_bilinear`);
* :func:`sweep_uv_offset`: uv shifted by whole repeats up to 1e6, float32
  and float64, error against the unshifted float64 render;
* :func:`sphere_seam`: the sphere of :func:`difftex.mapping.spherical_uv`
  across its atan2 seam and at a pole, analytic against finite-difference
  derivatives: level and error on the seam pixels;
* :func:`texture_shapes`: 1x1, 1xN, Nx1 and odd-sized textures;
* :func:`bad_derivatives`: zero, infinite and NaN uv derivatives, NaN uv;
* :func:`degenerate_mesh`: zero-area triangles and triangles crossing w = 0
  through rasterize + interpolate + sample, gradients to the clip-space
  positions.

Every lookup goes through :func:`check_lookup`, which also backpropagates
``sum()`` to the texture, uv and the derivatives and reports the gradient
norms in units that make them comparable: the texture gradient's L1 norm
over the number of output values (exactly 1 for a filter whose weights are
positive and sum to one, whatever the footprint), and the per-pixel uv /
derivative gradient over ``C * range * max(H, W)`` (the steepest slope a
texture of that value range can have, per uv unit).

Writes to ``--out`` (default results/stability) stability.png (one panel per
sweep) and stability.md (a markdown table); ``--docs`` copies the chart to
docs/images/stability.png.

    python -m experiments.studies.stability [--threads 1] [--out results/stability] [--small]
"""
from __future__ import annotations

import argparse
import importlib
import math
import time
from pathlib import Path
from typing import Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

import difftex
from difftex.metrics import psnr
from difftex.testing import checker_noise_texture, grazing_plane, icosphere, sphere_mvp, sphere_uv, supersampled

ROOT = Path(__file__).resolve().parents[2]

_sample_mod = importlib.import_module("difftex.texture.options")
FILTERS: tuple[str, ...] = tuple(_sample_mod.FILTERS)
MIP_FILTERS: tuple[str, ...] = tuple(_sample_mod.MIP_FILTERS)

# Sum of |weights| of a lookup: 1 for every filter whose weights are positive
# and sum to one; bicubic's Keys kernel (a = -0.75) has negative lobes, its
# 1-D sum of |w| peaks at 1.375 (t = 1/2), so 1.375^2 in 2-D.
WEIGHT_L1 = {f: 1.0 for f in FILTERS}
WEIGHT_L1["bicubic"] = 1.375 ** 2


def check_lookup(texture: Tensor, uv: Tensor, uv_dx: Optional[Tensor], uv_dy: Optional[Tensor], filter: str,
                 wrap="repeat", reference: Optional[Tensor] = None, mask: Optional[Tensor] = None,
                 **kw) -> dict:
    """Sample, backpropagate ``sum()`` and report finiteness, error and normalised gradient norms.

    Args:
        texture: [1, C, H, W]; uv, uv_dx, uv_dy: [B, Ho, Wo, 2] (derivatives
            may be None for the single-level filters).
        reference: optional [B, C or 1, Ho, Wo] to score against.
        mask: optional [B, 1, Ho, Wo] bool of the pixels to score.

    Returns:
        dict with ``out`` (detached), ``finite`` (outputs finite where uv is),
        ``grads_finite``, ``tex_l1`` (|d sum / d texture|_1 over the number
        of output values), ``uv_grad`` and ``deriv_grad`` (largest per-pixel
        gradient norm over C * range * max(H, W)), ``max_err`` and ``psnr``
        against the reference, and ``lo`` / ``hi`` overshoot of the output
        beyond the texture's value range.
    """
    tex = texture.detach().clone().requires_grad_(True)
    u = uv.detach().clone().requires_grad_(True)
    needs = filter in MIP_FILTERS or (uv_dx is not None and filter not in ("nearest", "bilinear", "bicubic"))
    if needs:
        dx = uv_dx.detach().clone().requires_grad_(True)
        dy = uv_dy.detach().clone().requires_grad_(True)
        out = difftex.sample(tex, u, filter=filter, wrap=wrap, uv_dx=dx, uv_dy=dy, **kw)
    else:
        dx = dy = None
        out = difftex.sample(tex, u, filter=filter, wrap=wrap)
    ok_uv = torch.isfinite(uv).all(-1).unsqueeze(1).expand_as(out)
    finite = bool(torch.isfinite(out[ok_uv]).all())
    nan_where_uv_nan = bool(torch.isnan(out[~ok_uv]).all()) if (~ok_uv).any() else True
    out.masked_fill(~ok_uv, 0).sum().backward()
    C, H, W = texture.shape[1:]
    rng = float(texture.max() - texture.min()) or 1.0
    slope = C * rng * max(H, W)
    n_out = int(ok_uv.sum())
    grads = [g for g in (tex.grad, u.grad, None if dx is None else dx.grad, None if dy is None else dy.grad)
             if g is not None]
    res = dict(out=out.detach(), finite=finite, nan_where_uv_nan=nan_where_uv_nan,
               grads_finite=all(bool(torch.isfinite(g).all()) for g in grads),
               tex_l1=float(tex.grad.abs().sum()) / max(n_out, 1),
               uv_grad=float(u.grad.norm(dim=-1).max()) / slope if u.grad is not None else 0.0,
               deriv_grad=(max(float(dx.grad.norm(dim=-1).max()), float(dy.grad.norm(dim=-1).max())) / slope
                           if dx is not None and dx.grad is not None else 0.0))
    o = out.detach()[ok_uv]
    res["lo"] = float(texture.min() - o.min()) / rng if o.numel() else 0.0
    res["hi"] = float(o.max() - texture.max()) / rng if o.numel() else 0.0
    if reference is not None:
        ref = reference.expand_as(out)
        m = ok_uv if mask is None else (mask.expand_as(out) & ok_uv)
        e = (out.detach() - ref)[m].abs()
        res["max_err"] = float(e.max()) if e.numel() else 0.0
        res["mean_err"] = float(e.mean()) if e.numel() else 0.0
        res["psnr"] = psnr(out.detach(), ref, mask=m)
    return res


# --------------------------------------------------------------------------
# exact box filter of the bilinear texture (axis-aligned footprints, repeat)
# --------------------------------------------------------------------------


def _periodic_antiderivative(t: Tensor, y: Tensor) -> Tensor:
    """G(y) = int_0^y f for the periodic piecewise-linear f with f(k) = t[..., k mod n] at integers k.

    t: [..., n]; y: [..., P] (same leading dims). Float64. The cumulative
    trapezoids give G at the knots; between them G is quadratic.
    """
    n = t.shape[-1]
    t_next = torch.roll(t, -1, -1)
    c = torch.cat([torch.zeros_like(t[..., :1]), torch.cumsum((t + t_next) / 2, -1)], -1)  # [..., n + 1]
    S = c[..., -1:]
    k = torch.floor(y)
    d = y - k
    q = torch.floor(k / n)
    kk = (k - q * n).long().clamp(0, n - 1)
    tk = torch.gather(t, -1, kk)
    tk1 = torch.gather(t_next, -1, kk)
    return q * S + torch.gather(c, -1, kk) + tk * d + 0.5 * d * d * (tk1 - tk)


def box_mean_bilinear(texture: Tensor, uv: Tensor, half_u: Tensor, half_v: Tensor) -> Tensor:
    """Exact mean of the bilinearly interpolated texture (repeat) over axis-aligned uv boxes.

    The box of pixel p is ``[u - half_u, u + half_u] x [v - half_v, v + half_v]``.
    Bilinear interpolation is a tensor product of hat functions, so the box
    integral separates: integrate every texel row's piecewise-linear
    interpolant over the u interval (:func:`_periodic_antiderivative`), then
    the piecewise-linear interpolant of those row integrals over the v
    interval.  Exact up to float64 rounding, for any box size (1000 repeats
    included), which no supersampled reference is.

    Args:
        texture: [1, C, H, W]; uv: [P, 2]; half_u, half_v: [P] half sizes in uv.

    Returns:
        [C, P] float64.
    """
    tex = texture[0].double()
    C, H, W = tex.shape
    uv = uv.double()
    x0 = (uv[:, 0] - half_u.double()) * W - 0.5  # texel-centre coordinates: knot k at texel k's centre
    x1 = (uv[:, 0] + half_u.double()) * W - 0.5
    y0 = (uv[:, 1] - half_v.double()) * H - 0.5
    y1 = (uv[:, 1] + half_v.double()) * H - 0.5
    P = uv.shape[0]
    rows = tex.reshape(C * H, W)
    xs = torch.stack([x0, x1]).reshape(1, 2 * P).expand(C * H, -1)
    Gx = _periodic_antiderivative(rows, xs.contiguous()).view(C, H, 2, P)
    a = (Gx[:, :, 1] - Gx[:, :, 0]).permute(0, 2, 1).contiguous()  # [C, P, H]: each row's integral over [x0, x1]
    ys = torch.stack([y0, y1], -1).view(1, P, 2).expand(C, P, 2).contiguous()
    Gy = _periodic_antiderivative(a, ys)  # [C, P, 2]
    return (Gy[..., 1] - Gy[..., 0]) / ((x1 - x0) * (y1 - y0))


# --------------------------------------------------------------------------
# sweeps
# --------------------------------------------------------------------------


def sweep_view_angle(angles: Sequence[float] = (0, 45, 70, 80, 85, 88, 89, 89.5, 89.9), res: int = 64,
                     tex_size: int = 256, filters: Sequence[str] = FILTERS) -> list[dict]:
    """Grazing plane at ``angle`` degrees off the normal (pitch 90 - angle), PSNR vs 16x16 supersampling.

    The field of view is min(36, pitch) degrees, so the top row looks
    pitch / 2 below the horizon and every pixel hits the plane (at 89.9 the
    plane is hit ~1100 units away: uv ~ 600, footprints ~1000:1).
    """
    tex = checker_noise_texture(tex_size)
    rows = []
    for a in angles:
        pitch = 90.0 - a
        fov = min(36.0, pitch)
        uv, dx, dy = grazing_plane(res, pitch, 1.0, fov_deg=fov)
        ref = supersampled(tex, grazing_plane(res, pitch, 1.0, fov_deg=fov, ss=16)[0], 16, "repeat")
        for f in filters:
            r = check_lookup(tex, uv, dx, dy, f, "repeat", reference=ref)
            r.pop("out")
            rows.append(dict(sweep="view angle", x=a, filter=f, **r))
    return rows


def head_on(res: int, texels_per_pixel: float, tex_h: int, tex_w: int, offset=(0.3, 0.7),
            dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor, Tensor]:
    """uv, uv_dx, uv_dy of a head-on (orthographic) view: square pixels ``texels_per_pixel`` texels wide."""
    r = torch.arange(res, dtype=torch.float64)
    s_u, s_v = texels_per_pixel / tex_w, texels_per_pixel / tex_h
    u = offset[0] + (r.view(1, -1) + 0.5) * s_u
    v = offset[1] + (r.view(-1, 1) + 0.5) * s_v
    uv = torch.stack(torch.broadcast_tensors(u, v), -1).unsqueeze(0)
    dx = torch.tensor([s_u, 0.0], dtype=torch.float64).expand(1, res, res, 2)
    dy = torch.tensor([0.0, s_v], dtype=torch.float64).expand(1, res, res, 2)
    return uv.to(dtype), dx.to(dtype).contiguous(), dy.to(dtype).contiguous()


def sweep_minification(factors: Sequence[float] = (0.5, 1, 2, 4, 16, 64, 256, 1000), res: int = 32,
                       tex_size: int = 256, filters: Sequence[str] = FILTERS) -> list[dict]:
    """Head-on plane minified ``factor`` texels a pixel, error against the exact box mean (repeat)."""
    tex = checker_noise_texture(tex_size)
    rows = []
    for m in factors:
        uv, dx, dy = head_on(res, m, tex_size, tex_size)
        exact = box_mean_bilinear(tex, uv.reshape(-1, 2), (dx[..., 0] / 2).reshape(-1), (dy[..., 1] / 2).reshape(-1))
        ref = exact.float().view(1, -1, res, res)
        for f in filters:
            r = check_lookup(tex, uv, dx, dy, f, "repeat", reference=ref)
            r.pop("out")
            rows.append(dict(sweep="minification", x=m, filter=f, **r))
    return rows


def sweep_uv_offset(offsets: Sequence[float] = (0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6), res: int = 32,
                    tex_size: int = 256, texels_per_pixel: float = 3.0,
                    filters: Sequence[str] = FILTERS) -> list[dict]:
    """uv shifted by a whole number of repeats: the image must not change; float32 and float64.

    Error is measured against the float64 render at offset 0.  In float32
    the input uv itself is rounded to ulp(offset) (0.0625 at 1e6: 16 texels
    of a 256 texture), so the float32 error grows like offset * 2^-24 *
    texels * slope; ``excess`` is the float32 error beyond that input
    rounding (float64 sampling of the same rounded uv), i.e. what the
    library adds.
    """
    tex64 = checker_noise_texture(tex_size, dtype=torch.float64)
    tex32 = tex64.float()
    uv0, dx, dy = head_on(res, texels_per_pixel, tex_size, tex_size, dtype=torch.float64)
    rows = []
    for f in filters:
        ref = check_lookup(tex64, uv0, dx, dy, f)["out"]
        for off in offsets:
            uv64 = uv0 + off
            r64 = check_lookup(tex64, uv64, dx, dy, f)
            uv32 = uv64.float()
            r32 = check_lookup(tex32, uv32, dx.float(), dy.float(), f)
            same_input = difftex.sample(tex64, uv32.double(), filter=f, uv_dx=dx, uv_dy=dy) \
                if f in MIP_FILTERS else difftex.sample(tex64, uv32.double(), filter=f)
            for dt, r in (("float64", r64), ("float32", r32)):
                err = float((r["out"].double() - ref).abs().max())
                excess = float((r32["out"].double() - same_input).abs().max()) if dt == "float32" else 0.0
                rows.append(dict(sweep="uv offset", x=off, filter=f, dtype=dt, err=err, excess=excess,
                                 finite=r["finite"], grads_finite=r["grads_finite"], tex_l1=r["tex_l1"],
                                 uv_grad=r["uv_grad"], deriv_grad=r["deriv_grad"]))
    return rows


SEAM_VIEW = (-1.0, 0.0, 0.8)  # eye direction: the seam (the -x meridian) runs down the image centre, +z pole at top


def sphere_seam(res: int = 64, tex_size: int = 256, minification: float = 2.0,
                filters: Sequence[str] = FILTERS, ss: int = 16) -> dict:
    """The spherical map across its seam and near its pole, analytic against finite-difference derivatives.

    Returns a dict with, per derivative kind ("analytic", "finite"): the
    mip level (:func:`difftex.lod`) on the seam pixels and its median over
    the rest, the coarsest level, and per filter the mean |error| against
    ss x ss supersampling on seam pixels and elsewhere, plus the
    :func:`check_lookup` numbers (finiteness, gradients) over the whole
    sphere, pole included.  Seam pixels: covered pixels whose u lies within
    1.5 pixel footprints of the seam (u = 0 = 1) and |v - 1/2| < 0.3; the
    rest are the other covered pixels of that band.
    """
    # Rolled by half a check so that the seam (u = 0) falls mid-check: a
    # check edge there would raise every filter's error on the seam pixels
    # for a reason that has nothing to do with the seam.
    tex = torch.roll(checker_noise_texture(tex_size, checks=8), tex_size // 16, dims=-1)
    verts, faces = icosphere(4)
    mvp = sphere_mvp(minification, res, tex_size, direction=SEAM_VIEW)
    uv16, _, _, m16 = sphere_uv(mvp, res * ss, verts, faces)
    wrap = ("repeat", "clamp")
    ref = supersampled(tex, uv16, ss, wrap)
    base = sphere_uv(mvp, res, verts, faces)
    out: dict = {"levels": difftex.mipmap(tex).__len__()}
    for kind in ("analytic", "finite"):
        uv, dx, dy, mask = base
        # The footprint of the analytic derivatives decides which pixels are seam pixels.
        du = dx[..., 0].abs() + dy[..., 0].abs()
        if kind == "finite":  # forward differences of uv between neighbouring pixels (as sphere_uv's)
            m = mask.squeeze(1).unsqueeze(-1)
            dx = torch.cat([uv[:, :, 1:] - uv[:, :, :-1], uv[:, :, -1:] - uv[:, :, -2:-1]], 2) * m
            dy = torch.cat([uv[:, 1:] - uv[:, :-1], uv[:, -1:] - uv[:, -2:-1]], 1) * m
        full = mask & (F.avg_pool2d(m16.float(), ss) > 1 - 1e-6)
        u = uv[..., 0]
        # Away from the poles (|v - 1/2| < 0.3), where the meridians converge
        # and footprints grow for a reason of their own (the pole sweep).
        band = ((uv[..., 1] - 0.5).abs() < 0.3) & full[:, 0]
        seam = (torch.minimum(u, 1 - u) < 1.5 * du) & band
        lod = difftex.lod(dx, dy, tex)
        rest = band & ~seam
        ko = dict(seam_pixels=int(seam.sum()), lod_seam_max=float(lod[seam].max()),
                  lod_rest_median=float(lod[rest].median()), lod_rest_max=float(lod[rest].max()), lod=lod, seam=seam, full=full, uv=uv)
        for f in filters:
            r = check_lookup(tex, uv, dx, dy, f, wrap, reference=ref, mask=full)
            e = (r["out"] - ref).abs().mean(1)
            ko[f] = dict(err_seam=float(e[seam].mean()), err_rest=float(e[rest].mean()),
                         out=r.pop("out"), **{k: r[k] for k in ("finite", "grads_finite", "tex_l1", "uv_grad",
                                                               "deriv_grad", "psnr")})
        out[kind] = ko
    out["reference"] = ref
    # The pole: look straight down the +z axis at 2x minification; the
    # pixel at the pole has r < EPS and zero derivatives (level 0).
    pmvp = sphere_mvp(minification, res + 1, tex_size, direction=(0.0, 1e-3, 1.0))
    uv, dx, dy, mask = sphere_uv(pmvp, res + 1, verts, faces)
    uvp16, _, _, mp16 = sphere_uv(pmvp, (res + 1) * ss, verts, faces)
    pref = supersampled(tex, uvp16, ss, wrap)
    pfull = mask & (F.avg_pool2d(mp16.float(), ss) > 1 - 1e-6)
    out["pole"] = {}
    for f in filters:
        r = check_lookup(tex, uv, dx, dy, f, wrap, reference=pref, mask=pfull)
        r.pop("out")
        out["pole"][f] = r
    return out


def texture_shapes(shapes: Sequence[tuple[int, int]] = ((1, 1), (1, 7), (7, 1), (3, 5), (17, 33), (1, 64)),
                   filters: Sequence[str] = FILTERS, n: int = 256, seed: int = 0,
                   wraps: Sequence[str] = ("repeat", "clamp", "mirror")) -> list[dict]:
    """Random uv in [-2, 3] with footprints from 0.01 to 1e4 texels on tiny, thin and odd textures.

    Reports per shape and filter: finiteness, gradients, ``const_err`` (1x1:
    |out - the texel|), ``axis_err`` (H = 1 or W = 1: change of the output
    when the degenerate coordinate moves, derivatives fixed), ``mean_err``
    (|out - texture mean| for footprints of 1e4 texels, mip filters).
    """
    g = torch.Generator().manual_seed(seed)
    rows = []
    for H, W in shapes:
        tex = torch.rand(1, 3, H, W, generator=g, dtype=torch.float64).float()
        uv = torch.rand(1, 1, n, 2, generator=g) * 5 - 2
        scale = 10 ** (torch.rand(1, 1, n, 1, generator=g) * 6 - 2) / max(H, W)
        ang = torch.rand(1, 1, n, 1, generator=g) * math.pi
        ratio = 10 ** (torch.rand(1, 1, n, 1, generator=g) * 2)
        dx = torch.cat([torch.cos(ang), torch.sin(ang)], -1) * scale
        dy = torch.cat([-torch.sin(ang), torch.cos(ang)], -1) * scale / ratio
        for wrap in wraps:
            for f in filters:
                r = check_lookup(tex, uv, dx, dy, f, wrap)
                o = r.pop("out")
                row = dict(sweep="texture shape", x=f"{H}x{W}", filter=f, wrap=wrap, **r)
                if H == 1 and W == 1:
                    row["const_err"] = float((o - tex.view(1, 3, 1, 1)).abs().max())
                if H == 1 or W == 1:
                    moved = uv.clone()
                    moved[..., 1 if H == 1 else 0] = 0.37
                    kw = dict(uv_dx=dx, uv_dy=dy) if f in MIP_FILTERS else {}
                    o2 = difftex.sample(tex, moved, filter=f, wrap=wrap, **kw)
                    row["axis_err"] = float((o - o2).abs().max())
                if f in MIP_FILTERS:
                    big = torch.full_like(dx, 0.0)
                    big[..., 0] = 1e4
                    bigy = torch.flip(big, [-1])
                    o3 = difftex.sample(tex, uv, filter=f, wrap=wrap, uv_dx=big, uv_dy=bigy)
                    row["mean_err"] = float((o3 - tex.mean((-1, -2)).view(1, 3, 1, 1)).abs().max())
                rows.append(row)
    return rows


def bad_derivatives(filters: Sequence[str] = MIP_FILTERS, tex_size: int = 32, seed: int = 0) -> list[dict]:
    """Zero, infinite and NaN derivatives (and NaN / infinite uv) among good pixels.

    Reports per filter and kind: finiteness of outputs and gradients, the
    change of the good pixels' outputs and texture gradient against a run
    without the bad pixels (``leak``), the bad pixels' derivative gradient
    (must be 0), and the distance of the bad pixels' outputs from what the
    docs promise: zero / NaN derivatives = level 0 (the filter at a vanishing
    footprint: bilinear, except EWA's texel-wide Gaussian), infinite =
    the coarsest level (the texture mean for a power-of-two size).
    """
    g = torch.Generator().manual_seed(seed)
    tex = torch.rand(1, 3, tex_size, tex_size, generator=g)
    n = 32
    uv = torch.rand(1, 1, n, 2, generator=g) * 2 - 0.5
    dx = torch.tensor([3.0 / tex_size, 0.5 / tex_size]).expand(1, 1, n, 2).clone()
    dy = torch.tensor([-0.5 / tex_size, 2.0 / tex_size]).expand(1, 1, n, 2).clone()
    bad = torch.zeros(n, dtype=torch.bool)
    bad[::4] = True
    kinds = {"zero": 0.0, "inf": math.inf, "nan": math.nan, "-inf": -math.inf}
    rows = []
    for f in filters:
        good = check_lookup(tex, uv[:, :, ~bad], dx[:, :, ~bad], dy[:, :, ~bad], f)
        t0 = tex.clone().requires_grad_(True)
        difftex.sample(t0, uv[:, :, ~bad], filter=f, uv_dx=dx[:, :, ~bad], uv_dy=dy[:, :, ~bad]).sum().backward()
        for kind, val in kinds.items():
            for which in ("both", "one"):
                bdx, bdy = dx.clone(), dy.clone()
                bdx[:, :, bad] = val
                if which == "both":
                    bdy[:, :, bad] = val
                t = tex.clone().requires_grad_(True)
                ddx = bdx.clone().requires_grad_(True)
                ddy = bdy.clone().requires_grad_(True)
                o = difftex.sample(t, uv, filter=f, uv_dx=ddx, uv_dy=ddy)
                o.sum().backward()
                for d in (ddx, ddy):  # nearest-mip passes no gradient to the derivatives at all
                    if d.grad is None:
                        d.grad = torch.zeros_like(d)
                # Texture gradient of the bad pixels alone, to compare the good ones'.
                t1 = tex.clone().requires_grad_(True)
                difftex.sample(t1, uv[:, :, bad], filter=f, uv_dx=bdx[:, :, bad], uv_dy=bdy[:, :, bad]).sum().backward()
                leak = max(float((o.detach()[..., ~bad] - good["out"]).abs().max()),
                           float((t.grad - t1.grad - t0.grad).abs().max()))
                row = dict(sweep="bad derivatives", x=f"{kind} ({which})", filter=f,
                           finite=bool(torch.isfinite(o).all()),
                           grads_finite=all(bool(torch.isfinite(x).all()) for x in (t.grad, ddx.grad, ddy.grad)),
                           bad_deriv_grad=float(max(ddx.grad[:, :, bad].abs().max(), ddy.grad[:, :, bad].abs().max()))
                           if which == "both" else float("nan"),
                           leak=leak)
                if which == "both" and kind in ("zero", "nan"):
                    # Level 0: the filter itself at a vanishing (1e-12) footprint (EWA's
                    # texel-sized Gaussian is not bilinear there, the others are).
                    tiny = torch.full_like(dx[:, :, bad], 1e-12)
                    lvl0 = difftex.sample(tex, uv[:, :, bad], filter=f, uv_dx=tiny, uv_dy=tiny)
                    row["promise_err"] = float((o.detach()[..., bad] - lvl0).abs().max())
                elif which == "both":
                    row["promise_err"] = float((o.detach()[..., bad] - tex.mean((-1, -2)).view(1, 3, 1, 1)).abs().max())
                rows.append(row)
        # NaN / infinite uv: NaN out there, nothing else touched, no texture gradient from it.
        for kind, val in (("nan uv", math.nan), ("inf uv", math.inf)):
            buv = uv.clone()
            buv[:, :, bad, 0] = val
            t = tex.clone().requires_grad_(True)
            o = difftex.sample(t, buv, filter=f, uv_dx=dx, uv_dy=dy)
            o.masked_fill(torch.isnan(o), 0).sum().backward()
            rows.append(dict(sweep="bad derivatives", x=kind, filter=f, nan_out=bool(torch.isnan(o[..., bad]).all()),
                             finite=bool(torch.isfinite(o[..., ~bad]).all()),
                             grads_finite=bool(torch.isfinite(t.grad).all()),
                             leak=max(float((o.detach()[..., ~bad] - good["out"]).abs().max()),
                                      float((t.grad - t0.grad).abs().max()))))
    return rows


def degenerate_mesh(filters: Sequence[str] = FILTERS, res: int = 32, dtype: torch.dtype = torch.float32) -> list[dict]:
    """Zero-area, single-point, sliver and w-crossing triangles through rasterize + interpolate + sample.

    Clip-space positions are leaves; ``sum()`` of the image is
    backpropagated to them and to the texture.  Reports finiteness, the
    texture L1 ratio, the largest per-vertex position gradient norm, and
    how many pixels each triangle covers.
    """
    P = [  # clip-space [x, y, z, w]
        # 0-2: an ordinary triangle, lower left
        [-0.9, -0.9, 0.5, 1.0], [-0.1, -0.9, 0.5, 1.0], [-0.5, -0.1, 0.5, 1.0],
        # 3-5: zero area (collinear)
        [0.1, 0.1, 0.5, 1.0], [0.5, 0.5, 0.5, 1.0], [0.9, 0.9, 0.5, 1.0],
        # 6-8: all three corners the same point
        [0.3, -0.3, 0.5, 1.0], [0.3, -0.3, 0.5, 1.0], [0.3, -0.3, 0.5, 1.0],
        # 9-11: a sliver 1e-6 NDC thick across the image
        [-1.0, 0.6, 0.4, 1.0], [1.0, 0.6, 0.4, 1.0], [0.0, 0.600001, 0.4, 1.0],
        # 12-14: crossing w = 0 (one corner behind the eye, w < 0): the visible part is unbounded in NDC
        [0.2, -0.8, 0.5, 1.0], [0.9, -0.8, 0.5, 1.0], [0.5, 0.5, -1.2, -0.5],
        # 15-17: one corner at w = 1e-6 (NDC ~1e6 away)
        [-0.8, 0.2, 0.0, 1.0], [-0.2, 0.2, 0.0, 1.0], [-0.5, 0.5, 0.0, 1e-6],
        # 18-20: one corner exactly at w = 0 (a point at infinity)
        [0.3, 0.2, 0.0, 1.0], [0.9, 0.2, 0.0, 1.0], [0.6, 0.5, 0.0, 0.0],
    ]
    pos0 = torch.tensor(P, dtype=dtype)
    faces = torch.arange(21).view(7, 3)
    uvs = torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]], dtype=dtype).repeat(7, 1)
    tex = checker_noise_texture(64, dtype=dtype)
    rows = []
    for f in filters:
        pos = pos0.clone().requires_grad_(True)
        t = tex.clone().requires_grad_(True)
        frags = difftex.rasterize(pos, faces, (res, res))
        uv, dx, dy = difftex.interpolate(uvs, faces, frags, derivatives=True)
        kw = dict(uv_dx=dx, uv_dy=dy) if f in MIP_FILTERS else {}
        img = difftex.sample(t, uv, filter=f, **kw)
        img = img * frags.mask.unsqueeze(1)
        img.sum().backward()
        cover = [int((frags.tri_id == i).sum()) for i in range(7)]
        n_out = int(frags.mask.sum()) * tex.shape[1]
        rows.append(dict(sweep="degenerate mesh", x="mesh", filter=f, finite=bool(torch.isfinite(img).all()),
                         grads_finite=bool(torch.isfinite(pos.grad).all() and torch.isfinite(t.grad).all()),
                         tex_l1=float(t.grad.abs().sum()) / max(n_out, 1),
                         pos_grad=float(pos.grad.norm(dim=-1).max()), cover=cover,
                         uv_deriv_max=float(torch.maximum(dx.detach().abs().max(), dy.detach().abs().max()))))
    return rows


# --------------------------------------------------------------------------
# script
# --------------------------------------------------------------------------


def _plot(results: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 3, figsize=(18, 10.5))
    cmap = plt.get_cmap("tab10")
    col = {f: cmap(i % 10) for i, f in enumerate(FILTERS)}
    ax = axes[0, 0]
    for f in FILTERS:
        rs = [r for r in results["view"] if r["filter"] == f]
        ax.plot([r["x"] for r in rs], [r["psnr"] for r in rs], "o-", color=col[f], label=f, ms=4)
    ax.set_xlabel("view angle off the plane normal (deg)")
    ax.set_ylabel("PSNR vs 16x16 supersampled (dB)")
    ax.set_title("grazing plane")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[0, 1]
    for f in FILTERS:
        rs = [r for r in results["minify"] if r["filter"] == f]
        ax.plot([r["x"] for r in rs], [max(r["max_err"], 1e-7) for r in rs], "o-", color=col[f], label=f, ms=4)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("texels per pixel (head-on, square footprint)")
    ax.set_ylabel("max |error| vs exact box mean")
    ax.set_title("minification up to 1000x")
    ax.grid(alpha=0.3, which="both")
    ax = axes[0, 2]
    for f in ("bilinear", "trilinear", "anisotropic", "ewa"):
        for dt, ls in (("float32", "-"), ("float64", "--")):
            rs = [r for r in results["offset"] if r["filter"] == f and r["dtype"] == dt and r["x"] > 0]
            ax.plot([r["x"] for r in rs], [max(r["err"], 1e-17) for r in rs], ls, marker="o", color=col[f],
                    label=f"{f} {dt}", ms=3)
    rs = [r for r in results["offset"] if r["filter"] == "bilinear" and r["dtype"] == "float32" and r["x"] > 0]
    ax.plot([r["x"] for r in rs], [r["x"] * 2.0 ** -24 for r in rs], ":", color="k", label="ulp(offset) / 2 (uv units)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("uv offset (whole repeats)")
    ax.set_ylabel("max |error| vs float64 at offset 0")
    ax.set_title("large uv with repeat")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3, which="both")
    seam = results["seam"]
    lv = seam["levels"]
    for j, kind in enumerate(("analytic", "finite")):
        ax = axes[1, j]
        img = seam[kind]["trilinear"]["out"][0].permute(1, 2, 0).clamp(0, 1).numpy()
        ax.imshow(img)
        ax.set_title(f"sphere, trilinear, {kind} derivatives: seam lod max {seam[kind]['lod_seam_max']:.1f} "
                     f"(rest median {seam[kind]['lod_rest_median']:.1f}, coarsest {lv - 1})", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    ax = axes[1, 2]
    names = list(FILTERS)
    x = torch.arange(len(names)).float()
    tex_l1 = [max(r["tex_l1"] for k in ("view", "minify") for r in results[k] if r["filter"] == f) for f in names]
    uvg = [max(r["uv_grad"] for k in ("view", "minify", "shapes") for r in results[k] if r["filter"] == f) for f in names]
    dg = [max(r["deriv_grad"] for k in ("view", "minify", "shapes") for r in results[k] if r["filter"] == f) for f in names]
    ax.bar(x - 0.25, tex_l1, 0.25, label="texture |grad|_1 / outputs")
    ax.bar(x, uvg, 0.25, label="max uv grad / (C range max(H,W))")
    ax.bar(x + 0.25, dg, 0.25, label="max uv_dx,uv_dy grad / (C range max(H,W))")
    ax.set_xticks(x.numpy(), names, rotation=30, fontsize=8)
    ax.set_yscale("log")
    ax.set_title("largest normalised gradient over the sweeps")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig.suptitle("difftex stability sweeps", fontsize=14)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: Optional[list[str]] = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="results/stability")
    ap.add_argument("--docs", action="store_true", help="also copy the chart to docs/images/stability.png")
    ap.add_argument("--small", action="store_true", help="the sizes of tests/experiments/test_stability.py (a quick "
                    "check; the charted numbers come from the defaults)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    steps = (("view", sweep_view_angle), ("minify", sweep_minification), ("offset", sweep_uv_offset),
             ("seam", sphere_seam), ("shapes", texture_shapes), ("bad", bad_derivatives), ("mesh", degenerate_mesh))
    small = dict(view=dict(angles=(0, 80, 89, 89.9), res=16, tex_size=64),
                 minify=dict(factors=(0.5, 1, 16, 64, 1000), res=16, tex_size=64),
                 offset=dict(offsets=(0, 1e3, 1e6), res=12, tex_size=64), seam=dict(res=32, tex_size=128, ss=8),
                 shapes=dict(n=32, wraps=("repeat", "mirror")))
    for name, fn in steps:
        t = time.perf_counter()
        results[name] = fn(**(small.get(name, {}) if args.small else {}))
        print(f"{name}: {time.perf_counter() - t:.1f} s", flush=True)
    lines = ["| filter | min PSNR view sweep (angle) | PSNR at 89.9 | max err minification (factor) | err at 1000x "
             "| float32 err at 1e6 | float32 excess at 1e6 | float64 err at 1e6 | seam err / rest (analytic) "
             "| seam err / rest (finite diff.) | max tex L1 | max uv grad | max deriv grad | mesh pos grad |",
             "| --- |" + " ---: |" * 13]
    for f in FILTERS:
        v = [r for r in results["view"] if r["filter"] == f]
        vm = min(v, key=lambda r: r["psnr"])
        mi = [r for r in results["minify"] if r["filter"] == f]
        mm = max(mi, key=lambda r: r["max_err"])
        off = {(r["dtype"], r["x"]): r for r in results["offset"] if r["filter"] == f}
        sa, sf = results["seam"]["analytic"][f], results["seam"]["finite"][f]
        allr = [r for k in ("view", "minify", "shapes") for r in results[k] if r["filter"] == f]
        mesh = [r for r in results["mesh"] if r["filter"] == f][0]
        lines.append(
            f"| {f} | {vm['psnr']:.1f} ({vm['x']:g}) | {v[-1]['psnr']:.1f} | {mm['max_err']:.3g} ({mm['x']:g}) | "
            f"{mi[-1]['max_err']:.3g} | {off[('float32', 1e6)]['err']:.3g} | {off[('float32', 1e6)]['excess']:.2g} | "
            f"{off[('float64', 1e6)]['err']:.2g} | {sa['err_seam']:.3f} / {sa['err_rest']:.3f} | "
            f"{sf['err_seam']:.3f} / {sf['err_rest']:.3f} | {max(r['tex_l1'] for r in allr):.4f} | "
            f"{max(r['uv_grad'] for r in allr):.3f} | {max(r['deriv_grad'] for r in allr):.3f} | "
            f"{mesh['pos_grad']:.3g} |")
    failures = [r for k in ("view", "minify", "offset", "shapes", "bad", "mesh") for r in results[k]
                if not r.get("finite", True) or not r.get("grads_finite", True)]
    seam = results["seam"]
    lines += ["", f"Seam: {seam['analytic']['seam_pixels']} seam pixels; max level there {seam['analytic']['lod_seam_max']:.2f} "
              f"with analytic derivatives (median elsewhere {seam['analytic']['lod_rest_median']:.2f}), "
              f"{seam['finite']['lod_seam_max']:.2f} with finite differences (coarsest level {seam['levels'] - 1}).",
              f"Non-finite outputs or gradients: {len(failures)} of "
              f"{sum(len(results[k]) for k in ('view', 'minify', 'offset', 'shapes', 'bad', 'mesh'))} cases.",
              f"Total {time.perf_counter() - t0:.0f} s."]
    table = "\n".join(lines)
    (out / "stability.md").write_text(table + "\n")
    print(table)
    for r in failures:
        print("NON-FINITE:", {k: v for k, v in r.items() if k not in ("out",)})
    _plot(results, out / "stability.png")
    if args.docs:
        import shutil
        (ROOT / "docs" / "images").mkdir(parents=True, exist_ok=True)
        shutil.copy(out / "stability.png", ROOT / "docs" / "images" / "stability.png")
    print(f"written to {out} in {time.perf_counter() - t0:.0f} s")
    return results


if __name__ == "__main__":
    main()

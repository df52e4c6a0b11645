"""Fast forward / first-order backward for the separable filters, on grid_sample.

``torch.nn.functional.grid_sample`` is one fused kernel on CPU and CUDA;
difftex's own gather-based code (``gather.py``) needs a dozen tensor ops and
runs 3-6x slower on a 2-core CPU. grid_sample lacks the repeat and mirror
wraps, per-axis modes, a border constant and double backward, so this path
reduces every wrap mode to what it has:

* along each axis, the texture is padded by the kernel's reach ``p`` with
  what the wrap mode reads there (the opposite edge for repeat, the mirrored
  edge for mirror, the constant for border; nothing for clamp), and
* the coordinate is folded into one period (``frac`` for repeat, a
  triangle wave of period 2 for mirror), so every tap lands in the padded
  texture, and grid_sample's "border" padding does the clamping.

The values are those of ``gather.separable_forward`` (the tested reference)
to rounding. The first-order backward is written by hand around
``aten::grid_sampler_2d_backward`` (plus the adjoints of the padding and the
folding): no autograd graph is recorded in the forward and no re-entrant
``autograd.grad`` runs in the backward, which is most of a small level's
cost. ``SeparableSample`` in ``separable.py`` runs this path; double backward
falls back to the reference backward.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ..wrap import fold, fold_slope, pad_index
from .gather import reduce_coordinate, reduce_uv, separable_backward, separable_forward

_GS_MODE = {"nearest": "nearest", "linear": "bilinear", "cubic": "bicubic"}
# Texels a tap may reach beyond [0, n) after folding: bicubic reads 2.
_REACH = {"nearest": 1, "linear": 1, "cubic": 2}
_ROW = 256


# F.pad modes that read what a wrap mode reads beyond the edge, for pads of
# up to ``reach`` texels (mirror reads texel 0 at -1, as "replicate" does,
# but texel 1 at -2, which no F.pad mode reads).
_FPAD = {"repeat": "circular", "border": "constant"}


def _fpad_mode(mode: str, p: int, n: int) -> str | None:
    if mode == "clamp":
        return None
    if mode == "mirror":
        return "replicate" if p == 1 else None
    return _FPAD[mode] if (mode == "border" or p <= n) else None


def _pad_axis(tex: Tensor, dim: int, p: int, mode: str, border: float) -> Tensor:
    """Pad ``p`` texels on both ends of ``dim`` (2 or 3) with what ``mode`` reads there."""
    n = tex.shape[dim]
    if mode == "clamp" or p == 0:
        return tex
    fmode = _fpad_mode(mode, p, n)
    if fmode is not None:
        return F.pad(tex, (p, p, 0, 0) if dim == 3 else (0, 0, p, p), mode=fmode,
                     **({"value": border} if fmode == "constant" else {}))
    return tex.index_select(dim, pad_index(mode, p, n, tex.device))


def _unpad_axis(g: Tensor, dim: int, p: int, mode: str) -> Tensor:
    """Adjoint of ``_pad_axis``: fold the gradient of the pad back onto the texels it copied."""
    if mode == "clamp" or p == 0:
        return g
    n = g.shape[dim] - 2 * p
    core = g.narrow(dim, p, n)
    if mode == "border":  # the constant has no texels
        return core
    idx = pad_index(mode, p, n, g.device)
    strips = torch.cat((g.narrow(dim, 0, p), g.narrow(dim, n + p, p)), dim)
    return core.clone().index_add_(dim, torch.cat((idx[:p], idx[n + p:])), strips)


def _pad(tex: Tensor, pu: int, pv: int, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """Pad both axes, in one F.pad call where the two modes allow it."""
    H, W = tex.shape[-2:]
    fu, fv = _fpad_mode(wrap_u, pu, W), _fpad_mode(wrap_v, pv, H)
    if pu and pv and fu is not None and fu == fv:
        return F.pad(tex, (pu, pu, pv, pv), mode=fu, **({"value": border} if fu == "constant" else {}))
    return _pad_axis(_pad_axis(tex, 3, pu, wrap_u, border), 2, pv, wrap_v, border)


# Along an axis, taps stay inside [0, n) while the texel coordinate x
# (centre of texel j at j) lies in [lo, n + hi): nearest rounds, linear reads
# floor(x) and floor(x) + 1, cubic floor(x) - 1 .. floor(x) + 2.
_INSIDE = {"nearest": (-0.5, -0.5), "linear": (0.0, -1.0), "cubic": (1.0, -2.0)}


def _crosses_edge(folded: Tensor, W: int, H: int, kind: str, wrap_u: str, wrap_v: str) -> Tensor:
    """[B, M] bool: points with a tap outside the texture on an axis that does not clamp."""
    lo, hi = _INSIDE[kind]
    out = torch.zeros(folded.shape[:-1], dtype=torch.bool, device=folded.device)
    for axis, n, mode in ((0, W, wrap_u), (1, H, wrap_v)):
        if mode != "clamp":
            x = folded[..., axis] * n - 0.5
            out |= (x < lo) | (x >= n + hi)
    return out


def _fold(u: Tensor, mode: str) -> Tensor:
    """One period of repeat / mirror; clamp and border stop a few textures past the edge.

    grid_sample scales the coordinate by the texture size: a finite but huge
    u (1e38 in float32) would overflow to inf there and read NaN. Past the
    stop every tap is off the texture, so the read is the same.
    """
    return fold(u, mode) if mode in ("repeat", "mirror") else reduce_coordinate(u, mode)


_GS_ENUM = {"linear": 0, "nearest": 1, "cubic": 2}  # aten's GridSamplerInterpolation


class _Rows:
    """grid_sample over M points laid out as rows; ``backward`` is its adjoint.

    tex [Bt,C,h,w], grid [B,M,2] in [-1, 1] (B = Bt, or a multiple of 1
    shared texture) -> [B,C,M], clamping at the edges. grid_sample's CPU
    kernel vectorises along an output row and splits work over the batch
    only: the points go in rows of ``_ROW``, and on CPU one texture's rows go
    to as many batch entries (views of the same texture, no copy) as there
    are threads - unless the texture needs a gradient and is larger than the
    point set: the backward would zero and sum one texture-sized gradient
    per entry.
    """

    def __init__(self, tex: Tensor, grid: Tensor, kind: str, tex_grad: bool):
        B, M = grid.shape[:2]
        split = 1
        h, w = tex.shape[-2:]
        if B == 1 and grid.device.type == "cpu" and (not tex_grad or M >= h * w):
            split = max(1, min(torch.get_num_threads(), -(-M // _ROW)))
        # Unsplit, the points are one row (as fast, and no padded copy).
        row = -(-M // split) if split == 1 else _ROW
        rows = -(-M // (row * split)) * split
        if rows * row != M:
            grid = F.pad(grid, (0, 0, 0, rows * row - M))
        self.kind, self.B, self.M, self.rows, self.row, self.split = kind, B, M, rows, row, split
        # One texture read by several entries: its gradient sums over them.
        self.shared = tex.shape[0] == 1 and B * split > 1
        self.tex = tex.expand(B * split, -1, -1, -1)  # a view: grid_sample reads one texture for all
        self.grid = grid.view(B * split, rows // split, row, 2)

    def forward(self) -> Tensor:
        out = F.grid_sample(self.tex, self.grid, mode=_GS_MODE[self.kind], padding_mode="border",
                            align_corners=False)
        if self.split > 1:
            out = out.transpose(0, 1)  # [C, split, rows / split, row]
        return out.reshape(self.B, -1, self.rows * self.row)[:, :, :self.M]

    def backward(self, g: Tensor, need_tex: bool, need_grid: bool) -> tuple[Tensor | None, Tensor | None]:
        """g [B,C,M] -> (gradient of the texture [1 or B, C, h, w], of the grid [B, M, 2])."""
        B, C = g.shape[:2]
        total = self.rows * self.row
        if total != self.M:
            g = F.pad(g, (0, total - self.M))
        if self.split > 1:
            g = g.view(C, self.split, self.rows // self.split, self.row).transpose(0, 1)
        g = g.reshape(B * self.split, C, self.rows // self.split, self.row)
        gt, gg = torch.ops.aten.grid_sampler_2d_backward(
            g, self.tex, self.grid, _GS_ENUM[self.kind], 1, False, [need_tex, need_grid])
        if need_tex and self.shared:
            gt = gt.sum(0, keepdim=True)
        if need_grid:
            gg = gg.reshape(B, total, 2)[:, :self.M]
        return (gt if need_tex else None), (gg if need_grid else None)


class FastSample:
    """One fast-path lookup; ``out`` holds the values, ``backward`` gives the first-order gradients.

    texture [Bt,C,H,W], uv [B,M,2] -> out [B,C,M] (Bt = B or 1). Runs
    without recording an autograd graph; ``tex_grad`` says whether the
    texture will need a gradient (it decides the thread split).
    """

    def __init__(self, texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float,
                 tex_grad: bool = False):
        B, M = uv.shape[:2]
        shared = texture.shape[0] == 1
        C, H, W = texture.shape[1:]
        self.args = (kind, wrap_u, wrap_v, border)
        self.texture = texture
        # A NaN / inf uv would index garbage inside the kernel: sample a safe
        # point instead and put the NaN back afterwards, so the pixel is NaN
        # and passes no gradient. On CPU one sum says whether any point is
        # bad (or so large that the sum overflows) without a per-point pass;
        # on other devices the masks are cheaper than that sync.
        self.bad = None
        if uv.device.type != "cpu" or not bool(torch.isfinite(uv.sum())):
            self.bad = ~torch.isfinite(uv).all(-1)
            uv = torch.where(self.bad.unsqueeze(-1), 0.0, uv)
        periodic = {wrap_u, wrap_v} & {"repeat", "mirror"}
        src = uv
        if kind == "nearest":
            size = uv.new_tensor([W, H])
            if periodic:
                # x = u * n - 0.5 rounds to its texel (half to even, as the reference and the kernel) before
                # the wrap: folding u first moves a tie across a mirror (or an odd number of texels) to its
                # other side. The texel's centre is folded instead, onto a texel centre.
                src = (torch.round(reduce_uv(uv, wrap_u, wrap_v) * size - 0.5) + 0.5) / size
        if wrap_u == wrap_v:
            folded = _fold(src, wrap_u)
        else:
            folded = torch.stack((_fold(src[..., 0], wrap_u), _fold(src[..., 1], wrap_v)), -1)
        if kind == "nearest" and periodic != {wrap_u, wrap_v}:
            # To the centre of the texel that x rounds to on a clamp / border axis: grid_sample's own rounding
            # would see a tie through the padded texture's rescaled coordinates, which are not exact, and
            # could pick either side. (A periodic axis holds a texel centre already.)
            folded = (torch.round(folded * size - 0.5) + 0.5) / size
        self.uv, self.folded = uv, folded
        self.edge = None
        if shared and (wrap_u, wrap_v) != ("clamp", "clamp") and H * W > B * M:
            # Padding would copy (and in backward fold back) a texture larger
            # than the point set: read the texture as it is, and give the few
            # points whose taps cross an edge to the gather reference.
            pu = pv = 0
            tex = texture
            edge = _crosses_edge(folded, W, H, kind, wrap_u, wrap_v)
            if bool(edge.any()):
                self.edge = edge.nonzero(as_tuple=True)
        else:
            reach = _REACH[kind]
            pu = 0 if wrap_u == "clamp" else reach
            pv = 0 if wrap_v == "clamp" else reach
            tex = _pad(texture, pu, pv, wrap_u, wrap_v, border)
        self.pads = (pu, pv)
        # uv of the (padded) texture, as grid_sample's [-1, 1] coordinates.
        self.scale = uv.new_tensor([2 * W / (W + 2 * pu), 2 * H / (H + 2 * pv)])
        shift = uv.new_tensor([2 * pu / (W + 2 * pu) - 1, 2 * pv / (H + 2 * pv) - 1])
        self.rows = _Rows(tex, torch.addcmul(shift, folded, self.scale), kind, tex_grad)
        out = self.rows.forward()
        if self.edge is not None:
            b, m = self.edge
            vals = separable_forward(texture, folded[b, m].unsqueeze(0), kind, wrap_u, wrap_v, border)
            out.transpose(1, 2).index_put_((b, m), vals[0].t())  # out is grid_sample's fresh result
        self.out = out if self.bad is None else torch.where(self.bad.unsqueeze(1), float("nan"), out)

    def backward(self, g: Tensor, need_tex: bool, need_uv: bool,
                 into: Tensor | None = None) -> tuple[Tensor | None, Tensor | None]:
        """Gradients of the texture and the uv for the output gradient g [B,C,M]; no graph.

        ``into``: a texture-shaped buffer the caller owns; the texture
        gradient is scattered into it by the gather reference instead of
        grid_sample's own zero-filled one (cheaper where the points are few
        next to the texels), and it is returned as the texture gradient.
        """
        kind, wrap_u, wrap_v, border = self.args
        need_uv = need_uv and kind != "nearest"
        if self.bad is not None:
            g = torch.where(self.bad.unsqueeze(1), 0.0, g)
        sparse = need_tex and into is not None
        if sparse:
            separable_backward(self.texture, self.folded, g, kind, wrap_u, wrap_v, border, True, False, into=into)
            need_tex = False
        g_edge = None
        if self.edge is not None:
            # Edge points were read by the reference: their grid_sample
            # values were replaced, so grid_sample gets no gradient for them.
            gp = g.transpose(1, 2)
            g_edge = gp[self.edge]  # [E, C]
            g = gp.index_put(self.edge, g.new_zeros(())).transpose(1, 2)
        gt, gg = self.rows.backward(g, need_tex, need_uv)
        grad_tex = grad_uv = None
        if need_tex:
            pu, pv = self.pads
            grad_tex = _unpad_axis(_unpad_axis(gt, 2, pv, wrap_v), 3, pu, wrap_u)
        if need_uv:
            grad_uv = gg * self.scale
        if g_edge is not None:
            b, m = self.edge
            # No padding here, so grad_tex is grid_sample's own fresh buffer:
            # the reference adds into it instead of a second texture-sized one.
            _, eu = separable_backward(self.texture, self.folded[b, m].unsqueeze(0), g_edge.t().unsqueeze(0),
                                       kind, wrap_u, wrap_v, border, need_tex, need_uv, into=grad_tex)
            if need_uv:
                grad_uv = grad_uv.index_put((b, m), eu[0])
        if need_uv:
            if wrap_u == wrap_v:
                slope = fold_slope(self.uv, wrap_u)
                if slope is not None:
                    grad_uv = grad_uv * slope
            else:
                su, sv = fold_slope(self.uv[..., 0], wrap_u), fold_slope(self.uv[..., 1], wrap_v)
                if su is not None or sv is not None:
                    one = torch.ones_like(self.uv[..., 0])
                    grad_uv = grad_uv * torch.stack((one if su is None else su, one if sv is None else sv), -1)
            if self.bad is not None:
                grad_uv = torch.where(self.bad.unsqueeze(-1), 0.0, grad_uv)
        return (into if sparse else grad_tex), grad_uv


def fast_forward(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """texture [Bt,C,H,W], uv [B,M,2] -> [B,C,M] (Bt = B or 1), no gradient."""
    return FastSample(texture, uv, kind, wrap_u, wrap_v, border).out

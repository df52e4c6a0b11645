"""Fast forward / first-order backward for the separable filters, on grid_sample.

``torch.nn.functional.grid_sample`` is one fused kernel on CPU and CUDA;
difftex's own gather-based code (``basic.py``) needs a dozen tensor ops and
runs 3-6x slower on a 2-core CPU. grid_sample lacks the repeat and mirror
wraps, per-axis modes, a border constant and double backward, so this path
reduces every wrap mode to what it has:

* along each axis, the texture is padded by the kernel's reach ``p`` with
  what the wrap mode reads there (the opposite edge for repeat, the mirrored
  edge for mirror, the constant for border; nothing for clamp), and
* the coordinate is folded into one period (``frac`` for repeat, a
  triangle wave of period 2 for mirror), so every tap lands in the padded
  texture, and grid_sample's "border" padding does the clamping.

The values are those of ``basic.separable_forward`` (the tested reference)
to rounding. ``SeparableSample`` in ``basic.py`` runs this path inside its
forward and backward; double backward falls back to the reference backward.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

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
    # Indices -p..-1 and n..n+p-1, mapped the way wrap.wrap_index maps them.
    before = torch.arange(-p, 0, device=tex.device)
    after = torch.arange(n, n + p, device=tex.device)
    if mode == "repeat":
        before, after = before % n, after % n
    else:  # mirror: period 2n, reflected about the texture's edges
        before, after = before % (2 * n), after % (2 * n)
        before = torch.where(before >= n, 2 * n - 1 - before, before)
        after = torch.where(after >= n, 2 * n - 1 - after, after)
    idx = torch.cat((before, torch.arange(n, device=tex.device), after))
    return tex.index_select(dim, idx)


def _pad(tex: Tensor, pu: int, pv: int, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """Pad both axes, in one F.pad call where the two modes allow it."""
    H, W = tex.shape[-2:]
    fu, fv = _fpad_mode(wrap_u, pu, W), _fpad_mode(wrap_v, pv, H)
    if pu and pv and fu is not None and fu == fv:
        return F.pad(tex, (pu, pu, pv, pv), mode=fu, **({"value": border} if fu == "constant" else {}))
    return _pad_axis(_pad_axis(tex, 3, pu, wrap_u, border), 2, pv, wrap_v, border)


def _fold(u: Tensor, mode: str) -> Tensor:
    """Fold a uv coordinate into the period that the padded texture holds."""
    if mode == "repeat":
        return u - torch.floor(u)
    if mode == "mirror":
        # Triangle wave: 0 -> 0, 1 -> 1, 2 -> 0; slope +-1 like the mirror.
        h = u * 0.5
        return 1 - torch.abs(2 * (h - torch.floor(h)) - 1)
    return u


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


def _grid_sample_rows(tex: Tensor, grid: Tensor, kind: str) -> Tensor:
    """tex [B,C,h,w], grid [B,M,2] in [-1, 1] -> [B,C,M], clamping at the edges."""
    Bt, C = tex.shape[:2]
    # grid_sample's CPU kernel vectorises along an output row and splits
    # work over the batch only: lay the M points out as rows of _ROW points,
    # and on CPU give one texture's rows to as many batch entries (views of
    # the same texture, no copy) as there are threads - unless the texture
    # needs a gradient and is larger than the point set: grid_sample's
    # backward would zero and sum one texture-sized gradient per entry.
    M = grid.shape[1]
    rows = -(-M // _ROW)
    split = 1
    h, w = tex.shape[-2:]
    if Bt == 1 and not grid.is_cuda and (not tex.requires_grad or M >= h * w):
        split = max(1, min(torch.get_num_threads(), rows))
        rows = -(-rows // split) * split
    if rows * _ROW != M:
        grid = F.pad(grid, (0, 0, 0, rows * _ROW - M))
    if split > 1:
        tex = tex.expand(split, -1, -1, -1)
    out = F.grid_sample(tex, grid.view(Bt * split, rows // split, _ROW, 2), mode=_GS_MODE[kind],
                        padding_mode="border", align_corners=False)
    if split > 1:
        out = out.transpose(0, 1)  # [C, split, rows / split, _ROW]
    return out.reshape(Bt, C, rows * _ROW)[:, :, :M]


def fast_forward(texture: Tensor, uv: Tensor, kind: str, wrap_u: str, wrap_v: str, border: float) -> Tensor:
    """texture [Bt,C,H,W], uv [B,M,2] -> [B,C,M] (Bt = B or 1), differentiable once by autograd."""
    from .basic import separable_forward  # the reference; basic imports this module

    B, M = uv.shape[:2]
    shared = texture.shape[0] == 1
    C, H, W = texture.shape[1:]
    # A NaN / inf uv would index garbage inside the kernel: sample a safe
    # point instead and put the NaN back afterwards, so the pixel is NaN and
    # passes no gradient to the texture. On CPU one sum says whether any
    # point is bad (or so large that the sum overflows) without a per-point
    # pass; on CUDA the masks are cheaper than that sync.
    bad = None
    if uv.is_cuda or not bool(torch.isfinite(uv.detach().sum())):
        bad = ~torch.isfinite(uv).all(-1)
        uv = torch.where(bad.unsqueeze(-1), 0.0, uv)
    if wrap_u == wrap_v:
        folded = _fold(uv, wrap_u)
    else:
        folded = torch.stack((_fold(uv[..., 0], wrap_u), _fold(uv[..., 1], wrap_v)), -1)
    edge = None
    if shared and (wrap_u, wrap_v) != ("clamp", "clamp") and H * W > B * M:
        # Padding would copy (and in backward fold back) a texture larger
        # than the point set: read the texture as it is, and give the few
        # points whose taps cross an edge to the gather reference.
        pu = pv = 0
        tex = texture
        edge = _crosses_edge(folded, W, H, kind, wrap_u, wrap_v)
    else:
        reach = _REACH[kind]
        pu = 0 if wrap_u == "clamp" else reach
        pv = 0 if wrap_v == "clamp" else reach
        tex = _pad(texture, pu, pv, wrap_u, wrap_v, border)
    if tex.shape[0] != B:
        tex = tex.expand(B, -1, -1, -1)  # a view: grid_sample reads one texture for all
    # uv of the (padded) texture, as grid_sample's [-1, 1] coordinates.
    scale = uv.new_tensor([2 * W / (W + 2 * pu), 2 * H / (H + 2 * pv)])
    shift = uv.new_tensor([2 * pu / (W + 2 * pu) - 1, 2 * pv / (H + 2 * pv) - 1])
    out = _grid_sample_rows(tex, torch.addcmul(shift, folded, scale), kind)
    if edge is not None and bool(edge.any()):
        b, m = edge.nonzero(as_tuple=True)
        vals = separable_forward(texture, folded[b, m].unsqueeze(0), kind, wrap_u, wrap_v, border)
        out = out.transpose(1, 2).index_put((b, m), vals[0].t()).transpose(1, 2)
    return out if bad is None else torch.where(bad.unsqueeze(1), float("nan"), out)

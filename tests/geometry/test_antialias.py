"""antialias: silhouette coverage against a 16x16 supersampled render, gradcheck, degenerate edges, bad input."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

import difftex
from difftex import antialias, rasterize
from difftex.geometry import silhouette_edges
from tests.conftest import DEVICES

SS = 16  # sub-samples per pixel side of the reference


def _triangle(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """One triangle in perspective (w differs per corner), generic: no corner or edge on a pixel centre."""
    ndc = torch.tensor([[-0.62, -0.53], [0.71, -0.21], [-0.13, 0.67]], dtype=dtype)
    w = torch.tensor([1.0, 1.7, 1.3], dtype=dtype)
    pos = torch.cat([ndc * w[:, None], 0.2 * w[:, None], w[:, None]], 1)
    return pos, torch.tensor([[0, 1, 2]])


def _weights(H: int, W: int, dtype) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    return 1 + 0.5 * torch.sin(xx / 5.0) * torch.cos(yy / 7.0)


def _aa_loss(pos, faces, H, W, wt):
    frags = rasterize(pos, faces, (H, W))
    cover = frags.mask.to(pos.dtype)[:, None]
    return (antialias(cover, frags, pos, faces)[0, 0] * wt).sum()


def _supersampled_loss(pos, faces, H, W, wt):
    frags = rasterize(pos, faces, (H * SS, W * SS))
    cover = F.avg_pool2d(frags.mask.to(pos.dtype)[:, None], SS)[0, 0]
    return (cover * wt).sum()


def test_gradient_matches_supersampled_coverage_finite_difference():
    # d/d(corner) of a weighted coverage sum: antialias's analytic gradient
    # against a central difference (half a pixel each way) of the 16x16
    # supersampled coverage, for every corner and axis. Measured at 48x48:
    # 0.08-2.9% on five, 7.5% on the apex moving along the triangle's axis
    # (corner 2, y): rows where the thin tip covers no pixel centre blend
    # nothing, and the apex's motion counts most there. Mean 2.3%.
    H = W = 48
    pos, faces = _triangle()
    wt = _weights(H, W, pos.dtype)
    p = pos.clone().requires_grad_(True)
    _aa_loss(p, faces, H, W, wt).backward()
    rel = []
    for v in range(3):
        for comp in (0, 1):
            h = 0.5 * 2 / W  # half a pixel, in NDC
            d = torch.zeros_like(pos)
            d[v, comp] = h * pos[v, 3]  # moves the projected corner by h
            fd = (_supersampled_loss(pos + d, faces, H, W, wt) - _supersampled_loss(pos - d, faces, H, W, wt)) / (2 * h)
            analytic = p.grad[v, comp] * pos[v, 3]  # per NDC unit of the projected corner (x_ndc = x / w)
            assert abs(fd) > 50  # a real silhouette gradient, not a vanishing one
            rel.append(float(abs(analytic - fd) / abs(fd)))
    print(rel)
    assert max(rel) < 0.09
    assert sum(rel) / len(rel) < 0.03


def test_values_approach_the_supersampled_coverage():
    # Antialiased coverage is closer to the 16x16 box-filtered coverage than
    # the aliased mask: mean abs error on edge pixels drops over 4x.
    H = W = 32
    pos, faces = _triangle()
    frags = rasterize(pos, faces, (H, W))
    mask = frags.mask.to(pos.dtype)[:, None]
    aa = antialias(mask, frags, pos, faces)
    ref = F.avg_pool2d(rasterize(pos, faces, (H * SS, W * SS)).mask.to(pos.dtype)[:, None], SS)
    edge = (ref > 0) & (ref < 1)
    err_aa = (aa - ref)[edge].abs().mean()
    err_mask = (mask - ref)[edge].abs().mean()
    print(float(err_aa), float(err_mask))
    assert err_aa < err_mask / 4
    assert float((aa - ref).abs().max()) < 0.35  # corners: the approximation's worst pixels
    # Interior and background pixels are untouched.
    assert torch.equal(aa[~edge], mask[~edge])


def test_gradcheck_float64():
    # Away from degenerate configurations (no edge near a pixel centre):
    # positions in full; the colour enters linearly, so fast mode suffices.
    H = W = 8
    pos, faces = _triangle()
    frags = rasterize(pos, faces, (H, W))
    torch.manual_seed(0)
    color = torch.rand(1, 2, H, W, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda p: antialias(color, frags, p, faces), (pos.clone().requires_grad_(),))
    assert torch.autograd.gradcheck(lambda c: antialias(c, frags, pos, faces), (color.requires_grad_(),),
                                    fast_mode=True)


def test_interior_edges_are_not_blended_but_the_outline_is():
    # A quad of two triangles with different colours: the shared diagonal
    # is no silhouette (both face the same way), the outline is.
    pos = torch.tensor([[-0.63, -0.58, 0, 1], [0.59, -0.61, 0, 1], [0.61, 0.57, 0, 1], [-0.6, 0.62, 0, 1]],
                       dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    sil = silhouette_edges(pos, faces)
    # Edge k is opposite corner k: the diagonal 0-2 is edge 1 of face 0 and edge 2 of face 1.
    assert sil.tolist() == [[[True, False, True], [True, True, False]]]
    frags = rasterize(pos, faces, (24, 24))
    color = torch.stack([(frags.tri_id == 0).double(), (frags.tri_id == 1).double()], 1)
    out = antialias(color, frags, pos, faces)
    changed = (out != color).any(1)[0]
    inside = frags.mask[0]
    # Changed pixels lie on the outline only: never two covered pixels across the diagonal.
    ring = inside & ~F.max_pool2d((~inside).double()[None, None], 3, 1, 1)[0, 0].bool()
    assert bool(changed.any())
    assert not bool((changed & ring).any())


def test_back_facing_neighbour_makes_a_silhouette():
    # Fold the quad: the second triangle turns clockwise in NDC, so the shared edge becomes a silhouette.
    pos = torch.tensor([[-0.63, -0.58, 0, 1], [0.59, -0.61, 0, 1], [0.61, 0.57, 0, 1], [0.9, -0.9, 0, 1]],
                       dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    assert silhouette_edges(pos, faces)[0, 0, 1] and silhouette_edges(pos, faces)[0, 1, 2]


@pytest.mark.parametrize("device", DEVICES)
def test_batch_and_dtypes_agree(device):
    pos, faces = _triangle()
    pos2 = torch.stack([pos, pos * torch.tensor([1.0, -1.0, 1.0, 1.0], dtype=pos.dtype)]).to(device)
    faces = faces.to(device)
    outs = {}
    for dtype in (torch.float32, torch.float64):
        p = pos2.to(dtype)
        frags = rasterize(p, faces, (20, 20))
        color = frags.mask.to(dtype)[:, None].expand(2, 3, 20, 20)
        outs[dtype] = antialias(color, frags, p, faces)
        assert outs[dtype].dtype == dtype and outs[dtype].shape == (2, 3, 20, 20)
        for b in range(2):
            fb = rasterize(p[b], faces, (20, 20))
            single = antialias(color[b:b + 1], fb, p[b], faces)
            assert torch.equal(single, outs[dtype][b:b + 1])
    assert torch.allclose(outs[torch.float32].double(), outs[torch.float64], atol=1e-5)
    # One set of positions (B = 1) serves a batch of images of it.
    one = pos.to(device)
    frags = rasterize(one.expand(2, 3, 4), faces, (20, 20))
    color = torch.rand(2, 3, 20, 20, dtype=torch.float64, device=device)
    assert torch.equal(antialias(color, frags, one, faces), antialias(color, frags, one.expand(2, 3, 4), faces))


def test_degenerate_edges_give_no_nan():
    # A zero-area triangle (two equal corners), an edge exactly through pixel
    # centres, a corner at w = 0 and one behind the eye.
    pos = torch.tensor([
        [-0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, 1.0],  # degenerate
        [-0.875, -0.875, 0.0, 1.0], [0.875, -0.875, 0.0, 1.0], [-0.875, 0.875, 0.0, 1.0],  # edges on centres
        [0.2, 0.3, 0.0, 0.0], [0.9, 0.1, 0.5, 1.0], [0.4, 0.9, 0.3, -1.0],  # w = 0 and w < 0
    ], dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    frags = rasterize(pos, faces, (8, 8))
    color = torch.rand(1, 3, 8, 8, dtype=torch.float64, requires_grad=True)
    out = antialias(color, frags, pos, faces)
    out.square().sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(pos.grad).all() and torch.isfinite(color.grad).all()
    assert torch.equal(pos.grad[:3], torch.zeros_like(pos.grad[:3]))  # the zero-area triangle blends nothing


def test_no_silhouette_returns_color_unchanged():
    pos, faces = _triangle()
    views = pos.expand(2, 3, 4)
    color = torch.rand(2, 3, 8, 8, dtype=torch.float64)
    assert torch.equal(antialias(color, rasterize(views, faces[:0], (8, 8)), views, faces[:0]), color)
    # A triangle covering the whole image has no silhouette pixel pair either.
    big = torch.tensor([[-3.0, -3.0, 0, 1], [3.0, -3.0, 0, 1], [0.0, 3.0, 0, 1]], dtype=torch.float64)
    assert torch.equal(antialias(color[:1], rasterize(big, faces, (8, 8)), big, faces), color[:1])


def test_bad_input_raises():
    pos, faces = _triangle()
    frags = rasterize(pos, faces, (8, 8))
    color = torch.zeros(1, 3, 8, 8, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"color: expected 4-D \[B, C, H, W\]"):
        antialias(color[0], frags, pos, faces)
    with pytest.raises(TypeError, match="color: expected a floating-point tensor"):
        antialias(color.long(), frags, pos, faces)
    with pytest.raises(TypeError, match="fragments: expected a difftex.Fragments, got dict"):
        antialias(color, {}, pos, faces)
    with pytest.raises(ValueError, match=r"fragments: expected tri_id of shape \(1, 9, 8\)"):
        antialias(torch.zeros(1, 3, 9, 8, dtype=torch.float64), frags, pos, faces)
    with pytest.raises(ValueError, match="pos: expected last dimension 4"):
        antialias(color, frags, pos[:, :3], faces)
    with pytest.raises(ValueError, match="pos: expected batch 1 or 1 like color"):
        antialias(color, frags, pos.expand(2, 3, 4), faces)
    with pytest.raises(ValueError, match="pos: expected finite clip-space positions"):
        antialias(color, frags, pos * float("nan"), faces)
    with pytest.raises(ValueError, match=r"faces indices must lie in \[0, 2\]"):
        antialias(color, frags, pos, faces + 1)
    with pytest.raises(ValueError, match="rings: expected an int >= 0, got -1"):
        antialias(color, frags, pos, faces, rings=-1)
    with pytest.raises(ValueError, match="fragments: tri_id refers to face 0 but faces has 0 rows"):
        antialias(color, frags, pos, faces[:0])
    assert difftex.antialias is antialias


def test_silhouettes_of_a_smooth_mesh_are_found_through_the_neighbour_rings():
    # icosphere(3) at 96x96: faces near the outline turn edge-on and hold
    # few pixel centres, so the crossing edge is often a neighbour's.
    # Measured: edge-pixel mean error against 8x8 supersampled coverage
    # 0.21 (mask) -> 0.054 (own edges only, the paper's test: 0.19).
    from difftex.testing import icosphere
    from tests.geometry.raster_helpers import view_matrix

    verts, faces = icosphere(3, dtype=torch.float64)
    _, view, proj = view_matrix(30.0, 20.0, 3.0)
    pos = difftex.camera.transform(verts, proj @ view)
    res, ss = 96, 8
    frags = rasterize(pos, faces, (res, res))
    mask = frags.mask.double()[:, None]
    aa = antialias(mask, frags, pos, faces)
    ref = F.avg_pool2d(rasterize(pos, faces, (res * ss, res * ss)).mask.double()[:, None], ss)
    edge = (ref > 0) & (ref < 1)
    err_mask, err_aa = float((mask - ref)[edge].abs().mean()), float((aa - ref)[edge].abs().mean())
    own = antialias(mask, frags, pos, faces, rings=0)
    err_own = float((own - ref)[edge].abs().mean())
    print(err_mask, err_own, err_aa)
    assert err_aa < err_mask / 3
    assert err_own > 2 * err_aa


def test_an_occluder_over_another_surface_blends_both_colours():
    # The perspective triangle (colour 1, nearer) over a big quad (colour 0.4) over background (0):
    # its outline is blended with the quad's colour where the quad is behind, with 0 elsewhere.
    tri, _ = _triangle()
    quad = torch.tensor([[-0.9, -0.3, 0.6, 1], [0.3, -0.9, 0.6, 1], [0.9, 0.9, 0.6, 1], [-0.2, 0.8, 0.6, 1]],
                        dtype=torch.float64)
    pos = torch.cat([tri, quad])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [3, 5, 6]])
    shade = torch.tensor([1.0, 0.4, 0.4], dtype=torch.float64)

    def image(res):
        frags = rasterize(pos, faces, (res, res))
        return frags, torch.where(frags.mask, shade[frags.tri_id.clamp_min(0)], 0.0)[:, None]

    frags, img = image(32)
    ref = F.avg_pool2d(image(32 * SS)[1], SS)
    aa = antialias(img, frags, pos, faces)
    edge = (ref - img).abs() > 1e-9
    err_aa, err_img = (aa - ref)[edge].abs().mean(), (img - ref)[edge].abs().mean()
    print(float(err_img), float(err_aa))
    assert err_aa < err_img / 3

"""Minification through the rasterizer: a mirror sphere reflecting a noise cube map, against 16 x 16 supersampling."""
import torch
import torch.nn.functional as F

from difftex.envmap import cubemap
from difftex.metrics import psnr
from difftex.testing import mirror_sphere


def test_mirror_sphere_psnr_ordering():
    """The sphere reflects the whole environment into a disc of ~26 pixels: minification grows from ~2 cube
    texels a pixel at the centre to unbounded at the silhouette, where the footprints are long and thin.
    Against the 16 x 16 supersampled bilinear render (box filtered), on the pixels covered by all 256
    sub-samples: measured bilinear 16.6, trilinear 25.5, anisotropic 27.8, ewa 25.7 dB (float32). EWA's
    Gaussian reaches a pixel step out along both axes (pbrt's falloff), wider than the box of a pixel that
    the reference averages, so it blurs more than anisotropic, as difftex.sample's EWA does in 2D (grazing
    checker-noise plane against 8 x 8 supersampling: trilinear 23.6, ewa 27.7, anisotropic 31.1 dB)."""
    S, res, ss = 64, 32, 16
    cube = torch.rand(1, 6, 3, S, S, generator=torch.Generator().manual_seed(0))
    eye = (0.4, 0.5, 2.2)
    d, dx, dy, mask = mirror_sphere(eye, res, subdivisions=3)
    ds, _, _, ms = mirror_sphere(eye, res, ss=ss, subdivisions=3)
    ref = F.avg_pool2d(cubemap(cube, ds), ss)
    mask = (mask & (F.avg_pool2d(ms.float().unsqueeze(1), ss)[:, 0] == 1)).unsqueeze(1)
    assert mask.sum() > 300
    got = {f: psnr(cubemap(cube, d, filter=f, dirs_dx=dx, dirs_dy=dy), ref, mask=mask)
           for f in ("bilinear", "trilinear", "anisotropic", "ewa")}
    assert got["bilinear"] < 19 and got["bilinear"] + 5 < got["trilinear"], got
    assert got["trilinear"] + 1.5 < got["anisotropic"], got
    assert got["anisotropic"] > 26.5, got
    assert got["trilinear"] < got["ewa"] < got["anisotropic"] - 1.5, got

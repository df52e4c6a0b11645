"""The main job at a small size: texture and uv fits through TexturedMesh."""
import pytest

from experiments.fit import fit_texture, fit_uv

SMALL = dict(iters=40, res=64, views=16, batch=4, eval_views=8, progress=False, save=False)


@pytest.fixture(scope="module")
def small_fits():
    return {f: fit_texture.fit(filter=f, **SMALL) for f in ("trilinear", "bilinear")}


def test_texture_fit_raises_psnr(small_fits):
    m = small_fits["trilinear"]
    print(m)
    # From a grey start at ~8 dB; 40 Adam steps reach well past it.
    assert m["initial_texture_psnr"] < 10.0
    assert m["texture_psnr"] > m["initial_texture_psnr"] + 6.0
    assert m["image_psnr"] > 25.0


def test_mipmapped_filter_beats_bilinear_on_minified_views(small_fits):
    tri, bil = small_fits["trilinear"], small_fits["bilinear"]
    print({k: (tri[k], bil[k]) for k in ("texture_psnr", "image_psnr")})
    # Bilinear reads a sparse set of texels of a 5x-100x minified texture:
    # the rest never learn, and its images alias against the EWA targets.
    assert tri["texture_psnr"] > bil["texture_psnr"] + 1.0
    assert tri["image_psnr"] > bil["image_psnr"] + 1.0


def test_uv_fit_reduces_error_fivefold():
    m = fit_uv.fit_uv(iters=80, res=64, views=12, batch=8, progress=False, save=False)
    print(m)
    assert m["uv_error_before"] > 20.0
    assert m["uv_error_after"] < m["uv_error_before"] / 5


def test_fit_writes_metrics_and_images(tmp_path):
    m = fit_texture.fit(filter="trilinear", iters=2, res=32, views=4, batch=2, eval_views=2, progress=False, out=tmp_path)
    import json
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert {"filter", "iters", "texture_psnr", "image_psnr", "seconds"} <= saved.keys()
    assert saved["iters"] == 2 and saved["filter"] == "trilinear"
    assert abs(saved["texture_psnr"] - m["texture_psnr"]) < 1e-9
    for name in ("views.png", "texture.png", "curves.png"):
        assert (tmp_path / name).stat().st_size > 1000

"""The main job at a small size: texture and uv fits through TexturedMesh; --capture with and without the cache."""
from pathlib import Path

import pytest
import torch

import difftex
from difftex.io import load_capture, visible_frames
from experiments.fit import fit_texture, fit_uv, frame_cache, runtime

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


# --------------------------------------------------------------------------
# --capture with the frames held in memory (experiments/fit/frame_cache.py) against the per-step path

MESH = Path(__file__).resolve().parents[2] / "data" / "spot" / "spot_triangulated.obj"
CAPTURE_FIT = dict(iters=6, batch=3, lr=0.1, tex_size=64, progress=False, save=False)


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    cap = tmp_path_factory.mktemp("cap")
    fit_texture.make_capture(cap, res=32, views=6, seed=0)
    return cap


def _fit_capture(cap, out, **kw):
    """(metrics, final texture) of a small capture fit; the texture from its last checkpoint."""
    m = fit_texture.fit_capture(cap, MESH, out=out, **dict(CAPTURE_FIT, checkpoint_every=2, **kw))
    return m, runtime.load_checkpoint(out)["texture"]


@pytest.fixture(scope="module")
def per_step_fit(small_capture, tmp_path_factory):
    # One loader worker: the images come from another process, as by default.
    return _fit_capture(small_capture, tmp_path_factory.mktemp("per_step"), cache_mb=0, workers=1)


def test_cached_capture_fit_equals_per_step_fit(small_capture, per_step_fit, tmp_path, monkeypatch):
    def no_loader(*a, **k):
        raise AssertionError("a cached fit built a DataLoader")

    monkeypatch.setattr(torch.utils.data, "DataLoader", no_loader)
    m, tex = _fit_capture(small_capture, tmp_path, workers=2)
    ref_m, ref_tex = per_step_fit
    print({k: (m[k], ref_m[k]) for k in ("cached", "cache_bytes", "image_psnr", "workers")})
    assert m["cached"] and not ref_m["cached"] and m["workers"] == 0 and ref_m["cache_bytes"] == 0
    assert torch.equal(tex, ref_tex)  # bit-identical: the same batches, fragments and images
    assert m["image_psnr"] == ref_m["image_psnr"]  # the evaluation pass too
    assert m["frames_used"] == 6
    # What the cache holds: images + masks (16 B a pixel) and 44 B per covered pixel, plus the offsets.
    covered = m["cache_bytes"] - frame_cache.image_bytes(6, (32, 32)) - 7 * 8
    assert covered % frame_cache.compact_bytes() == 0
    assert 0 < covered // frame_cache.compact_bytes() < 6 * 32 * 32


def test_capture_fit_matches_the_demo(small_fits, tmp_path):
    """The demo's views written as a capture and fitted back (cached, the default) reach the demo's texture PSNR."""
    from difftex.testing.meshes import SPOT_TEXTURE

    demo = small_fits["trilinear"]
    fit_texture.make_capture(tmp_path, res=SMALL["res"], views=SMALL["views"], seed=0)
    m = fit_texture.fit_capture(tmp_path, MESH, iters=SMALL["iters"], batch=SMALL["batch"], tex_size=1024,
                                reference_texture=SPOT_TEXTURE, progress=False, save=False)
    print(m["texture_psnr"], demo["texture_psnr"], m["cache_bytes"])
    assert m["cached"] and m["workers"] == 0
    # The photographs are 8-bit and the cameras pass through transforms.json in float64: not bit-equal targets.
    assert abs(m["texture_psnr"] - demo["texture_psnr"]) < 0.05


@pytest.mark.parametrize("resume_cache_mb", [fit_texture.CACHE_MB, 0])
def test_cached_capture_fit_resumes_to_the_same_texture(small_capture, per_step_fit, tmp_path, monkeypatch,
                                                        resume_cache_mb):
    def killed(step):
        if step == 3:
            raise KeyboardInterrupt  # stands in for a kill right after step 3 (its checkpoint is step 4's)

    monkeypatch.setattr(runtime, "maybe_kill_at", killed)
    with pytest.raises(KeyboardInterrupt):
        _fit_capture(small_capture, tmp_path)
    assert runtime.load_checkpoint(tmp_path)["step"] == 4
    monkeypatch.undo()
    m, tex = _fit_capture(small_capture, tmp_path, resume=True, cache_mb=resume_cache_mb, workers=0)
    assert m["cached"] == (resume_cache_mb > 0)
    assert torch.equal(tex, per_step_fit[1])  # bit-identical, whichever path resumes


def test_capture_cache_budget_and_fragments(small_capture):
    cap = load_capture(small_capture)
    model = difftex.TexturedMesh(difftex.load_mesh(MESH), torch.zeros(1, 3, 8, 8))
    mvp = cap.mvp()
    counts, frags = frame_cache.rasterize_frames(model, mvp, (32, 32), budget_bytes=1 << 30, chunk=4)
    assert torch.equal(counts, visible_frames(mvp, model.positions, model.faces, (32, 32)))
    need = frags.nbytes - 7 * 8  # the offsets are not budgeted
    assert need == int(counts.sum()) * frame_cache.compact_bytes()
    assert frame_cache.rasterize_frames(model, mvp, (32, 32), budget_bytes=need)[1] is not None
    assert frame_cache.rasterize_frames(model, mvp, (32, 32), budget_bytes=need - 1)[1] is None
    assert frame_cache.rasterize_frames(model, mvp, (32, 32), budget_bytes=0)[1] is None
    pick = [4, 1, 1]
    got, want = frags.fragments(pick), model.rasterize(mvp[pick], (32, 32))
    for f in ("tri_id", "bary", "bary_dx", "bary_dy"):
        assert torch.equal(getattr(got, f), getattr(want, f)), f
    sub = frags.subset([4, 1])
    assert torch.equal(sub.fragments([0, 1, 1]).bary, got.bary)  # frames 4, 1 renumbered 0, 1
    with pytest.raises(ValueError, match="budget_bytes"):
        frame_cache.rasterize_frames(model, mvp, (32, 32), budget_bytes=-1)


@pytest.mark.parametrize("bad", [-1, float("nan"), float("inf"), True, "64"])
def test_capture_cache_mb_must_be_a_size(small_capture, tmp_path, bad):
    with pytest.raises(ValueError, match="cache_mb"):
        fit_texture.fit_capture(small_capture, MESH, out=tmp_path, cache_mb=bad, **CAPTURE_FIT)


def test_stochastic_demo_fit_learns_repeats_and_scores_deterministically(small_fits):
    runs = [fit_texture.fit(filter="trilinear", stochastic=1, **SMALL) for _ in range(2)]
    a, b = runs
    print({k: (a[k], small_fits["trilinear"][k]) for k in ("texture_psnr", "image_psnr")})
    assert (a["stochastic"], a["decorrelate"]) == (1, True)
    assert a["texture_psnr"] == b["texture_psnr"] and a["image_psnr"] == b["image_psnr"]  # seeded draws
    # Unbiased gradients, noisier: most of the deterministic fit's gain in 40 steps.
    assert a["texture_psnr"] > a["initial_texture_psnr"] + 4.0
    assert a["texture_psnr"] < small_fits["trilinear"]["texture_psnr"] + 0.5
    with pytest.raises(SystemExit):
        fit_texture.main(["--capture", "x", "--mesh", "y", "--stochastic", "1"])

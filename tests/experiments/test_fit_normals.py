"""experiments/fit/fit_normals.py, short: the photometric-stereo fit recovers normals and albedo."""
from experiments.fit.fit_normals import run


def test_fit_normals_improves(tmp_path):
    m = run(iters=40, res=48, tex=24, progress=False, log_every=20, out=tmp_path)
    # Flat start: the true bumps are ~10 degrees off; 40 steps must remove most of it and lift the albedo.
    assert m["normal_error_deg_start"] > 5
    assert m["normal_error_deg"] < 0.5 * m["normal_error_deg_start"]
    assert m["albedo_psnr"] > m["albedo_psnr_start"] + 15
    assert (tmp_path / "images.png").stat().st_size > 0 and (tmp_path / "curves.png").stat().st_size > 0

"""The environment-lighting fit at a small size: the cube and the Phong highlight learn from mirror-sphere images."""
import json

from experiments.fit import fit_envmap


def test_envmap_fit_learns_environment_and_phong(tmp_path):
    m = fit_envmap.fit(iters=60, res=48, views=16, batch=4, progress=False, out=tmp_path, eval_every=20)
    print(m)
    # Measured (60 steps, 16 views of 48^2): environment 25.0 -> 38.2 dB on the seen directions; k_s and the
    # exponent move from 0.2 / 10 towards (0.9, 0.75, 0.5) / 40: errors 0.83 / 0.75 at the start, 0.34 / 0.27 here.
    assert m["env_psnr"] > m["initial_env_psnr"] + 8
    assert m["ks_error"] < 0.6 and m["exponent_error"] < 0.6
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert abs(saved["env_psnr"] - m["env_psnr"]) < 1e-9
    for name in ("views.png", "envmap.png", "curves.png"):
        assert (tmp_path / name).stat().st_size > 1000

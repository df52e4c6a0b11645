"""Fitting at scale: 2 processes (torchrun, gloo) against 1, runs killed and resumed, fits to a capture.

Every run here uses one intra-op thread: torch's CPU reductions and the native kernel's backward give the
same bits for the same thread count, which is what "bit-identical after a resume" rests on.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from difftex.io.capture import CaptureWarning
from difftex.testing.meshes import SPOT_TEXTURE
from experiments.fit import fit_texture, runtime

ROOT = Path(__file__).resolve().parents[2]
SMALL = dict(filter="trilinear", iters=20, res=32, views=8, batch=4, eval_views=2, progress=False)
CLI = ["--iters", "20", "--res", "32", "--views", "8", "--batch", "4", "--eval-views", "2", "--no-progress"]


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _env(**extra):
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    env.update({k: str(v) for k, v in extra.items()})
    return env


def _cli(out, *args, env=None, torchrun=0):
    launcher = ([sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={torchrun}"]
                if torchrun else [sys.executable])
    cmd = launcher + ["-m", "experiments.fit.fit_texture", *CLI, "--out", str(out), *args]
    return subprocess.run(cmd, cwd=ROOT, env=env or _env(), capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    m = fit_texture.fit(**SMALL, out=out, checkpoint_every=5, save=False)
    return m, torch.load(out / runtime.CHECKPOINT, weights_only=False)


def test_two_processes_match_one(reference, tmp_path):
    m1, ck1 = reference
    r = _cli(tmp_path, "--checkpoint-every", "20", torchrun=2)
    assert r.returncode == 0, r.stderr[-3000:]
    m2 = json.loads((tmp_path / "metrics.json").read_text())
    ck2 = torch.load(tmp_path / runtime.CHECKPOINT, weights_only=False)
    diff = (ck2["texture"] - ck1["texture"]).abs().max().item()
    print("max |texture diff| =", diff, "psnr", m1["texture_psnr"], m2["texture_psnr"])
    assert m2["processes"] == 2 and m2["allreduce_bytes_per_step"] == 3 * 1024 * 1024 * 4
    assert ck2["step"] == 20
    assert diff <= 1e-4
    assert abs(m2["texture_psnr"] - m1["texture_psnr"]) <= 0.05
    assert m2["texture_psnr"] > m1["initial_texture_psnr"] + 3  # it did fit


@pytest.mark.parametrize("hook, value, last_good", [(runtime.KILL_AT_STEP_ENV, 12, 10),
                                                    (runtime.KILL_IN_WRITE_ENV, 2, 5)])
def test_killed_run_resumes_to_the_same_texture(reference, tmp_path, hook, value, last_good):
    _, ck_ref = reference
    r = _cli(tmp_path, "--checkpoint-every", "5", env=_env(**{hook: value}))
    assert r.returncode == -9, r.stderr[-3000:]  # SIGKILL
    assert not (tmp_path / "metrics.json").exists()
    stale = list(tmp_path.glob(".checkpoint.pt.tmp-*"))
    if hook == runtime.KILL_IN_WRITE_ENV:
        # Killed halfway through writing step 10's checkpoint: a partial temporary file, step 5 intact.
        assert len(stale) == 1 and 0 < stale[0].stat().st_size < (tmp_path / runtime.CHECKPOINT).stat().st_size
    ck = runtime.load_checkpoint(tmp_path)
    assert ck["step"] == last_good and not list(tmp_path.glob(".checkpoint.pt.tmp-*"))
    m = fit_texture.fit(**SMALL, out=tmp_path, checkpoint_every=5, resume=True, save=False)
    final = runtime.load_checkpoint(tmp_path)
    assert final["step"] == 20
    assert torch.equal(final["texture"], ck_ref["texture"])  # bit-identical
    assert final["curve"] == ck_ref["curve"]
    assert m["texture_psnr"] == reference[0]["texture_psnr"]


def test_resume_refuses_other_settings(reference, tmp_path):
    fit_texture.fit(**dict(SMALL, iters=5), out=tmp_path, checkpoint_every=5, save=False)
    with pytest.raises(ValueError, match=r"--resume: .*other settings .*'iters': \(5, 20\)"):
        fit_texture.fit(**SMALL, out=tmp_path, checkpoint_every=5, resume=True, save=False)


def test_fit_to_capture_skips_frames_that_see_nothing(tmp_path):
    cap = tmp_path / "cap"
    fit_texture.make_capture(cap, res=32, views=4, seed=0)
    meta = json.loads((cap / "transforms.json").read_text())
    away = torch.tensor(meta["frames"][2]["transform_matrix"])
    away[:3, :3] = -away[:3, :3]  # turned round: looks away from spot, into empty space
    meta["frames"][2]["transform_matrix"] = away.tolist()
    (cap / "transforms.json").write_text(json.dumps(meta))
    mesh = ROOT / "data" / "spot" / "spot_triangulated.obj"
    with pytest.warns(CaptureWarning, match=r"frame 2 \('images/frame_00002.png'\): the camera sees nothing"):
        m = fit_texture.fit_capture(cap, mesh, iters=8, batch=2, lr=0.1, tex_size=1024, workers=1,
                                    out=tmp_path / "o", progress=False, reference_texture=SPOT_TEXTURE)
        grey = fit_texture.fit_capture(cap, mesh, iters=0, batch=2, tex_size=1024, workers=0, progress=False,
                                       save=False, reference_texture=SPOT_TEXTURE)
    print(m["image_psnr"], grey["image_psnr"], m["texture_psnr"], grey["texture_psnr"])
    assert m["frames"] == 4 and m["frames_used"] == 3
    assert m["image_psnr"] > grey["image_psnr"] + 3  # the photos' pixels under their alpha
    assert m["texture_psnr"] > grey["texture_psnr"] + 2
    assert (tmp_path / "o" / "texture.png").stat().st_size > 1000
    for f in meta["frames"]:
        f["transform_matrix"] = away.tolist()
    (cap / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="no frame's camera sees the mesh"):
        fit_texture.fit_capture(cap, mesh, iters=2, batch=2, tex_size=64, workers=0, out=tmp_path / "o",
                                progress=False, save=False)

"""The pose fit at a small size: a cube's rotation recovered from antialiased silhouettes."""
import json

import torch

from experiments.fit import fit_pose


def test_pose_fit_recovers_the_rotation_from_45_degrees_off():
    m = fit_pose.fit_pose(iters=60, res=48, views=4, start_deg=45.0, progress=False, save=False)
    print(m)
    assert abs(m["start_deg"] - 45.0) < 1e-3
    assert m["final_deg"] < 2.0


def test_pose_error_is_taken_modulo_the_cube_symmetries():
    R = fit_pose.rotation(torch.tensor([0.3, -0.2, 0.5]))
    quarter = fit_pose.rotation(torch.tensor([0.0, 0.0, torch.pi / 2]))
    tilt = fit_pose.rotation(torch.tensor([0.0, 0.1, 0.0]))
    assert fit_pose.cube_symmetries().shape == (24, 3, 3)
    assert fit_pose.pose_error_deg(R @ quarter, R) < 1e-4  # a symmetry of the cube: no error
    assert abs(fit_pose.pose_error_deg(tilt @ R, R) - 0.1 * 180 / torch.pi) < 1e-3


def test_fit_writes_metrics_and_figure(tmp_path):
    m = fit_pose.fit_pose(iters=2, res=24, views=2, progress=False, out=tmp_path)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["iters"] == 2 and abs(saved["final_deg"] - m["final_deg"]) < 1e-9
    assert (tmp_path / "pose.png").stat().st_size > 1000

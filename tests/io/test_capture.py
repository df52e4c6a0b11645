"""Captures in the transforms.json convention: the clip-space conversion, a spot round trip, bad frames."""
import json
import math

import pytest
import torch

import difftex
from difftex import camera
from difftex.io.capture import (CaptureDataset, CaptureWarning, intrinsics_from_projection, load_capture,
                                projection_from_intrinsics, save_capture, visible_frames)
from difftex.testing import spot_mesh, spot_texture

RES = 40


def test_centred_intrinsics_equal_perspective():
    fov_x = math.radians(50.0)
    w, h = 64, 48
    fl = 0.5 * w / math.tan(fov_x / 2)
    P = projection_from_intrinsics(fl, fl, w / 2, h / 2, w, h, 0.5, 20.0, dtype=torch.float64)
    fov_y = 2 * math.atan(0.5 * h / fl)
    ref = camera.perspective(fov_y, w / h, 0.5, 20.0, dtype=torch.float64)
    assert torch.allclose(P, ref, rtol=0, atol=1e-12)


def test_pixel_centre_convention():
    # A view-space point that the pinhole model puts at pixel (r, c)'s centre (image coordinate
    # (c + 0.5, r + 0.5), off-centre principal point) lands at DESIGN.md's NDC for that pixel centre.
    w, h, fl_x, fl_y, cx, cy = 8, 6, 7.0, 9.0, 3.1, 2.7
    P = projection_from_intrinsics(fl_x, fl_y, cx, cy, w, h, dtype=torch.float64)
    r, c, d = 2, 5, 3.0
    point = torch.tensor([(c + 0.5 - cx) * d / fl_x, -(r + 0.5 - cy) * d / fl_y, -d], dtype=torch.float64)
    clip = camera.transform(point[None], P)[0]
    ndc = clip[:2] / clip[3]
    assert torch.allclose(ndc, torch.tensor([(c + 0.5) / w * 2 - 1, 1 - (r + 0.5) / h * 2], dtype=torch.float64),
                          atol=1e-12)
    back = intrinsics_from_projection(P, w, h)
    for k, v in dict(fl_x=fl_x, fl_y=fl_y, cx=cx, cy=cy, near=0.1, far=100.0).items():
        assert back[k] == pytest.approx(v, rel=1e-12), k


def test_intrinsics_from_projection_rejects_orthographic():
    with pytest.raises(ValueError, match="proj: expected a pinhole perspective projection"):
        intrinsics_from_projection(camera.orthographic(-1.0, 1.0, -1.0, 1.0), 8, 8)


def _spot_views(n=4, res=RES):
    from experiments.fit.fit_texture import random_cameras

    proj, view = random_cameras(n, seed=3, dist_range=(2.5, 5.0))
    model = difftex.TexturedMesh(spot_mesh(), spot_texture(), filter="trilinear", learn_texture=False)
    with torch.no_grad():
        img, mask = model(proj @ view, (res, res))
    return model, proj, view, img, mask


@pytest.fixture(scope="module")
def spot_capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("spot_capture")
    model, proj, view, img, mask = _spot_views()
    save_capture(folder, img, view, proj, masks=mask)
    return folder, model, proj, view, img, mask


def test_round_trip_renders_equal_views(spot_capture):
    folder, model, proj, view, img, mask = spot_capture
    meta = json.loads((folder / "transforms.json").read_text())
    assert meta["w"] == RES and len(meta["frames"]) == 4
    # The JSON holds camera-to-world in OpenGL axes: the camera centre is the look_at eye.
    c2w = torch.tensor(meta["frames"][0]["transform_matrix"], dtype=torch.float64)
    eye = -view[0, :3, :3].double().T @ view[0, :3, 3].double()
    assert torch.allclose(c2w[:3, 3], eye, atol=1e-5)

    cap = load_capture(folder)
    assert len(cap) == 4 and cap.resolution == (RES, RES)
    ds = CaptureDataset(cap)
    items = [ds[i] for i in range(4)]
    images = torch.stack([it["image"] for it in items])
    masks = torch.stack([it["mask"] for it in items])
    assert (images - img).abs().max() <= 0.5 / 255 + 1e-6  # 8-bit files: half a code
    assert torch.equal(masks, mask)
    with torch.no_grad():
        again, mask2 = model(torch.stack([it["mvp"] for it in items]), (RES, RES))
    assert torch.equal(mask2, mask)
    assert (again - img).abs().max() <= 1 / 255
    assert mask.mean() > 0.05  # the views do see spot


def test_dataloader_with_workers_matches_indexing(spot_capture):
    ds = CaptureDataset(load_capture(spot_capture[0]))
    loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=1)
    batches = list(loader)
    assert [b["index"].tolist() for b in batches] == [[0, 1], [2, 3]]
    assert torch.equal(batches[1]["image"][0], ds[2]["image"])
    assert torch.equal(batches[0]["mvp"], torch.stack([ds[0]["mvp"], ds[1]["mvp"]]))


def test_blender_style_angle_and_path_without_extension(tmp_path):
    # Blender synthetic: camera_angle_x only, file_path without ".png", size from the image.
    img = torch.rand(3, 12, 16)
    difftex.save_image(tmp_path / "r_0.png", img)
    c2w = torch.eye(4)
    c2w[2, 3] = 4.0
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"camera_angle_x": 0.8, "frames": [{"file_path": "./r_0", "transform_matrix": c2w.tolist()}]}))
    cap = load_capture(tmp_path)
    f = cap.frames[0]
    assert (f.width, f.height) == (16, 12) and f.image_path.name == "r_0.png"
    assert f.fl_x == pytest.approx(8 / math.tan(0.4)) and f.fl_y == f.fl_x and (f.cx, f.cy) == (8, 6)
    P = camera.perspective(2 * math.atan(6 / f.fl_x), 16 / 12, dtype=torch.float64)
    assert torch.allclose(cap.mvp(torch.float64)[0], P @ torch.linalg.inv(c2w.double()), atol=1e-12)
    item = CaptureDataset(cap)[0]
    assert torch.equal(item["mask"], torch.ones(1, 12, 16))  # no alpha: every pixel counts


def test_angles_alone_and_per_frame_angles_over_shared_focal_lengths(tmp_path):
    # camera_angle_y alone raised (it now gives both focal lengths); a frame's own camera_angle_x lost to
    # the shared fl_x / fl_y (it now sets the frame's camera, square pixels).
    difftex.save_image(tmp_path / "a.png", torch.rand(3, 30, 40))
    frame = {"file_path": "a.png", "transform_matrix": torch.eye(4).tolist()}
    for top, own, want in (({"camera_angle_y": 0.9}, {}, 15 / math.tan(0.45)),
                           ({"fl_x": 50.0, "fl_y": 50.0}, {"camera_angle_x": 0.8}, 20 / math.tan(0.4)),
                           ({"camera_angle_x": 0.8}, {"fl_x": 60.0}, 60.0)):
        (tmp_path / "transforms.json").write_text(json.dumps({**top, "frames": [{**frame, **own}]}))
        f = load_capture(tmp_path).frames[0]
        assert (f.fl_x, f.fl_y) == (pytest.approx(want), pytest.approx(want)), (top, own)
        assert (f.cx, f.cy, f.width, f.height) == (20, 15, 40, 30)


def _bad_capture(tmp_path, **change):
    """Three good 8x8 frames, then ``change`` applied to the JSON of frame 1."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(3):
        difftex.save_image(tmp_path / f"f{i}.png", torch.rand(3, 8, 8))
        c2w = torch.eye(4)
        c2w[2, 3] = 3.0 + i
        frames.append({"file_path": f"f{i}.png", "transform_matrix": c2w.tolist()})
    frames[1].update(change)
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 4.0,
                                                          "w": 8, "h": 8, "frames": frames}))
    return tmp_path


def test_missing_image_raises_or_is_skipped(tmp_path):
    folder = _bad_capture(tmp_path, file_path="gone.png")
    with pytest.raises(FileNotFoundError, match=r"frame 1 \('gone.png'\): image not found"):
        load_capture(folder)
    with pytest.warns(CaptureWarning, match=r"skipping: .*frame 1 \('gone.png'\): image not found"):
        cap = load_capture(folder, on_bad="skip")
    assert [f.name for f in cap.frames] == ["f0.png", "f2.png"]


def test_wrong_size_names_the_frame(tmp_path):
    folder = _bad_capture(tmp_path)
    difftex.save_image(folder / "f1.png", torch.rand(3, 8, 10))
    with pytest.raises(ValueError, match=r"frame 1 \('f1.png'\): image .* is 10x8 pixels, the intrinsics say 8x8"):
        load_capture(folder)
    # Changed after loading: the lazy read names the frame too.
    cap = load_capture(_bad_capture(tmp_path / "b"))
    difftex.save_image(cap.frames[2].image_path, torch.rand(3, 9, 8))
    with pytest.raises(ValueError, match=r"frame 2 \('f2.png'\): image is 8x9 pixels, expected 8x8"):
        CaptureDataset(cap)[2]


@pytest.mark.parametrize("matrix, message", [
    ([[1, 0, 0, 0], [0, float("nan"), 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]], "NaN or infinite"),
    ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "must be 4x4"),
    ([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 3], [0, 0, 0, 1]], "singular"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 1, 1]], "last row must be"),
])
def test_bad_matrix_names_the_frame(tmp_path, matrix, message):
    folder = _bad_capture(tmp_path / "b", transform_matrix=[[x for x in row] for row in matrix])
    with pytest.raises(ValueError, match=rf"frame 1 \('f1.png'\): transform_matrix.*{message}"):
        load_capture(folder)


def test_everything_skipped_or_distorted_raises(tmp_path):
    folder = _bad_capture(tmp_path, k1=0.1)
    with pytest.raises(ValueError, match=r"frame 1 .*lens distortion k1=0.1 is not supported"):
        load_capture(folder)
    meta = json.loads((folder / "transforms.json").read_text())
    for f in meta["frames"]:
        f["file_path"] = "nowhere.png"
    (folder / "transforms.json").write_text(json.dumps(meta))
    with pytest.warns(CaptureWarning), pytest.raises(ValueError, match="no usable frame"):
        load_capture(folder, on_bad="skip")


def test_visible_frames_counts_pixels():
    mesh = spot_mesh()
    # Looking at spot, and from the same place looking away from it.
    view = camera.look_at(torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0]]),
                          torch.tensor([[0.0, 0.1, 0.2], [0.0, 0.0, 6.0]]))
    mvp = camera.perspective(40.0, 1.0, degrees=True) @ view
    counts = visible_frames(mvp, mesh.positions, mesh.faces, (16, 16), chunk=1)
    assert counts[0] > 20 and counts[1] == 0


def test_per_frame_intrinsics_round_trip(tmp_path):
    # Two cameras with different fields of view and an off-centre principal point: written as
    # nerfstudio-style per-frame intrinsics, read back as the same projections.
    P = torch.stack([camera.perspective(30.0, 1.5, 0.2, 50.0, degrees=True, dtype=torch.float64),
                     projection_from_intrinsics(20.0, 22.0, 5.0, 3.5, 12, 8, 0.2, 50.0, dtype=torch.float64)])
    V = camera.look_at(torch.tensor([[0.0, 0.0, 3.0], [1.0, 2.0, 3.0]], dtype=torch.float64))
    save_capture(tmp_path, torch.rand(2, 3, 8, 12), V, P, ext=".jpg")
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert "fl_x" not in meta and meta["frames"][1]["cx"] == pytest.approx(5.0)
    cap = load_capture(tmp_path)
    assert torch.allclose(cap.mvp(torch.float64), P @ V, atol=1e-12)


def test_save_capture_checks_arguments(tmp_path):
    V = camera.look_at(torch.tensor([[0.0, 0.0, 3.0]]))
    P = camera.perspective(0.8)
    with pytest.raises(ValueError, match=r"world_to_view: expected \[2, 4, 4\] like images"):
        save_capture(tmp_path, torch.rand(2, 3, 8, 8), V, P)
    with pytest.raises(ValueError, match="masks are written as alpha, which needs '.png'"):
        save_capture(tmp_path, torch.rand(1, 3, 8, 8), V, P, masks=torch.ones(1, 1, 8, 8), ext=".jpg")
    with pytest.raises(ValueError, match="proj: expected a pinhole perspective projection"):
        save_capture(tmp_path, torch.rand(1, 3, 8, 8), V, camera.orthographic(-1.0, 1.0, -1.0, 1.0))

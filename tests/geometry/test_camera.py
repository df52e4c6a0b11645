"""Tests for difftex.camera: known points land on known pixels, matrix properties, bad input."""

from __future__ import annotations

import math

import pytest
import torch

from difftex import camera, rasterize


@pytest.mark.parametrize("H,W", [(64, 64), (48, 96)])
def test_known_point_lands_on_expected_pixel(H, W):
    # Camera at z = 5 looking at the origin with a 90 degree vertical fov:
    # tan(fov / 2) = 1, so a point (X, Y, 0) has NDC (X / (5 aspect), Y / 5).
    r, c = 13, 40
    x_ndc = (c + 0.5) / W * 2 - 1
    y_ndc = 1 - (r + 0.5) / H * 2
    aspect = W / H
    point = torch.tensor([[x_ndc * 5 * aspect, y_ndc * 5, 0.0]], dtype=torch.float64)
    mvp = camera.perspective(90.0, aspect, 1.0, 20.0, degrees=True, dtype=torch.float64) @ camera.look_at(
        (0.0, 0.0, 5.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    ).double()
    clip = camera.transform(point, mvp)[0]
    ndc = clip[:3] / clip[3]
    assert float(clip[3]) == pytest.approx(5.0)
    col = (float(ndc[0]) + 1) / 2 * W - 0.5
    row = (1 - float(ndc[1])) / 2 * H - 0.5
    assert col == pytest.approx(c, abs=1e-9) and row == pytest.approx(r, abs=1e-9)

    # and the rasterizer puts a tiny triangle around it on exactly that pixel
    e = 0.2 * 5 / H  # a fifth of a pixel in world units at that distance
    tri = point + torch.tensor([[-e, -e, 0.0], [e, -e, 0.0], [0.0, e, 0.0]], dtype=torch.float64)
    frags = rasterize(camera.transform(tri, mvp), torch.tensor([[0, 1, 2]]), (H, W))
    hit = torch.nonzero(frags.tri_id[0] >= 0).tolist()
    assert hit == [[r, c]]


def test_look_at_is_rigid_and_points_the_camera():
    eye = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    at = torch.tensor([-0.5, 0.3, 0.1], dtype=torch.float64)
    V = camera.look_at(eye, at, (0.0, 1.0, 0.0))
    assert V.shape == (4, 4) and V.dtype == torch.float64
    R = V[:3, :3]
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64))
    assert float(torch.det(R)) == pytest.approx(1.0)
    h = lambda p: V @ torch.cat((p, torch.ones(1, dtype=torch.float64)))
    torch.testing.assert_close(h(eye)[:3], torch.zeros(3, dtype=torch.float64))
    dist = float((at - eye).norm())
    torch.testing.assert_close(h(at)[:3], torch.tensor([0.0, 0.0, -dist], dtype=torch.float64))
    # world up stays up (positive view y), the view x axis points right
    assert float(h(eye + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))[1]) > 0
    # batched eyes broadcast against a shared target
    eyes = torch.tensor([[0.0, 0.0, 4.0], [4.0, 0.0, 0.0]])
    Vb = camera.look_at(eyes, (0.0, 0.0, 0.0))
    assert Vb.shape == (2, 4, 4) and Vb.dtype == torch.float32
    # the second camera looks down world -x: that direction becomes view -z
    torch.testing.assert_close(Vb[1, :3, :3] @ torch.tensor([-1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, -1.0]))


def test_perspective_depth_range_and_units():
    P = camera.perspective(math.radians(60.0), 1.5, 0.5, 30.0, dtype=torch.float64)
    torch.testing.assert_close(P, camera.perspective(60.0, 1.5, 0.5, 30.0, degrees=True, dtype=torch.float64))
    for z_view, z_ndc in ((-0.5, -1.0), (-30.0, 1.0)):
        clip = P @ torch.tensor([0.0, 0.0, z_view, 1.0], dtype=torch.float64)
        assert float(clip[2] / clip[3]) == pytest.approx(z_ndc)
        assert float(clip[3]) == pytest.approx(-z_view)
    # the top edge of the frustum maps to NDC y = 1, the right edge to x = 1
    t = math.tan(math.radians(30.0))
    clip = P @ torch.tensor([t * 1.5 * 2.0, t * 2.0, -2.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(clip[:2] / clip[3], torch.ones(2, dtype=torch.float64))
    assert camera.perspective(1.0, 1.0, 0.1, 10.0).dtype == torch.float32


def test_orthographic_maps_box_to_ndc_cube():
    O = camera.orthographic(-2.0, 6.0, -1.0, 3.0, 0.5, 10.0, dtype=torch.float64)
    pts = torch.tensor([[-2.0, 3.0, -0.5], [6.0, -1.0, -10.0], [2.0, 1.0, -5.25]], dtype=torch.float64)
    clip = camera.transform(pts, O)
    torch.testing.assert_close(clip[:, 3], torch.ones(3, dtype=torch.float64))
    expected = torch.tensor([[-1.0, 1.0, -1.0], [1.0, -1.0, 1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(clip[:, :3], expected)


def test_camera_is_differentiable():
    eye = torch.tensor([0.3, 0.4, 2.0], dtype=torch.float64, requires_grad=True)
    fov = torch.tensor(0.9, dtype=torch.float64, requires_grad=True)
    pts = torch.tensor([[0.1, 0.2, 0.0], [-0.3, 0.1, 0.2]], dtype=torch.float64)

    def fn(eye, fov):
        mvp = camera.perspective(fov, 1.2, 0.1, 10.0) @ camera.look_at(eye, (0.0, 0.0, 0.0))
        c = camera.transform(pts, mvp)
        return c[:, :3] / c[:, 3:]

    assert torch.autograd.gradcheck(fn, (eye, fov))


def test_bad_input_errors_name_the_argument():
    with pytest.raises(ValueError, match="eye and at"):
        camera.look_at((1.0, 1.0, 1.0), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="up"):
        camera.look_at((0.0, 2.0, 0.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    with pytest.raises(ValueError, match="eye.*\\[..., 3\\]"):
        camera.look_at((0.0, 2.0), (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="fov_y"):
        camera.perspective(180.0, 1.0, 0.1, 1.0, degrees=True)
    with pytest.raises(ValueError, match="fov_y"):
        camera.perspective(-0.5, 1.0, 0.1, 1.0)
    with pytest.raises(ValueError, match="near"):
        camera.perspective(1.0, 1.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="near < far"):
        camera.perspective(1.0, 1.0, 2.0, 1.0)
    with pytest.raises(ValueError, match="aspect"):
        camera.perspective(1.0, 0.0, 0.1, 1.0)
    with pytest.raises(ValueError, match="left < right"):
        camera.orthographic(1.0, -1.0, -1.0, 1.0)
    with pytest.raises(ValueError, match="fov_y.*finite"):
        camera.perspective(float("nan"), 1.0, 0.1, 1.0)
    with pytest.raises(ValueError, match="points"):
        camera.transform(torch.rand(5, 2), torch.eye(4))
    with pytest.raises(ValueError, match="matrix"):
        camera.transform(torch.rand(5, 3), torch.eye(3))
    with pytest.raises(ValueError, match=r"points' batch shape \(2,\) and matrix's \(3,\) must broadcast"):
        camera.transform(torch.rand(2, 5, 3), torch.rand(3, 4, 4))
    with pytest.raises(TypeError, match="dtype"):
        camera.perspective(1.0, dtype=torch.int64)


@pytest.mark.parametrize("default", [torch.float64, torch.float32])
def test_no_tensor_arguments_follow_the_default_dtype(default):
    # Like torch.tensor(1.0) and mapping.uv_transform: with no float tensor to follow, the default dtype.
    previous = torch.get_default_dtype()
    torch.set_default_dtype(default)
    try:
        mats = [camera.look_at((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
                camera.perspective(60.0, 1.5, 0.1, 10.0, degrees=True),
                camera.orthographic(-1.0, 1.0, -1.0, 1.0, 0.1, 10.0),
                camera.look_at(torch.tensor([1, 2, 3]), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))]  # int tensor
        assert [m.dtype for m in mats] == [default] * 4
        # float tensors still decide, and an explicit dtype wins
        assert camera.perspective(torch.tensor(1.0, dtype=torch.float32), 1.0, 0.1, 10.0).dtype == torch.float32
        assert camera.orthographic(-1.0, 1.0, -1.0, 1.0, 0.1, 10.0, dtype=torch.float32).dtype == torch.float32
        # same values as the float64 build, to the default's precision
        want = camera.perspective(60.0, 1.5, 0.1, 10.0, degrees=True, dtype=torch.float64)
        torch.testing.assert_close(mats[1].double(), want, rtol=1e-6, atol=1e-6)
    finally:
        torch.set_default_dtype(previous)
    assert torch.get_default_dtype() == previous

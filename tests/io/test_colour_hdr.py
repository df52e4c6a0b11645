"""Tests for difftex.io: sRGB decoding / encoding, Radiance HDR through OpenCV, the optional-extra errors."""

import sys

import numpy as np
import pytest
import torch

from difftex import io
from difftex.io.images import _apply_to_colour

kornia_color = pytest.importorskip("kornia.color")
pytest.importorskip("cv2")


def srgb_to_linear(c):
    """IEC 61966-2-1 decoding, written from the standard (not kornia's code)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x):
    """IEC 61966-2-1 encoding."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)


# ----------------------------------------------------------------- sRGB


def test_reference_formula_known_values():
    # Guards the reference used below: published values of the sRGB curve.
    assert srgb_to_linear(0.5) == pytest.approx(0.21404, abs=5e-6)
    assert srgb_to_linear(0.04045) == pytest.approx(0.0031308, abs=1e-7)
    assert srgb_to_linear(1.0) == 1.0 and srgb_to_linear(0.0) == 0.0
    assert linear_to_srgb(0.0031308) == pytest.approx(0.04045, abs=1e-7)


def test_transfer_known_values():
    x = torch.tensor([0.5, 0.04045, 1.0, 0.0], dtype=torch.float64).reshape(1, 1, 1, 4)
    lin = _apply_to_colour(x, kornia_color.rgb_to_linear_rgb)
    torch.testing.assert_close(lin.flatten(), torch.tensor([0.21404, 0.0031308, 1.0, 0.0], dtype=torch.float64),
                               atol=5e-6, rtol=0)
    assert lin[0, 0, 0, 2].item() == 1.0 and lin[0, 0, 0, 3].item() == 0.0
    torch.testing.assert_close(lin.flatten(), torch.as_tensor(srgb_to_linear(x.flatten().numpy())),
                               atol=1e-12, rtol=0)


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_load_srgb_every_8bit_code(tmp_path, channels):
    codes = np.arange(256, dtype=np.float64).reshape(16, 16) / 255
    x = torch.as_tensor(codes).expand(channels, 16, 16).clone()
    if channels in (2, 4):
        x[-1] = 0.25  # alpha, code 64
    io.save_image(tmp_path / "c.png", x)
    raw = io.load_texture(tmp_path / "c.png", dtype=torch.float64)
    lin = io.load_texture(tmp_path / "c.png", srgb=True, dtype=torch.float64)
    n = 1 if channels <= 2 else 3
    # default: values as stored
    torch.testing.assert_close(raw[0, :n], torch.as_tensor(codes).expand(n, 16, 16), atol=1e-15, rtol=0)
    torch.testing.assert_close(lin[0, :n], torch.as_tensor(srgb_to_linear(codes)).expand(n, 16, 16),
                               atol=1e-12, rtol=0)
    if channels in (2, 4):
        assert (lin[0, -1] - 64 / 255).abs().max().item() == 0.0  # alpha untouched


def test_load_srgb_16bit(tmp_path):
    codes = np.array([[0, 1, 2650, 2651, 32768, 65535]], dtype=np.float64) / 65535  # 2650.9 / 65535 = 0.04045
    io.save_image(tmp_path / "c16.png", torch.as_tensor(codes).expand(3, 1, 6), bits=16)
    lin = io.load_texture(tmp_path / "c16.png", srgb=True, dtype=torch.float64)
    torch.testing.assert_close(lin[0], torch.as_tensor(srgb_to_linear(codes)).expand(3, 1, 6), atol=1e-12, rtol=0)


def test_save_srgb_writes_encoded_codes(tmp_path):
    # Linear values whose sRGB encodings are exactly the 256 codes come back as those codes.
    codes = np.arange(256, dtype=np.float64).reshape(1, 16, 16) / 255
    rgba = torch.as_tensor(srgb_to_linear(codes)).expand(4, 16, 16).clone()
    rgba[3] = 0.25
    io.save_image(tmp_path / "e.png", rgba, srgb=True)
    stored = io.load_texture(tmp_path / "e.png", dtype=torch.float64)  # as stored
    torch.testing.assert_close(stored[0, :3], torch.as_tensor(codes).expand(3, 16, 16), atol=1e-15, rtol=0)
    assert (stored[0, 3] - 64 / 255).abs().max().item() == 0.0  # alpha written linearly


@pytest.mark.parametrize("bits,channels", [(8, 1), (8, 2), (8, 3), (8, 4), (16, 3), (16, 2)])
def test_srgb_round_trip(tmp_path, bits, channels):
    g = torch.Generator().manual_seed(bits + channels)
    x = torch.rand(1, channels, 12, 9, dtype=torch.float64, generator=g)
    x[0, 0, 0, :3] = torch.tensor([0.0, 1.0, 0.002], dtype=torch.float64)  # ends and the linear segment
    io.save_image(tmp_path / "r.png", x, bits=bits, srgb=True)
    y = io.load_texture(tmp_path / "r.png", srgb=True, dtype=torch.float64)
    assert y.shape == x.shape
    code = 255 if bits == 8 else 65535
    n = 1 if channels <= 2 else 3
    # Within half a code once encoded (the file quantises the encoded value).
    err = np.abs(linear_to_srgb(y[0, :n].numpy()) - linear_to_srgb(x[0, :n].numpy())).max()
    assert err <= 0.5 / code + 1e-12
    if channels in (2, 4):  # alpha: half a code of the value itself
        assert (y[0, -1] - x[0, -1]).abs().max().item() <= 0.5 / code + 1e-12
    # Dark linear values keep more precision than an as-stored (srgb=False) round trip would.
    assert y[0, 0, 0, 2].item() == pytest.approx(0.002, abs=2e-4 if bits == 8 else 1e-6)


def test_srgb_argument_checked(tmp_path):
    io.save_image(tmp_path / "a.png", torch.rand(3, 2, 2))
    with pytest.raises(TypeError, match="srgb must be a bool"):
        io.load_texture(tmp_path / "a.png", srgb="yes")
    with pytest.raises(TypeError, match="srgb must be a bool"):
        io.save_image(tmp_path / "a.png", torch.rand(3, 2, 2), srgb=None)


# ----------------------------------------------------------------- Radiance HDR


def _rgbe_bound(x):
    """Per pixel, one RGBE step: 2^e / 256 where 2^(e-1) <= max channel < 2^e."""
    m = x.max(axis=0)
    e = np.frexp(m)[1]
    return np.ldexp(1.0, e - 8)


def test_hdr_round_trip_values_above_one(tmp_path):
    rng = np.random.default_rng(3)
    x = 2.0 ** rng.uniform(-6, 10, size=(3, 7, 11))  # 0.016 .. 1024, flat and RLE-coded rows both below
    x[:, 0, 0] = [1.5, 100.0, 3.0]  # 8-bit mantissas under the pixel's exponent: exact
    io.save_image(tmp_path / "e.hdr", torch.as_tensor(x))
    for dtype in (torch.float32, torch.float64):
        y = io.load_texture(tmp_path / "e.hdr", dtype=dtype)
        assert y.shape == (1, 3, 7, 11) and y.dtype == dtype
        yy = y[0].double().numpy()
        assert (np.abs(yy - x) <= _rgbe_bound(x)[None]).all()
        # the largest channel keeps its 8-bit mantissa: relative error under 1/128 (1/256 of 2^e)
        mx = x.max(axis=0)
        assert (np.abs(yy.max(axis=0) - mx) / mx < 1 / 128).all()
        assert yy.max() > 500.0  # not clamped to [0, 1]
        assert yy[:, 0, 0].tolist() == [1.5, 100.0, 3.0]


def test_hdr_wide_rows_use_rle(tmp_path):
    # Width 8..32767 makes OpenCV write run-length rows; the round trip must not depend on it.
    x = torch.linspace(0.0, 40.0, 3 * 4 * 64, dtype=torch.float64).reshape(3, 4, 64)
    io.save_image(tmp_path / "w.hdr", x)
    y = io.load_texture(tmp_path / "w.hdr", dtype=torch.float64)[0].numpy()
    assert (np.abs(y - x.numpy()) <= _rgbe_bound(x.numpy())[None]).all()


def test_hdr_channel_order(tmp_path):
    # A file written by hand from the format (flat pixels r, g, b, e with value m * 2^(e - 136)):
    # pixel 0 red = 1, pixel 1 blue = 1, so a BGR swap cannot hide.
    data = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 2\n" + bytes([128, 0, 0, 129, 0, 0, 128, 129])
    (tmp_path / "hand.hdr").write_bytes(data)
    y = io.load_texture(tmp_path / "hand.hdr", dtype=torch.float64)
    assert y.shape == (1, 3, 1, 2)
    torch.testing.assert_close(y[0, :, 0, 0], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), atol=4e-3, rtol=0)
    torch.testing.assert_close(y[0, :, 0, 1], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=4e-3, rtol=0)
    # and the writer puts red first in the file
    red = torch.zeros(3, 1, 2, dtype=torch.float64)
    red[0] = 4.0
    io.save_image(tmp_path / "red.hdr", red)
    raw = (tmp_path / "red.hdr").read_bytes()
    pixels = raw[raw.index(b"+X 2\n") + 5:]
    assert pixels[:4] == bytes([128, 0, 0, 131])  # 4 = 128 * 2^(131 - 136)
    back = io.load_texture(tmp_path / "red.hdr", dtype=torch.float64)
    assert back[0, :, 0, 0].tolist() == [4.0, 0.0, 0.0]


def test_hdr_grey_negative_and_srgb_flag(tmp_path):
    g = torch.tensor([[0.5, 2.0, -3.0]], dtype=torch.float64)
    io.save_image(tmp_path / "g.hdr", g, srgb=True)  # HDR stores linear values: srgb changes nothing
    y = io.load_texture(tmp_path / "g.hdr", dtype=torch.float64)
    assert y.shape == (1, 3, 1, 3)
    assert y[0, :, 0].tolist() == [[0.5, 2.0, 0.0]] * 3  # grey as three channels, negative clamped to 0
    torch.testing.assert_close(io.load_texture(tmp_path / "g.hdr", srgb=True, dtype=torch.float64), y,
                               atol=0, rtol=0)


def test_hdr_errors(tmp_path):
    with pytest.raises(ValueError, match=r"HDR image needs 1 or 3 channels.*\(4, 2, 2\)"):
        io.save_image(tmp_path / "a.hdr", torch.rand(4, 2, 2))
    with pytest.raises(ValueError, match=r"HDR image needs 1 or 3 channels.*\(2, 2, 2\)"):
        io.save_image(tmp_path / "a.hdr", torch.rand(2, 2, 2))
    with pytest.raises(ValueError, match="NaN or infinite"):
        io.save_image(tmp_path / "a.hdr", torch.full((3, 2, 2), float("inf")))
    big = torch.full((3, 2, 2), 2.0 ** 127, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"below 2\^127"):
        io.save_image(tmp_path / "a.hdr", big)
    assert not (tmp_path / "a.hdr").exists()
    io.save_image(tmp_path / "ok.hdr", torch.rand(3, 16, 16) * 10)
    data = (tmp_path / "ok.hdr").read_bytes()
    (tmp_path / "cut.hdr").write_bytes(data[: len(data) - 40])
    with pytest.raises(ValueError, match=r"cut.hdr'?: corrupt or truncated Radiance HDR data"):
        io.load_texture(tmp_path / "cut.hdr")
    (tmp_path / "text.hdr").write_bytes(b"hello")
    with pytest.raises(ValueError, match="text.hdr' is not a Radiance HDR file"):
        io.load_texture(tmp_path / "text.hdr")
    (tmp_path / "flip.hdr").write_bytes(data.replace(b"-Y 16 +X 16", b"+Y 16 +X 16"))
    with pytest.raises(ValueError, match=r"flip.hdr'?: unsupported Radiance resolution line.*-Y <height> \+X"):
        io.load_texture(tmp_path / "flip.hdr")
    (tmp_path / "empty.hdr").write_bytes(data.replace(b"-Y 16 +X 16", b"-Y 0 +X 16"))
    with pytest.raises(ValueError, match=r"empty.hdr'?: the header gives an empty 16x0"):
        io.load_texture(tmp_path / "empty.hdr")
    io.save_image(tmp_path / "sun.hdr", torch.full((3, 1, 1), 1e5))
    with pytest.raises(ValueError, match=r"sun.hdr'?: values up to 9.9.*e\+04 overflow dtype torch.float16"):
        io.load_texture(tmp_path / "sun.hdr", dtype=torch.float16)


# ----------------------------------------------------------------- without OpenCV


def test_without_opencv(tmp_path, monkeypatch):
    io.save_image(tmp_path / "a16.png", torch.rand(3, 4, 4), bits=16)
    io.save_image(tmp_path / "a.hdr", torch.rand(3, 4, 4))
    monkeypatch.setitem(sys.modules, "cv2", None)  # import cv2 now raises ImportError
    hint = r"pip install difftex\[images\]"
    with pytest.raises(ImportError, match="16-bit PNG needs OpenCV.*" + hint):
        io.load_texture(tmp_path / "a16.png")
    with pytest.raises(ImportError, match="16-bit PNG needs OpenCV.*" + hint):
        io.save_image(tmp_path / "b16.png", torch.rand(3, 4, 4), bits=16)
    with pytest.raises(ImportError, match="Radiance HDR image needs OpenCV.*" + hint):
        io.load_texture(tmp_path / "a.hdr")
    with pytest.raises(ImportError, match="Radiance HDR image needs OpenCV.*" + hint):
        io.save_image(tmp_path / "b.hdr", torch.rand(3, 4, 4))
    # 8-bit PNG and JPEG go through imageio as before
    x = torch.rand(3, 4, 4, dtype=torch.float64)
    for name in ("a8.png", "a.jpg"):
        io.save_image(tmp_path / name, x)
        assert io.load_texture(tmp_path / name).shape == (1, 3, 4, 4)
    assert (io.load_texture(tmp_path / "a8.png", dtype=torch.float64)[0] - x).abs().max().item() <= 0.5 / 255 + 1e-12
    # grey + alpha 16-bit is written without OpenCV (neither OpenCV nor Pillow writes it)
    io.save_image(tmp_path / "la16.png", torch.rand(2, 4, 4), bits=16)
    ihdr = (tmp_path / "la16.png").read_bytes()[16:26]
    assert ihdr == bytes([0, 0, 0, 4, 0, 0, 0, 4, 16, 4])  # width 4, height 4, 16 bits, colour type 4 (grey + alpha)

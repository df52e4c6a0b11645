"""Tests for difftex.io: malformed headers, pixel caps, non-finite mesh data, argument types."""

import struct
import warnings
import zlib

import numpy as np
import pytest
import torch

from difftex import io

pytest.importorskip("cv2")
Image = pytest.importorskip("PIL.Image")


def _chunk(tag, data):
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def _png_with_header(path, w, h, ctype=2, depth=16, rows=None):
    """A PNG whose IHDR says w x h; IDAT holds ``rows`` raw bytes (default: what the header asks for)."""
    bpp = {0: 1, 4: 2, 2: 3, 6: 4}[ctype] * depth // 8
    raw = rows if rows is not None else b"".join(b"\0" + b"\0" * (w * bpp) for _ in range(h))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0))
                     + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b""))


# ----------------------------------------------------------------- PNG headers and pixel caps


@pytest.mark.parametrize("w,h", [(0, 2), (2, 0)])
def test_png16_empty_header_raises(tmp_path, w, h):
    # The old decoder returned a [1, 3, 0, 2] / [1, 3, 2, 0] texture.
    _png_with_header(tmp_path / "e.png", w, h, rows=b"\0" * 2)
    with pytest.raises(ValueError, match=rf"e.png'?: the header gives an empty {w}x{h} \(width x height\) image"):
        io.load_texture(tmp_path / "e.png")


def test_png8_empty_header_raises(tmp_path):
    _png_with_header(tmp_path / "e8.png", 0, 2, depth=8, rows=b"\0" * 2)
    with pytest.raises(ValueError, match=r"e8.png'?: the header gives an empty 0x2"):
        io.load_texture(tmp_path / "e8.png")


def test_png16_pixel_cap_from_header(tmp_path):
    # 16400^2 RGBA16 is 2.15 GB decoded; the header alone decides (nothing is inflated), as Pillow does
    # for 8-bit files.  The old decoder inflated first (here: a corrupt-data error; with real data a
    # bare MemoryError).
    path = tmp_path / "bomb.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", 16400, 16400, 16, 6, 0, 0, 0))
                     + _chunk(b"IEND", b""))
    assert 16400 ** 2 > 2 * Image.MAX_IMAGE_PIXELS
    with pytest.raises(ValueError, match=r"bomb.png'?: image size 16400x16400 \(268960000 pixels\) exceeds "
                                         r"\d+ pixels, twice PIL.Image.MAX_IMAGE_PIXELS"):
        io.load_texture(path)


@pytest.mark.parametrize("bits", [8, 16])
def test_pixel_cap_follows_pillow_setting(tmp_path, monkeypatch, bits):
    x = torch.rand(3, 8, 8)
    io.save_image(tmp_path / "s.png", x, bits=bits)  # 64 pixels
    io.save_image(tmp_path / "b.png", torch.rand(3, 11, 11), bits=bits)  # 121 pixels
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 50)
    # between the limit and twice it: Pillow's warning, and the image loads
    with pytest.warns(Image.DecompressionBombWarning):
        assert io.load_texture(tmp_path / "s.png").shape == (1, 3, 8, 8)
    # above twice the limit: ValueError naming the file, for 8-bit (Pillow) and 16-bit (OpenCV) alike
    with pytest.raises(ValueError, match="b.png"):
        io.load_texture(tmp_path / "b.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", None)  # Pillow's "no limit"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert io.load_texture(tmp_path / "b.png").shape == (1, 3, 11, 11)


def test_hdr_pixel_cap(tmp_path, monkeypatch):
    io.save_image(tmp_path / "b.hdr", torch.rand(3, 11, 11))
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 50)
    with pytest.raises(ValueError, match=r"b.hdr'?: image size 11x11 \(121 pixels\) exceeds 100 pixels"):
        io.load_texture(tmp_path / "b.hdr")


def test_png16_trns_and_truncated_rows(tmp_path):
    # A tRNS key becomes an alpha channel, as Pillow does for 8-bit files (the old 16-bit decoder dropped it,
    # OpenCV keeps the RGB key but drops the grey one).
    a = np.array([[0, 1000], [40000, 65535]], np.uint16)
    for ctype, pixels, key in ((0, a[:, :, None], struct.pack(">H", 1000)),
                               (2, np.stack([a, a // 2, a // 3], -1), struct.pack(">HHH", 1000, 500, 333))):
        raw = b"".join(b"\0" + row.astype(">u2").tobytes() for row in pixels)
        (tmp_path / "t.png").write_bytes(
            b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", 2, 2, 16, ctype, 0, 0, 0))
            + _chunk(b"tRNS", key) + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b""))
        t = io.load_texture(tmp_path / "t.png", dtype=torch.float64)
        c = pixels.shape[2]
        assert t.shape == (1, c + 1, 2, 2)
        torch.testing.assert_close(t[0, :c], torch.as_tensor(pixels / 65535.0).permute(2, 0, 1), atol=1e-15, rtol=0)
        assert t[0, c].tolist() == [[1.0, 0.0], [1.0, 1.0]]
    # A valid zlib stream with fewer rows than the header says.
    _png_with_header(tmp_path / "short.png", 4, 4, rows=b"\0" * (1 + 4 * 6) * 2)
    with pytest.raises(ValueError, match=r"short.png'?: corrupt or truncated PNG data"):
        io.load_texture(tmp_path / "short.png")


# ----------------------------------------------------------------- argument types


def test_load_texture_dtype_must_be_a_floating_torch_dtype(tmp_path):
    io.save_image(tmp_path / "a.png", torch.rand(3, 2, 2))
    with pytest.raises(TypeError, match=r"dtype must be a floating torch.dtype.*got 'float32'"):
        io.load_texture(tmp_path / "a.png", dtype="float32")
    with pytest.raises(TypeError, match=r"dtype must be a floating torch.dtype.*got torch.uint8"):
        io.load_texture(tmp_path / "a.png", dtype=torch.uint8)


def test_load_mesh_dtype_must_be_floating(tmp_path):
    (tmp_path / "t.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0.25 0.25\nf 1/1 2/1 3/1\n")
    # The old loader returned uv [[0, 0]] for int64: 0.25 truncated.
    with pytest.raises(TypeError, match=r"dtype must be a floating torch.dtype.*got torch.int64"):
        io.load_mesh(tmp_path / "t.obj", dtype=torch.int64)
    with pytest.raises(TypeError, match=r"dtype must be a floating torch.dtype.*got 'float64'"):
        io.load_mesh(tmp_path / "t.obj", dtype="float64")
    assert io.load_mesh(tmp_path / "t.obj", dtype=torch.float64).uv.tolist() == [[0.25, 0.75]]


def test_path_none_is_a_type_error(tmp_path):
    with pytest.raises(TypeError, match=r"path must be a str or os.PathLike naming the image file, got NoneType"):
        io.load_texture(None)
    with pytest.raises(TypeError, match=r"path must be a str or os.PathLike naming the mesh file, got NoneType"):
        io.load_mesh(None)
    with pytest.raises(TypeError, match=r"path must be a str or os.PathLike naming the image file, got int"):
        io.save_image(3, torch.rand(3, 2, 2))


# ----------------------------------------------------------------- non-finite and huge mesh data


TRI = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"


@pytest.mark.parametrize("line,lineno", [
    ("v nan 0 0", 7), ("v 0 inf 0", 7), ("v 0 0 -inf", 7), ("vt nan 0.5", 7), ("vt 0.5 inf", 7), ("vt NaN", 7),
    ("vn 0 nan 1", 7),
])
def test_obj_non_finite_coordinates_name_the_line(tmp_path, line, lineno):
    (tmp_path / "nan.obj").write_text(TRI + line + "\nf 1/1 2/2 3/3\n")
    with pytest.raises(ValueError, match=rf"nan.obj'? line {lineno}: cannot parse '{line}' \(non-finite coordinate"):
        io.load_mesh(tmp_path / "nan.obj")


@pytest.mark.parametrize("corner", ["99999999999999999999/1", "1/-99999999999999999999", "1/1/99999999999999999999"])
def test_obj_index_past_int64_names_the_file(tmp_path, corner):
    # The old parser kept the Python int and numpy raised a bare OverflowError.
    (tmp_path / "huge.obj").write_text(TRI + "vn 0 0 1\nf 1/1/1 2/2/1 " + corner + "\n")
    with pytest.raises(ValueError, match=r"huge.obj'? line 8: cannot parse .*out of the int64 range"):
        io.load_mesh(tmp_path / "huge.obj")


def test_obj_index_just_out_of_range_still_reported(tmp_path):
    (tmp_path / "r.obj").write_text(TRI + "f 1/1 2/2 4611686018427387903/3\n")  # 2^62 - 1: fits, out of range
    with pytest.raises(ValueError, match=r"r.obj'?: position index out of range \[0, 3\)"):
        io.load_mesh(tmp_path / "r.obj")


def test_obj_vt_without_numbers(tmp_path):
    (tmp_path / "vt.obj").write_text(TRI + "vt\nf 1/1 2/2 3/3\n")
    with pytest.raises(ValueError, match=r"vt.obj'? line 7: .*'vt' needs at least a u coordinate"):
        io.load_mesh(tmp_path / "vt.obj")
    (tmp_path / "u.obj").write_text(TRI + "vt 0.5\nf 1/1 2/2 3/4\n")  # v missing: 0 per the spec, 1 after the flip
    assert io.load_mesh(tmp_path / "u.obj", dtype=torch.float64).uv[3].tolist() == [0.5, 1.0]


def test_ply_nan_position_names_the_field(tmp_path):
    header = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
              "property float s\nproperty float t\nelement face 1\nproperty list uchar int vertex_indices\n"
              "end_header\n")
    (tmp_path / "nan.ply").write_text(header + "0 0 0 0 0\nnan 0 0 1 0\n0 1 0 0 1\n3 0 1 2\n")
    with pytest.raises(ValueError, match=r"nan.ply'?: positions has NaN or infinite values"):
        io.load_mesh(tmp_path / "nan.ply")
    (tmp_path / "nanuv.ply").write_text(header + "0 0 0 0 0\n1 0 0 inf 0\n0 1 0 0 1\n3 0 1 2\n")
    with pytest.raises(ValueError, match=r"nanuv.ply'?: uv has NaN or infinite values"):
        io.load_mesh(tmp_path / "nanuv.ply")
    (tmp_path / "ok.ply").write_text(header + "0 0 0 0 0\n1 0 0 1 0\n0 1 0 0 1\n3 0 1 2\n")
    assert io.load_mesh(tmp_path / "ok.ply", dtype=torch.float64).uv.tolist() == [[0, 1], [1, 1], [0, 0]]

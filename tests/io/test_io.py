"""Tests for difftex.io: image round trips, the spot mesh, error messages."""

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from difftex import io

REPO = Path(__file__).resolve().parents[2]
SPOT_OBJ = REPO / "data" / "spot" / "spot_triangulated.obj"
SPOT_PNG = REPO / "data" / "spot" / "spot_texture.png"

# Counts read off the file with grep: 2930 'v', 3225 'vt', 0 'vn', 5856 'f' lines (all triangles).
SPOT_V, SPOT_VT, SPOT_F = 2930, 3225, 5856


@pytest.fixture(scope="module")
def spot():
    return io.load_mesh(SPOT_OBJ, dtype=torch.float64)


# ----------------------------------------------------------------- images


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_png8_round_trip(tmp_path, channels):
    x = torch.rand(channels, 13, 17, dtype=torch.float64, generator=torch.Generator().manual_seed(channels))
    io.save_image(tmp_path / "a.png", x)
    y = io.load_texture(tmp_path / "a.png", dtype=torch.float64)
    assert y.shape == (1, channels, 13, 17)
    # rounding to the nearest 8-bit code: at most half a code off
    assert (y[0] - x).abs().max().item() <= 0.5 / 255 + 1e-12


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_png16_round_trip(tmp_path, channels):
    x = torch.rand(1, channels, 9, 11, dtype=torch.float64, generator=torch.Generator().manual_seed(10 + channels))
    io.save_image(tmp_path / "a.png", x, bits=16)
    y = io.load_texture(tmp_path / "a.png", dtype=torch.float64)
    assert y.shape == (1, channels, 9, 11)
    assert (y - x).abs().max().item() <= 0.5 / 65535 + 1e-12
    # and 16 bits really are 16 bits (an 8-bit reduction would be ~1/510 off)
    assert (y - x).abs().max().item() < 1.0 / 65535


def test_grayscale_hw_and_rgba(tmp_path):
    g = torch.linspace(0, 1, 8 * 5, dtype=torch.float64).reshape(8, 5)
    io.save_image(tmp_path / "g.png", g)
    tex = io.load_texture(tmp_path / "g.png", dtype=torch.float64)
    assert tex.shape == (1, 1, 8, 5)
    assert tex[0, 0, 0, 0].item() == 0.0 and tex[0, 0, -1, -1].item() == 1.0
    rgba = torch.rand(1, 4, 6, 7, dtype=torch.float64)
    rgba[:, 3] = 0.25
    io.save_image(tmp_path / "rgba.png", rgba)
    back = io.load_texture(tmp_path / "rgba.png", dtype=torch.float64)
    assert back.shape == (1, 4, 6, 7)
    assert (back[0, 3] - 64 / 255).abs().max().item() == 0.0  # round(0.25 * 255) = 64


def test_save_clamps(tmp_path):
    x = torch.tensor([[-1.0, 0.5, 2.0]])
    io.save_image(tmp_path / "c.png", x)
    y = io.load_texture(tmp_path / "c.png")
    assert y.flatten().tolist() == pytest.approx([0.0, 128 / 255, 1.0], abs=1e-7)


def test_jpeg_round_trip(tmp_path):
    # smooth image: JPEG (quality 95) keeps it within a few codes
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 32), torch.linspace(0, 1, 48), indexing="ij")
    x = torch.stack([xx, yy, 0.5 * (xx + yy)])
    io.save_image(tmp_path / "a.jpg", x)
    y = io.load_texture(tmp_path / "a.jpg")
    assert y.shape == (1, 3, 32, 48)
    assert (y[0] - x).abs().mean().item() < 4 / 255


def _png16_filtered(path, a):
    """A 16-bit PNG written with all five row filters (row r uses filter r % 5)."""
    h, w, c = a.shape
    bpp = 2 * c
    rows = np.ascontiguousarray(a.astype(">u2")).view(np.uint8).reshape(h, w * bpp).astype(np.int64)
    out = []
    prev = np.zeros(w * bpp, np.int64)
    for r in range(h):
        cur, ft = rows[r], r % 5
        left = np.concatenate([np.zeros(bpp, np.int64), cur[:-bpp]])
        upleft = np.concatenate([np.zeros(bpp, np.int64), prev[:-bpp]])
        if ft == 0:
            pred = 0
        elif ft == 1:
            pred = left
        elif ft == 2:
            pred = prev
        elif ft == 3:
            pred = (left + prev) // 2
        else:
            p = left + prev - upleft
            pa, pb, pc = abs(p - left), abs(p - prev), abs(p - upleft)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, prev, upleft))
        out.append(bytes([ft]) + ((cur - pred) & 255).astype(np.uint8).tobytes())
        prev = cur

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    ctype = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, ctype, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"".join(out))) + chunk(b"IEND", b""))


def test_png16_decoder_all_filters(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.integers(0, 65536, size=(10, 7, 3)).astype(np.uint16)
    _png16_filtered(tmp_path / "f.png", a)
    y = io.load_texture(tmp_path / "f.png", dtype=torch.float64)
    assert np.array_equal(np.round(y[0].permute(1, 2, 0).numpy() * 65535).astype(np.uint16), a)


def test_png16_gray_written_by_pillow(tmp_path):
    import imageio.v3 as iio

    a = (np.arange(40 * 30).reshape(40, 30) * 53 % 65536).astype(np.uint16)
    iio.imwrite(tmp_path / "g16.png", a)  # Pillow chooses its own (adaptive) filters
    y = io.load_texture(tmp_path / "g16.png", dtype=torch.float64)
    assert y.shape == (1, 1, 40, 30)
    assert np.array_equal(np.round(y[0, 0].numpy() * 65535).astype(np.uint16), a)


def test_spot_texture():
    tex = io.load_texture(SPOT_PNG)
    assert tex.shape == (1, 3, 1024, 1024) and tex.dtype == torch.float32
    assert 0.0 <= tex.min().item() and tex.max().item() <= 1.0


def test_data_path():
    assert io.data_path("spot/spot_texture.png") == SPOT_PNG
    with pytest.raises(FileNotFoundError, match="nope.png"):
        io.data_path("nope.png")


def test_image_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.png"):
        io.load_texture(tmp_path / "missing.png")
    (tmp_path / "a.tga").write_bytes(b"\0" * 10)
    with pytest.raises(ValueError, match=r"unsupported image format '\.tga'.*expected one of \.png"):
        io.load_texture(tmp_path / "a.tga")
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="broken.png"):
        io.load_texture(tmp_path / "broken.png")
    with pytest.raises(ValueError, match=r"image must be .*got \(2, 5, 3, 3\)"):
        io.save_image(tmp_path / "x.png", torch.rand(2, 5, 3, 3))
    with pytest.raises(ValueError, match="bits=16 needs a .png"):
        io.save_image(tmp_path / "x.jpg", torch.rand(3, 4, 4), bits=16)
    with pytest.raises(ValueError, match="NaN"):
        io.save_image(tmp_path / "x.png", torch.full((3, 2, 2), float("nan")))
    with pytest.raises(TypeError, match="floating"):
        io.save_image(tmp_path / "x.png", torch.zeros(3, 2, 2, dtype=torch.uint8))


def test_transparency_and_cmyk_images(tmp_path):
    from PIL import Image

    # A palette PNG with a tRNS chunk (pngquant / TinyPNG output): alpha kept.
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[..., 0] = 200
    rgba[..., 3] = [[0, 128], [255, 64]]
    Image.fromarray(rgba, "RGBA").quantize(4, method=Image.Quantize.FASTOCTREE).save(tmp_path / "p.png")
    t = io.load_texture(tmp_path / "p.png")
    assert t.shape == (1, 4, 2, 2)
    torch.testing.assert_close(t[0, 3] * 255, torch.tensor([[0.0, 128.0], [255.0, 64.0]]))
    # Grey with a transparent grey value: grey + alpha.
    Image.fromarray(np.array([[0, 100], [200, 255]], np.uint8), "L").save(tmp_path / "l.png", transparency=100)
    t = io.load_texture(tmp_path / "l.png")
    assert t.shape == (1, 2, 2, 2)
    torch.testing.assert_close(t[0, 1], torch.tensor([[1.0, 0.0], [1.0, 1.0]]))
    # A palette PNG without tRNS stays RGB.
    Image.fromarray(np.full((3, 3, 3), 9, np.uint8)).convert("P").save(tmp_path / "n.png")
    assert io.load_texture(tmp_path / "n.png").shape == (1, 3, 3, 3)
    # A CMYK JPEG is RGB, not "RGBA".
    Image.fromarray(np.full((4, 4, 3), (255, 0, 0), np.uint8)).convert("CMYK").save(tmp_path / "c.jpg", quality=100)
    t = io.load_texture(tmp_path / "c.jpg")
    assert t.shape == (1, 3, 4, 4)
    torch.testing.assert_close(t[0, :, 0, 0], torch.tensor([1.0, 0.0, 0.0]), atol=2 / 255, rtol=0)


def test_truncated_png16_names_the_file(tmp_path):
    io.save_image(tmp_path / "x16.png", torch.rand(3, 8, 8), bits=16)
    data = (tmp_path / "x16.png").read_bytes()
    (tmp_path / "cut16.png").write_bytes(data[:len(data) // 2])
    with pytest.raises(ValueError, match=r"cut16.png'?: corrupt or truncated PNG data"):
        io.load_texture(tmp_path / "cut16.png")


# ----------------------------------------------------------------- meshes


def test_obj_with_byte_order_mark(tmp_path):
    text = "\ufeffv 0 0 0\nv 1 0 0\nv 0 1 0\nv 5 5 5\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"
    (tmp_path / "bom.obj").write_bytes(text.encode("utf-8"))
    m = io.load_mesh(tmp_path / "bom.obj", dtype=torch.float64)
    # The first 'v' line is read (the mark used to hide it: the face got vertices 2-4).
    torch.testing.assert_close(m.positions[m.faces[0]],
                               torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64))


def test_spot_counts(spot):
    assert spot.positions.shape == (SPOT_V, 3)
    assert spot.faces.shape == (SPOT_F, 3) and spot.faces.dtype == torch.int64
    assert spot.uv.shape == (SPOT_VT, 2)
    assert spot.uv_faces.shape == (SPOT_F, 3) and spot.uv_faces.dtype == torch.int64
    assert spot.normals is None and spot.normal_faces is None
    assert spot.positions.dtype == torch.float64


def test_spot_indices_and_uv_range(spot):
    assert spot.faces.min().item() == 0 and spot.faces.max().item() == SPOT_V - 1
    assert spot.uv_faces.min().item() == 0 and spot.uv_faces.max().item() == SPOT_VT - 1
    # every position and every uv is used by some corner
    assert torch.unique(spot.faces).numel() == SPOT_V
    assert torch.unique(spot.uv_faces).numel() == SPOT_VT
    # The file's uv are kept exactly, and 4 of its 3225 vt lie slightly outside
    # the unit square (u down to -0.0522421, v_obj up to 1.00065): the rest is inside.
    outside = ((spot.uv < 0) | (spot.uv > 1)).any(dim=1)
    assert int(outside.sum()) == 4
    assert spot.uv[:, 0].min().item() == -0.0522421
    assert spot.uv[:, 1].min().item() == pytest.approx(1.0 - 1.00065, abs=1e-15)
    assert spot.uv.max().item() <= 1.0
    assert spot.uv[~outside].min().item() >= 0.0


def test_spot_exact_against_file_lines(spot):
    lines = SPOT_OBJ.read_text().splitlines()
    v0 = [float(x) for x in next(l for l in lines if l.startswith("v ")).split()[1:]]
    vt0 = [float(x) for x in next(l for l in lines if l.startswith("vt ")).split()[1:]]
    f0 = next(l for l in lines if l.startswith("f ")).split()[1:]
    assert spot.positions[0].tolist() == v0
    # v flipped: v = 1 - v_obj (DESIGN.md), u unchanged
    assert spot.uv[0, 0].item() == vt0[0]
    assert spot.uv[0, 1].item() == pytest.approx(1.0 - vt0[1], abs=1e-15)
    assert spot.faces[0].tolist() == [int(c.split("/")[0]) - 1 for c in f0]
    assert spot.uv_faces[0].tolist() == [int(c.split("/")[1]) - 1 for c in f0]


def test_spot_matches_trimesh_per_corner(spot):
    # trimesh splits the seams (3225 vertices); per corner both must agree.
    import trimesh

    t = trimesh.load(SPOT_OBJ, process=False)
    assert len(t.vertices) == SPOT_VT
    ref_pos = torch.as_tensor(np.asarray(t.vertices)[t.faces])
    ref_uv = torch.as_tensor(np.asarray(t.visual.uv)[t.faces])
    assert (spot.positions[spot.faces] - ref_pos).abs().max().item() < 1e-6  # trimesh parses to float32-ish
    assert (spot.corner_uv()[..., 0] - ref_uv[..., 0]).abs().max().item() < 1e-6
    assert (spot.corner_uv()[..., 1] - (1 - ref_uv[..., 1])).abs().max().item() < 1e-6
    pos, uv, faces = spot.unified()
    assert pos.shape == (SPOT_VT, 3) and uv.shape == (SPOT_VT, 2)
    assert torch.equal(pos[faces], spot.positions[spot.faces])
    assert torch.equal(uv[faces], spot.corner_uv())


def test_glb_and_ply_via_trimesh(tmp_path, spot):
    import trimesh

    t = trimesh.load(SPOT_OBJ, process=False)
    t.export(tmp_path / "spot.glb")
    t.export(tmp_path / "spot.ply")
    for name in ("spot.glb", "spot.ply"):
        m = io.load_mesh(tmp_path / name, dtype=torch.float64)
        assert m.faces.shape == (SPOT_F, 3) and m.positions.shape == (SPOT_VT, 3)
        assert torch.equal(m.uv_faces, m.faces)
        # glTF stores uv as float32 and v down; trimesh flips it to v up on load
        assert (m.corner_uv() - spot.corner_uv()).abs().max().item() < 1e-6, name
        assert (m.positions[m.faces] - spot.positions[spot.faces]).abs().max().item() < 1e-6, name


def test_obj_quads_normals_negative_indices(tmp_path):
    (tmp_path / "quad.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n"
        "f -4/1/1 -3/2/1 -2/3/1 -1/4/1\n"
    )
    m = io.load_mesh(tmp_path / "quad.obj")
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert m.uv_faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert m.uv[:, 1].tolist() == [1.0, 1.0, 0.0, 0.0]
    assert m.normals.shape == (1, 3) and m.normal_faces.tolist() == [[0, 0, 0], [0, 0, 0]]
    moved = m.to("cpu", torch.float64)
    assert moved.positions.dtype == torch.float64 and moved.faces.dtype == torch.int64


def test_mesh_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.obj"):
        io.load_mesh(tmp_path / "nothing.obj")
    (tmp_path / "m.stl").write_text("solid x\nendsolid x\n")
    with pytest.raises(ValueError, match=r"unsupported mesh format '\.stl'.*expected one of \.obj"):
        io.load_mesh(tmp_path / "m.stl")
    (tmp_path / "nouv.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="nouv.obj.*no texture coordinates"):
        io.load_mesh(tmp_path / "nouv.obj")
    (tmp_path / "partial.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2 3/1\n")
    with pytest.raises(ValueError, match="corner without a texture coordinate"):
        io.load_mesh(tmp_path / "partial.obj")
    (tmp_path / "range.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 4/1\n")
    with pytest.raises(ValueError, match="range.obj.*position index out of range"):
        io.load_mesh(tmp_path / "range.obj")
    (tmp_path / "bad.obj").write_text("v 0 zero 0\n")
    with pytest.raises(ValueError, match="bad.obj.*line 1"):
        io.load_mesh(tmp_path / "bad.obj")
    for tag in ("v", "vn"):
        (tmp_path / "short.obj").write_text(f"v 0 0 0\nv 1 0 0\n{tag} 0 1\nvt 0 0\nf 1/1 2/1 1/1\n")
        with pytest.raises(ValueError, match=f"short.obj.*line 3.*'{tag}' needs 3 coordinates"):
            io.load_mesh(tmp_path / "short.obj")
    import trimesh

    trimesh.creation.box().export(tmp_path / "box.ply")  # no uv
    with pytest.raises(ValueError, match="box.ply.*no texture coordinates"):
        io.load_mesh(tmp_path / "box.ply")

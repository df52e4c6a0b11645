"""Images (imageio) and meshes (OBJ parser / trimesh) in difftex's conventions.

Conventions (DESIGN.md section 2): textures are ``[1, C, H, W]`` floats in
``[0, 1]``; uv ``(0, 0)`` is the top-left corner of the texture with ``v``
running down the rows, so mesh loaders convert the files' v-up coordinate
with ``v = 1 - v_file``.

Why OBJ has its own parser: an OBJ face corner indexes positions (``v``),
texture coordinates (``vt``) and normals (``vn``) independently.  trimesh
cannot keep that: with ``process=False, maintain_order=True`` it keeps the
2930 spot positions but only one uv per position (the seam corners get a
wrong uv), and without ``maintain_order`` it splits seam vertices (spot
becomes 3225 vertices) and reorders them.  The small parser below keeps the
file's positions, uv list and per-corner indices exactly.  The other formats
(GLB / glTF / PLY) store one uv per vertex in the file itself, so trimesh's
vertex list is already the exact content of the file and ``uv_faces`` equals
``faces`` there.
"""

from __future__ import annotations

import struct
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

__all__ = [
    "DATA_DIR",
    "Mesh",
    "data_path",
    "load_mesh",
    "load_texture",
    "save_image",
]

PathLike = Union[str, Path]

#: The repository's ``data/`` folder.  It exists for a source checkout and an
#: editable install (the package is imported from the checkout); a wheel does
#: not ship it, and :func:`data_path` then says so.
DATA_DIR = Path(__file__).resolve().parent.parent / "data"

MESH_EXTENSIONS = (".obj", ".glb", ".gltf", ".ply")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def data_path(name: str) -> Path:
    """Path of a bundled asset, e.g. ``data_path("spot/spot_texture.png")``.

    Args:
        name: path relative to the repository's ``data/`` folder.

    Returns:
        An existing ``Path``.

    Raises FileNotFoundError naming the path when the asset (or the whole
    data folder, as in a non-editable install) is missing.
    """
    path = DATA_DIR / name
    if not path.exists():
        raise FileNotFoundError(
            f"bundled asset {name!r} not found at {path}; the data/ folder is only "
            "available from a source checkout or an editable install"
        )
    return path


# --------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh with face-varying uv (and optionally normals).

    Fields:
        positions: [V, 3] float.
        faces: [F, 3] int64 indices into ``positions``.
        uv: [T, 2] float, DESIGN.md convention (v down, already flipped).
        uv_faces: [F, 3] int64 indices into ``uv``; corner ``k`` of face
            ``f`` has texture coordinate ``uv[uv_faces[f, k]]``.
        normals: [N, 3] float or None when the file has none.
        normal_faces: [F, 3] int64 indices into ``normals`` or None.
    """

    positions: torch.Tensor
    faces: torch.Tensor
    uv: torch.Tensor
    uv_faces: torch.Tensor
    normals: Optional[torch.Tensor] = None
    normal_faces: Optional[torch.Tensor] = None

    def to(self, device=None, dtype: Optional[torch.dtype] = None) -> "Mesh":
        """Copy to ``device``; ``dtype`` applies to the float fields only."""

        def f(t):
            return None if t is None else t.to(device=device, dtype=dtype)

        def i(t):
            return None if t is None else t.to(device=device)

        return Mesh(f(self.positions), i(self.faces), f(self.uv), i(self.uv_faces),
                    f(self.normals), i(self.normal_faces))

    def corner_uv(self) -> torch.Tensor:
        """[F, 3, 2] uv of every face corner (``uv[uv_faces]``)."""
        return self.uv[self.uv_faces]

    def unified(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Split vertices at uv seams so one index list serves both attributes.

        Returns:
            positions [N, 3], uv [N, 2], faces [F, 3] int64 with one vertex per
            distinct (position index, uv index) pair, in order of first use.
            For spot that is 3225 vertices, the same count trimesh produces.
        """
        pairs = torch.stack([self.faces.reshape(-1), self.uv_faces.reshape(-1)], dim=1)
        uniq, inverse = torch.unique(pairs, dim=0, return_inverse=True)
        # torch.unique sorts; renumber by first use so the order is stable and readable.
        n = uniq.shape[0]
        first = torch.full((n,), inverse.numel(), dtype=torch.int64, device=inverse.device)
        first.scatter_reduce_(0, inverse, torch.arange(inverse.numel(), device=inverse.device),
                              reduce="amin")
        order = torch.argsort(first)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(n, device=order.device)
        uniq = uniq[order]
        faces = rank[inverse].reshape(-1, 3)
        return self.positions[uniq[:, 0]], self.uv[uniq[:, 1]], faces


def _check_file(path: PathLike, what: str, extensions: tuple[str, ...]) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {str(path)!r}")
    if path.suffix.lower() not in extensions:
        raise ValueError(
            f"unsupported {what} format {path.suffix!r} for {str(path)!r}; "
            f"expected one of {', '.join(extensions)}"
        )
    return path


def _parse_obj(path: Path):
    """Positions, uv, normals and per-corner index triples of an OBJ file.

    Polygons are fan-triangulated (as trimesh does); negative (relative)
    indices are resolved; ``l``/``p``/groups/materials are ignored.
    """
    v, vt, vn = [], [], []
    fv, ft, fn = [], [], []
    # utf-8-sig: a byte-order mark would otherwise hide the first line's tag.
    with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts:
                continue
            tag = parts[0]
            try:
                if tag in ("v", "vn") and len(parts) < 4:
                    raise ValueError(f"'{tag}' needs 3 coordinates")
                if tag == "v":
                    v.append([float(x) for x in parts[1:4]])
                elif tag == "vt":
                    # vt u [v [w]]: a missing v means 0 per the OBJ spec.
                    u = float(parts[1])
                    vv = float(parts[2]) if len(parts) > 2 else 0.0
                    vt.append([u, vv])
                elif tag == "vn":
                    vn.append([float(x) for x in parts[1:4]])
                elif tag == "f":
                    corners = []
                    for c in parts[1:]:
                        idx = c.split("/")
                        iv = int(idx[0])
                        it = int(idx[1]) if len(idx) > 1 and idx[1] else 0
                        inn = int(idx[2]) if len(idx) > 2 and idx[2] else 0
                        # OBJ is 1-based; negative indices count back from the
                        # elements read so far.  0 marks "absent".
                        iv = iv - 1 if iv > 0 else len(v) + iv
                        it = (it - 1 if it > 0 else len(vt) + it) if it else -1
                        inn = (inn - 1 if inn > 0 else len(vn) + inn) if inn else -1
                        corners.append((iv, it, inn))
                    if len(corners) < 3:
                        raise ValueError("a face needs at least 3 corners")
                    for k in range(1, len(corners) - 1):
                        tri = (corners[0], corners[k], corners[k + 1])
                        fv.append([c[0] for c in tri])
                        ft.append([c[1] for c in tri])
                        fn.append([c[2] for c in tri])
            except (ValueError, IndexError) as exc:
                raise ValueError(f"{str(path)!r} line {lineno}: cannot parse {line.strip()!r} ({exc})") from None
    return (np.asarray(v, dtype=np.float64).reshape(-1, 3),
            np.asarray(vt, dtype=np.float64).reshape(-1, 2),
            np.asarray(vn, dtype=np.float64).reshape(-1, 3),
            np.asarray(fv, dtype=np.int64).reshape(-1, 3),
            np.asarray(ft, dtype=np.int64).reshape(-1, 3),
            np.asarray(fn, dtype=np.int64).reshape(-1, 3))


def _check_indices(path: Path, name: str, idx: np.ndarray, count: int) -> None:
    if idx.size and (idx.min() < 0 or idx.max() >= count):
        raise ValueError(
            f"{str(path)!r}: {name} index out of range [0, {count}) "
            f"(found {idx.min()}..{idx.max()})"
        )


def _load_obj(path: Path):
    v, vt, vn, fv, ft, fn = _parse_obj(path)
    if fv.shape[0] == 0:
        raise ValueError(f"{str(path)!r} has no faces; expected a triangle mesh with uv")
    if vt.shape[0] == 0 or (ft < 0).all():
        raise ValueError(
            f"{str(path)!r} has no texture coordinates; expected 'vt' lines and faces "
            "written as f v/vt or f v/vt/vn"
        )
    if (ft < 0).any():
        bad = int(np.nonzero((ft < 0).any(axis=1))[0][0])
        raise ValueError(
            f"{str(path)!r}: triangle {bad} has a corner without a texture coordinate; "
            "expected every face corner to carry a vt index"
        )
    _check_indices(path, "position", fv, v.shape[0])
    _check_indices(path, "texture coordinate", ft, vt.shape[0])
    normals = normal_faces = None
    if vn.shape[0] and (fn >= 0).all():
        _check_indices(path, "normal", fn, vn.shape[0])
        normals, normal_faces = vn, fn
    uv = vt.copy()
    uv[:, 1] = 1.0 - uv[:, 1]
    return v, fv, uv, ft, normals, normal_faces


def _load_trimesh(path: Path):
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises a zoo of types for broken files
        raise ValueError(f"trimesh could not read {str(path)!r}: {exc}") from exc
    parts = []  # (positions, faces, uv or None, normals or None)
    if isinstance(loaded, trimesh.Scene):
        for node in loaded.graph.nodes_geometry:
            transform, name = loaded.graph[node]
            g = loaded.geometry[name]
            if not isinstance(g, trimesh.Trimesh):
                continue
            pos = trimesh.transform_points(np.asarray(g.vertices), transform)
            nrm = None
            if "vertex_normals" in g._cache:  # loaded from the file, not computed
                nrm = np.asarray(g.vertex_normals) @ np.linalg.inv(transform[:3, :3])
                nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
            parts.append((pos, np.asarray(g.faces), getattr(g.visual, "uv", None), nrm))
    elif isinstance(loaded, trimesh.Trimesh):
        nrm = np.asarray(loaded.vertex_normals) if "vertex_normals" in loaded._cache else None
        parts.append((np.asarray(loaded.vertices), np.asarray(loaded.faces),
                      getattr(loaded.visual, "uv", None), nrm))
    if not parts or sum(p[1].shape[0] for p in parts) == 0:
        raise ValueError(f"{str(path)!r} has no triangles; expected a triangle mesh with uv")
    if any(p[2] is None or len(p[2]) != len(p[0]) for p in parts):
        raise ValueError(f"{str(path)!r} has no texture coordinates; expected a mesh with uv")
    offset, faces = 0, []
    for p in parts:
        faces.append(np.asarray(p[1], dtype=np.int64) + offset)
        offset += p[0].shape[0]
    positions = np.concatenate([p[0] for p in parts])
    faces = np.concatenate(faces)
    uv = np.concatenate([np.asarray(p[2], dtype=np.float64) for p in parts])
    # trimesh stores uv v-up for every format (it flips glTF's v on load).
    uv[:, 1] = 1.0 - uv[:, 1]
    normals = normal_faces = None
    if all(p[3] is not None for p in parts):
        normals = np.concatenate([p[3] for p in parts])
        normal_faces = faces
    return positions, faces, uv, faces, normals, normal_faces


def load_mesh(path: PathLike, *, device=None, dtype: torch.dtype = torch.float32) -> Mesh:
    """Load a textured triangle mesh with exact face-varying uv.

    Args:
        path: ``.obj`` (own parser, keeps the file's v / vt / vn lists and
            per-corner indices; polygons are fan-triangulated) or ``.glb`` /
            ``.gltf`` / ``.ply`` through trimesh (one uv per vertex, scene
            transforms applied, several meshes concatenated).
        device, dtype: of the float fields; index fields are int64.

    Returns:
        A :class:`Mesh` with uv in DESIGN.md's convention, ``v = 1 - v_file``.

    Nothing here is differentiable (it is file input).  Raises
    FileNotFoundError for a missing file, ValueError naming the path for an
    unsupported extension, a file without faces or without uv, an
    unparsable line or an out-of-range index.
    """
    path = _check_file(path, "mesh", MESH_EXTENSIONS)
    if path.suffix.lower() == ".obj":
        arrays = _load_obj(path)
    else:
        arrays = _load_trimesh(path)
    pos, faces, uv, uv_faces, normals, normal_faces = arrays

    def f(a):
        return None if a is None else torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

    def i(a):
        return None if a is None else torch.as_tensor(np.ascontiguousarray(a), dtype=torch.int64, device=device)

    return Mesh(f(pos), i(faces), f(uv), i(uv_faces), f(normals), i(normal_faces))


# --------------------------------------------------------------------------
# images
# --------------------------------------------------------------------------

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type -> channels, for the non-palette types.
_PNG_CHANNELS = {0: 1, 4: 2, 2: 3, 6: 4}


def _png_header(path: Path) -> Optional[tuple[int, int, int, int, int]]:
    """(width, height, bit depth, colour type, interlace) or None if not a PNG."""
    with open(path, "rb") as fh:
        head = fh.read(33)
    if len(head) < 33 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    w, h, depth, ctype, _, _, interlace = struct.unpack(">IIBBBBB", head[16:29])
    return w, h, depth, ctype, interlace


def _read_png16(path: Path, header) -> np.ndarray:
    """Decode a 16-bit non-palette PNG to uint16 [H, W, C].

    Pillow (imageio's PNG backend) silently reduces 16-bit RGB / RGBA /
    gray-alpha PNGs to 8 bits, so these are decoded here: zlib + the five
    PNG row filters.
    """
    w, h, depth, ctype, interlace = header
    if interlace:
        raise ValueError(f"{str(path)!r}: interlaced 16-bit PNG is not supported; "
                         "expected a non-interlaced file")
    c = _PNG_CHANNELS[ctype]
    data = path.read_bytes()
    pos, idat = 8, []
    while pos + 8 <= len(data):
        length, tag = struct.unpack(">I4s", data[pos:pos + 8])
        if tag == b"IDAT":
            idat.append(data[pos + 8:pos + 8 + length])
        elif tag == b"IEND":
            break
        pos += 12 + length
    bpp = 2 * c
    stride = w * bpp
    try:
        raw = np.frombuffer(zlib.decompress(b"".join(idat)), dtype=np.uint8)
    except zlib.error as exc:
        raise ValueError(f"{str(path)!r}: corrupt or truncated PNG data ({exc})") from None
    if raw.size < h * (stride + 1):
        raise ValueError(f"{str(path)!r}: truncated PNG data")
    rows = raw[: h * (stride + 1)].reshape(h, stride + 1)
    out = np.zeros((h, stride), dtype=np.uint8)
    prev = np.zeros(stride, dtype=np.int32)
    for r in range(h):
        ftype, line = rows[r, 0], rows[r, 1:].astype(np.int32)
        if ftype == 0:
            cur = line
        elif ftype == 1:  # Sub: running sum per byte position modulo 256
            cur = np.cumsum(line.reshape(w, bpp), axis=0).reshape(-1) & 255
        elif ftype == 2:  # Up
            cur = (line + prev) & 255
        elif ftype in (3, 4):  # Average / Paeth depend on the left pixel: go pixel by pixel
            cur = line.copy()
            left = np.zeros(bpp, dtype=np.int32)
            upleft = np.zeros(bpp, dtype=np.int32)
            for x in range(w):
                sl = slice(x * bpp, (x + 1) * bpp)
                up = prev[sl]
                if ftype == 3:
                    pred = (left + up) >> 1
                else:
                    p = left + up - upleft
                    pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - upleft)
                    pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, upleft))
                cur[sl] = (line[sl] + pred) & 255
                left, upleft = cur[sl], up
        else:
            raise ValueError(f"{str(path)!r}: bad PNG filter type {ftype} in row {r}")
        out[r] = cur
        prev = cur.astype(np.int32)
    return out.view(">u2").astype(np.uint16).reshape(h, w, c)


def _write_png16(path: Path, array: np.ndarray) -> None:
    """Write uint16 [H, W, C] (C = 1..4) as a 16-bit PNG (Pillow cannot for C > 1)."""
    h, w, c = array.shape
    ctype = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    rows = np.ascontiguousarray(array.astype(">u2")).view(np.uint8).reshape(h, w * c * 2)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()

    def chunk(tag: bytes, payload: bytes) -> bytes:
        crc = zlib.crc32(tag + payload) & 0xFFFFFFFF
        return struct.pack(">I", len(payload)) + tag + payload + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", w, h, 16, ctype, 0, 0, 0)
    path.write_bytes(_PNG_SIGNATURE + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 6))
                     + chunk(b"IEND", b""))


# Pillow modes that imageio returns as they are: bilevel, grey(+alpha), RGB(A), 16/32-bit grey, float.
_PLAIN_MODES = ("1", "L", "LA", "RGB", "RGBA", "I;16", "I;16B", "I;16L", "I", "F")


def _read_mode(meta: dict) -> str | None:
    """The Pillow mode to convert to on reading (None: as stored).

    Palette, grey and RGB images with a tRNS transparency keep it as an
    alpha channel (imageio drops it otherwise); CMYK, YCbCr, LAB and HSV
    JPEGs / PNGs become RGB (as stored they would pass for RGBA or RGB).
    """
    mode, transparent = meta.get("mode"), "transparency" in meta
    if mode in ("P", "PA"):
        return "RGBA" if transparent or mode == "PA" else "RGB"
    if transparent and mode in ("L", "RGB"):
        return "LA" if mode == "L" else "RGBA"
    if mode is not None and mode not in _PLAIN_MODES:
        return "RGB"
    return None


def load_texture(path: PathLike, *, device=None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Load a PNG / JPEG image as a texture in [0, 1].

    Args:
        path: ``.png`` (8- or 16-bit, gray / gray-alpha / RGB / RGBA /
            palette) or ``.jpg`` / ``.jpeg``.
        device, dtype: of the result (floating dtype).

    Returns:
        [1, C, H, W] with C = 1 (gray), 2 (gray + alpha), 3 (RGB) or 4
        (RGBA); 8-bit values are divided by 255, 16-bit by 65535.  Row 0 is
        the top of the image (uv v = 0).

    Not differentiable (file input).  Raises FileNotFoundError for a missing
    file, ValueError naming the path for an unsupported extension or an
    unreadable file, TypeError for a non-floating dtype.
    """
    if not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating dtype, got {dtype}")
    path = _check_file(path, "image", IMAGE_EXTENSIONS)
    header = _png_header(path)
    if header is not None and header[2] == 16 and header[3] in _PNG_CHANNELS:
        array = _read_png16(path, header)
    else:
        import imageio.v3 as iio

        try:
            mode = _read_mode(iio.immeta(path))
            with warnings.catch_warnings():
                # Pillow suggests RGBA for palette + transparency, which is what mode asks for.
                warnings.filterwarnings("ignore", message="Palette images with Transparency")
                array = np.asarray(iio.imread(path) if mode is None else iio.imread(path, mode=mode))
        except Exception as exc:
            raise ValueError(f"could not read image {str(path)!r}: {exc}") from exc
    if array.dtype == np.uint8:
        scale = 255.0
    elif array.dtype == np.uint16:
        scale = 65535.0
    elif array.dtype == np.bool_:
        scale = 1.0
    else:
        raise ValueError(f"{str(path)!r}: unsupported pixel type {array.dtype}; expected 8- or 16-bit")
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 2, 3, 4):
        raise ValueError(f"{str(path)!r}: unsupported image shape {array.shape}; expected [H, W(, C<=4)]")
    tensor = torch.from_numpy(array.astype(np.float64) / scale)
    return tensor.permute(2, 0, 1).unsqueeze(0).to(device=device, dtype=dtype).contiguous()


def save_image(path: PathLike, image: torch.Tensor, *, bits: int = 8) -> None:
    """Save an image tensor in [0, 1] as PNG / JPEG.

    Args:
        path: ``.png`` or ``.jpg`` / ``.jpeg``; the folder must exist.
        image: [H, W], [C, H, W] or [1, C, H, W] float, C in 1..4 (JPEG:
            1 or 3).  Values are clamped to [0, 1] and rounded to the nearest
            code, so a round trip is exact to half a code.
        bits: 8, or 16 (PNG only).

    Not differentiable (detaches).  Raises ValueError naming the argument for
    a bad shape, non-finite values, an unsupported extension or bit depth,
    TypeError for a non-floating tensor.
    """
    path = Path(path)
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"image must be a torch.Tensor, got {type(image).__name__}")
    if not image.dtype.is_floating_point:
        raise TypeError(f"image must be a floating tensor in [0, 1], got dtype {image.dtype}")
    ext = path.suffix.lower()
    if ext not in IMAGE_EXTENSIONS:
        raise ValueError(f"unsupported image format {path.suffix!r} for {str(path)!r}; "
                         f"expected one of {', '.join(IMAGE_EXTENSIONS)}")
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    if bits == 16 and ext != ".png":
        raise ValueError(f"bits=16 needs a .png path, got {str(path)!r}")
    x = image.detach()
    if x.dim() == 4:
        if x.shape[0] != 1:
            raise ValueError(f"image must be [H, W], [C, H, W] or [1, C, H, W], got {tuple(image.shape)}")
        x = x[0]
    if x.dim() == 2:
        x = x[None]
    if x.dim() != 3 or not 1 <= x.shape[0] <= 4 or x.shape[1] == 0 or x.shape[2] == 0:
        raise ValueError(f"image must be [H, W], [C, H, W] or [1, C, H, W] with C in 1..4, "
                         f"got {tuple(image.shape)}")
    if ext != ".png" and x.shape[0] not in (1, 3):
        raise ValueError(f"JPEG image needs 1 or 3 channels, got image of shape {tuple(image.shape)}")
    if not torch.isfinite(x).all():
        raise ValueError("image has NaN or infinite values; expected finite values in [0, 1]")
    array = x.to("cpu", torch.float64).clamp(0.0, 1.0).permute(1, 2, 0).numpy()
    if bits == 16:
        _write_png16(path, np.round(array * 65535.0).astype(np.uint16))
        return
    import imageio.v3 as iio

    array8 = np.round(array * 255.0).astype(np.uint8)
    if array8.shape[2] == 1:
        array8 = array8[:, :, 0]
    if ext == ".png":
        iio.imwrite(path, array8)
    else:
        iio.imwrite(path, array8, quality=95)

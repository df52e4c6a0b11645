"""Images (imageio; a hand-written reader for 16-bit PNG) as textures in difftex's conventions.

Conventions (DESIGN.md section 2): textures are ``[1, C, H, W]`` floats in
``[0, 1]``; row 0 is the top of the image (uv ``v = 0``).
"""
from __future__ import annotations

import struct
import warnings
import zlib
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from .files import PathLike, check_file

__all__ = ["IMAGE_EXTENSIONS", "load_texture", "save_image"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


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
    path = check_file(path, "image", IMAGE_EXTENSIONS)
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

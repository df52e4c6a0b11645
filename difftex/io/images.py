"""Images as textures in difftex's conventions: PNG / JPEG / Radiance HDR, optional sRGB decoding.

Conventions (DESIGN.md section 2): textures are ``[1, C, H, W]`` floats;
row 0 is the top of the image (uv ``v = 0``).  8- and 16-bit files give
values in ``[0, 1]`` (code / 255 or code / 65535), Radiance ``.hdr`` files
give linear float values, not clamped (environment maps exceed 1).

Colour: by default values are returned *as stored* (``srgb=False``); most
8-bit textures are sRGB-encoded, and ``srgb=True`` decodes them to linear
light (the colour channels; alpha is linear already) so that filtering and
mip building average light, as GPUs do with sRGB texture formats.
:func:`save_image` with ``srgb=True`` encodes linear values back.

Decoders: 8-bit PNG and JPEG go through imageio (Pillow), which also handles
palettes, tRNS transparency and CMYK JPEGs.  Pillow reduces 16-bit RGB(A)
PNGs to 8 bits and knows no HDR, so 16-bit PNG and ``.hdr`` go through
OpenCV's headless build, the optional extra ``pip install difftex[images]``;
without it those formats raise ImportError saying so, the others still work.
"""
from __future__ import annotations

import re
import struct
import warnings
import zlib
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from .files import PathLike, check_file, check_path

__all__ = ["IMAGE_EXTENSIONS", "load_texture", "save_image"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".hdr")

_EXTRA_HINT = "pip install difftex[images] (OpenCV's headless build, opencv-python-headless)"

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type -> channels, for the non-palette types.
_PNG_CHANNELS = {0: 1, 4: 2, 2: 3, 6: 4}

# Radiance RGBE: 8-bit mantissas sharing an exponent byte e - 128, so the
# largest channel must stay below 2^127 (e = 128 would wrap around to 0).
_RGBE_LIMIT = 2.0 ** 127


def _cv2(what: str):
    """OpenCV, or ImportError naming the extra that provides it."""
    try:
        import cv2
    except ImportError:
        raise ImportError(f"{what} needs OpenCV, an optional dependency: {_EXTRA_HINT}") from None
    return cv2


def _png_header(path: Path) -> Optional[tuple[int, int, int, int, int]]:
    """(width, height, bit depth, colour type, interlace) or None if not a PNG."""
    with open(path, "rb") as fh:
        head = fh.read(33)
    if len(head) < 33 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    w, h, depth, ctype, _, _, interlace = struct.unpack(">IIBBBBB", head[16:29])
    return w, h, depth, ctype, interlace


def _hdr_size(path: Path) -> tuple[int, int]:
    """(width, height) from a Radiance header: '#?' line, variables, blank line, '-Y H +X W'."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    if not head.startswith(b"#?"):
        raise ValueError(f"{str(path)!r} is not a Radiance HDR file; expected it to start with '#?RADIANCE'")
    end = head.find(b"\n\n")
    if end < 0:
        raise ValueError(f"{str(path)!r}: truncated Radiance header (no blank line before the resolution)")
    line = head[end + 2:].split(b"\n", 1)[0]
    m = re.fullmatch(rb"\s*-Y\s+(\d+)\s+\+X\s+(\d+)\s*", line)
    if m is None:
        # The other seven orientations (flipped / transposed) are legal but rare; OpenCV reads none of them.
        raise ValueError(f"{str(path)!r}: unsupported Radiance resolution line {line[:40]!r}; "
                         "expected '-Y <height> +X <width>' (rows top to bottom)")
    return int(m.group(2)), int(m.group(1))


def _check_size(path: Path, width: int, height: int) -> None:
    """Empty images and Pillow's decompression-bomb limit, from the header before decoding.

    Pillow warns above ``PIL.Image.MAX_IMAGE_PIXELS`` and refuses twice that
    (None disables both); the OpenCV formats follow the same setting so that
    one knob governs every format.
    """
    if width == 0 or height == 0:
        raise ValueError(f"{str(path)!r}: the header gives an empty {width}x{height} (width x height) image; "
                         "expected at least 1x1 pixels")
    from PIL import Image

    cap = Image.MAX_IMAGE_PIXELS
    if cap is None:
        return
    pixels = width * height
    if pixels > 2 * cap:
        raise ValueError(f"{str(path)!r}: image size {width}x{height} ({pixels} pixels) exceeds "
                         f"{2 * cap} pixels, twice PIL.Image.MAX_IMAGE_PIXELS (Pillow's decompression-bomb "
                         "limit); raise PIL.Image.MAX_IMAGE_PIXELS, or set it to None, to read it")
    if pixels > cap:
        warnings.warn(f"{str(path)!r}: image size {width}x{height} ({pixels} pixels) exceeds "
                      f"PIL.Image.MAX_IMAGE_PIXELS = {cap}, could be a decompression bomb",
                      Image.DecompressionBombWarning, stacklevel=3)


def _decode_cv2(path: Path, what: str) -> np.ndarray:
    """OpenCV decode (IMREAD_UNCHANGED) with RGB(A) channel order; ValueError naming the file on failure.

    imdecode on the file's bytes rather than imread(path): imread cannot open
    non-ASCII paths on Windows, and both return None rather than raising.
    """
    cv2 = _cv2(what)
    data = np.fromfile(path, dtype=np.uint8)
    try:
        array = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except cv2.error as exc:
        raise ValueError(f"{str(path)!r}: OpenCV could not decode the {what} ({exc})") from None
    if array is None:
        kind = "PNG" if path.suffix.lower() == ".png" else "Radiance HDR"
        raise ValueError(f"{str(path)!r}: corrupt or truncated {kind} data (OpenCV could not decode it)")
    if array.ndim == 3 and array.shape[2] in (3, 4):
        array = array[:, :, [2, 1, 0, 3][: array.shape[2]]]  # OpenCV stores BGR(A)
    return array


def _png_grey_key(data: np.ndarray) -> Optional[int]:
    """The transparent grey value of a grey PNG's tRNS chunk (None without one); chunks before IDAT."""
    raw, pos = data.tobytes(), 8
    while pos + 8 <= len(raw):
        length, tag = struct.unpack(">I4s", raw[pos:pos + 8])
        if tag == b"tRNS" and length >= 2:
            return struct.unpack(">H", raw[pos + 8:pos + 10])[0]
        if tag in (b"IDAT", b"IEND"):  # tRNS must precede IDAT
            return None
        pos += 12 + length
    return None


def _read_png16(path: Path, header) -> np.ndarray:
    """Decode a 16-bit non-palette PNG to uint16 [H, W, C] (C = the file's channels, + alpha for tRNS)."""
    w, h, _, ctype, _ = header
    _check_size(path, w, h)
    array = _decode_cv2(path, "16-bit PNG")
    if array.dtype != np.uint16:
        raise ValueError(f"{str(path)!r}: OpenCV decoded a {array.dtype} image from a 16-bit PNG; expected uint16")
    if array.ndim == 2:
        array = array[:, :, None]
    if ctype in (0, 4) and array.shape[2] in (3, 4):
        # OpenCV has no grey + alpha layout: it expands grey (with alpha or a tRNS key) to BGR(A), B = G = R.
        array = array[:, :, [0, 3]] if array.shape[2] == 4 else array[:, :, :1]
    if ctype == 0 and array.shape[2] == 1:
        # OpenCV turns an RGB tRNS key into alpha but drops a grey one; Pillow's 8-bit path keeps both.
        # tRNS precedes IDAT, so the first MiB holds it unless huge ancillary chunks come first.
        key = _png_grey_key(np.fromfile(path, dtype=np.uint8, count=1 << 20))
        if key is not None:
            alpha = np.where(array[:, :, 0] == key, 0, 65535).astype(np.uint16)
            array = np.concatenate([array, alpha[:, :, None]], axis=2)
    if array.shape[:2] != (h, w):
        raise ValueError(f"{str(path)!r}: decoded {array.shape[1]}x{array.shape[0]} pixels, "
                         f"the header says {w}x{h}")
    return array


def _read_hdr(path: Path) -> np.ndarray:
    """Decode a Radiance .hdr to float32 RGB [H, W, 3], linear, as stored."""
    w, h = _hdr_size(path)
    _check_size(path, w, h)
    array = _decode_cv2(path, "Radiance HDR image")
    if array.ndim != 3 or array.shape[2] != 3 or array.dtype != np.float32:
        raise ValueError(f"{str(path)!r}: OpenCV decoded {array.dtype} {array.shape} from a Radiance file; "
                         "expected float32 [H, W, 3]")
    return array


def _write_png16_grey_alpha(path: Path, array: np.ndarray) -> None:
    """Write uint16 [H, W, 2] as a grey + alpha 16-bit PNG.

    Neither OpenCV (its encoder takes 1, 3 or 4 channels) nor Pillow (no
    16-bit LA mode) writes this layout, so the few chunks are written here:
    filter type 0 on every row, zlib level 6.
    """
    h, w, _ = array.shape
    rows = np.ascontiguousarray(array.astype(">u2")).view(np.uint8).reshape(h, w * 4)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()

    def chunk(tag: bytes, payload: bytes) -> bytes:
        crc = zlib.crc32(tag + payload) & 0xFFFFFFFF
        return struct.pack(">I", len(payload)) + tag + payload + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", w, h, 16, 4, 0, 0, 0)
    path.write_bytes(_PNG_SIGNATURE + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 6))
                     + chunk(b"IEND", b""))


def _write_cv2(path: Path, array: np.ndarray, what: str) -> None:
    """Encode RGB(A) / grey [H, W, C] with OpenCV by the path's extension and write the bytes."""
    cv2 = _cv2(what)
    if array.ndim == 3 and array.shape[2] in (3, 4):
        array = array[:, :, [2, 1, 0, 3][: array.shape[2]]]
    ok, buf = cv2.imencode(path.suffix.lower(), np.ascontiguousarray(array))
    if not ok:  # imencode / imwrite report failure by a flag, not an exception
        raise ValueError(f"OpenCV could not encode the {what} for {str(path)!r}")
    path.write_bytes(buf.tobytes())


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


def _apply_to_colour(x: torch.Tensor, fn: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """``fn`` (a kornia sRGB transfer, which takes [*, 3, H, W]) on the colour channels of [*, C, H, W].

    C = 1 / 2 is grey (+ alpha), C = 3 / 4 is RGB (+ alpha); alpha is
    coverage, linear by definition, and passes through unchanged.
    """
    n = 1 if x.shape[-3] <= 2 else 3
    colour = x[..., :n, :, :]
    if n == 1:
        # The sRGB curve is per channel: grey goes through it like any one of R, G, B.
        out = fn(colour.expand(*colour.shape[:-3], 3, *colour.shape[-2:]))[..., :1, :, :]
    else:
        out = fn(colour)
    return torch.cat([out, x[..., n:, :, :]], dim=-3)


def _check_srgb(srgb) -> None:
    if not isinstance(srgb, (bool, np.bool_)):
        raise TypeError(f"srgb must be a bool (True: sRGB-encoded file, linear tensor), got {srgb!r}")


def load_texture(path: PathLike, *, srgb: bool = False, device=None,
                 dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Load a PNG / JPEG / Radiance HDR image as a texture.

    Args:
        path: ``.png`` (8- or 16-bit, grey / grey + alpha / RGB / RGBA /
            palette, tRNS transparency kept as alpha), ``.jpg`` / ``.jpeg``,
            or ``.hdr`` (Radiance RGBE).  16-bit PNG and HDR need OpenCV
            (``pip install difftex[images]``).
        srgb: False (default): values as stored in the file.  True: the
            file holds sRGB-encoded colour; grey / RGB channels are decoded
            with the sRGB transfer function (IEC 61966-2-1) to linear light,
            alpha is left as stored.  HDR files are linear already, so it
            changes nothing for them.
        device, dtype: of the result; dtype a floating ``torch.dtype``.

    Returns:
        [1, C, H, W] with C = 1 (grey), 2 (grey + alpha), 3 (RGB) or 4
        (RGBA); 8-bit values are divided by 255, 16-bit by 65535, so they
        lie in [0, 1]; HDR gives C = 3 linear values >= 0, not clamped
        (RGBE keeps 8 mantissa bits per pixel: about 2 to 3 significant
        digits relative to the pixel's largest channel).  Row 0 is the top
        of the image (uv v = 0).

    Not differentiable (file input).  Raises TypeError naming ``path`` when
    it is no str / PathLike, naming ``dtype`` for a non-floating or
    non-dtype value, naming ``srgb`` for a non-bool; FileNotFoundError for
    a missing file; ValueError naming the path for an unsupported
    extension, an unreadable or truncated file, an empty (0-pixel) image,
    an image over Pillow's pixel limit (twice ``PIL.Image.MAX_IMAGE_PIXELS``,
    checked from the header before decoding; above the limit itself a
    ``DecompressionBombWarning``), and HDR values that overflow ``dtype``;
    ImportError naming the extra for 16-bit PNG / HDR without OpenCV.
    """
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating torch.dtype such as torch.float32, got {dtype!r}")
    _check_srgb(srgb)
    path = check_file(path, "image", IMAGE_EXTENSIONS)
    if path.suffix.lower() == ".hdr":
        tensor = torch.from_numpy(_read_hdr(path).astype(np.float64)).permute(2, 0, 1).unsqueeze(0)
        out = tensor.to(device=device, dtype=dtype).contiguous()
        if not torch.isfinite(out).all():
            raise ValueError(f"{str(path)!r}: values up to {tensor.max().item():.4g} overflow dtype {dtype}; "
                             "expected a dtype that holds them, e.g. torch.float32")
        return out
    header = _png_header(path)
    if header is not None and header[2] == 16 and header[3] in _PNG_CHANNELS:
        array = _read_png16(path, header)
    else:
        if header is not None and (header[0] == 0 or header[1] == 0):
            _check_size(path, header[0], header[1])
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
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"{str(path)!r}: empty {array.shape[1]}x{array.shape[0]} image; expected at least 1x1")
    tensor = torch.from_numpy(array.astype(np.float64) / scale).permute(2, 0, 1).unsqueeze(0)
    if srgb:
        import kornia.color

        tensor = _apply_to_colour(tensor, kornia.color.rgb_to_linear_rgb)
    return tensor.to(device=device, dtype=dtype).contiguous()


def save_image(path: PathLike, image: torch.Tensor, *, bits: int = 8, srgb: bool = False) -> None:
    """Save an image tensor as PNG / JPEG (values in [0, 1]) or Radiance HDR (linear floats).

    Args:
        path: ``.png``, ``.jpg`` / ``.jpeg`` or ``.hdr``; the folder must
            exist.  16-bit PNG and HDR need OpenCV
            (``pip install difftex[images]``).
        image: [H, W], [C, H, W] or [1, C, H, W] float, C in 1..4 (JPEG and
            HDR: 1 or 3; HDR writes grey as three equal channels).  PNG /
            JPEG values are clamped to [0, 1] and rounded to the nearest
            code, so a round trip is exact to half a code.  HDR values are
            clamped below at 0 (RGBE has no sign) and must stay below 2^127;
            RGBE truncates each channel to a multiple of 2^(e - 8), where
            2^(e - 1) <= the pixel's largest channel < 2^e.
        bits: 8, or 16 (PNG only); ignored for HDR (always RGBE float).
        srgb: False (default): values are written as they are.  True: the
            tensor holds linear light; grey / RGB channels are encoded with
            the sRGB transfer function after clamping, alpha is written as
            it is; ``load_texture(..., srgb=True)`` inverts it.  HDR stores
            linear values, so it changes nothing there.

    Not differentiable (detaches).  Raises TypeError naming ``path`` when it
    is no str / PathLike, for a non-tensor or non-floating image, for a
    non-bool ``srgb``; ValueError naming the argument for a bad shape,
    non-finite values, an unsupported extension or bit depth, HDR values at
    or above 2^127; ImportError naming the extra for 16-bit PNG / HDR
    without OpenCV; FileNotFoundError when the folder does not exist.
    """
    path = check_path(path, "image")
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"image must be a torch.Tensor, got {type(image).__name__}")
    if not image.dtype.is_floating_point:
        raise TypeError(f"image must be a floating tensor in [0, 1], got dtype {image.dtype}")
    _check_srgb(srgb)
    ext = path.suffix.lower()
    if ext not in IMAGE_EXTENSIONS:
        raise ValueError(f"unsupported image format {path.suffix!r} for {str(path)!r}; "
                         f"expected one of {', '.join(IMAGE_EXTENSIONS)}")
    if ext != ".hdr":
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
        kind = "HDR" if ext == ".hdr" else "JPEG"
        raise ValueError(f"{kind} image needs 1 or 3 channels, got image of shape {tuple(image.shape)}")
    if not torch.isfinite(x).all():
        raise ValueError("image has NaN or infinite values; expected finite values")
    if ext == ".hdr":
        hdr = x.to("cpu", torch.float64).clamp(min=0.0)
        if hdr.max().item() >= _RGBE_LIMIT:
            raise ValueError(f"image has values up to {hdr.max().item():.4g}; Radiance RGBE holds values "
                             "below 2^127 (~1.7e38)")
        hdr = hdr.expand(3, -1, -1) if hdr.shape[0] == 1 else hdr
        _write_cv2(path, hdr.permute(1, 2, 0).numpy().astype(np.float32), "Radiance HDR image")
        return
    x = x.to("cpu", torch.float64).clamp(0.0, 1.0)
    if srgb:
        import kornia.color

        # kornia's encoder gives 1 - 2^-53 for 1 (round-off; the code still rounds to 255 / 65535); the clamp
        # only guarantees the code range.
        x = _apply_to_colour(x, kornia.color.linear_rgb_to_rgb).clamp(0.0, 1.0)
    array = x.permute(1, 2, 0).numpy()
    if bits == 16:
        array16 = np.round(array * 65535.0).astype(np.uint16)
        if array16.shape[2] == 2:
            _write_png16_grey_alpha(path, array16)
        else:
            _write_cv2(path, array16[:, :, 0] if array16.shape[2] == 1 else array16, "16-bit PNG")
        return
    import imageio.v3 as iio

    array8 = np.round(array * 255.0).astype(np.uint8)
    if array8.shape[2] == 1:
        array8 = array8[:, :, 0]
    if ext == ".png":
        iio.imwrite(path, array8)
    else:
        iio.imwrite(path, array8, quality=95)

"""Captures on disk: photographs with known cameras in the ``transforms.json`` convention.

The convention is the one NeRF-style tools share (Blender synthetic scenes,
instant-ngp, nerfstudio): a JSON file with the intrinsics, either
``camera_angle_x`` and / or ``camera_angle_y`` (full fields of view, radians;
one alone means square pixels; principal point at the centre) or
``fl_x, fl_y, cx, cy`` in pixels, the
image size ``w, h``, and ``frames``, each with a ``file_path`` (relative to
the JSON's folder; Blender's scenes leave out the ``.png``) and a 4x4
camera-to-world ``transform_matrix``. Camera axes are OpenGL's: the camera
looks down its -z axis with +y up and +x to the right, which is difftex's
view space (:mod:`difftex.geometry.camera`), so world -> view is the
matrix's inverse. nerfstudio's per-frame ``fl_x, fl_y, cx, cy, w, h``
(and per-frame angles) override the shared ones. Images are PNG / JPEG; an alpha channel is the
object mask.

Pixels (DESIGN.md section 2): the image coordinate ``(x, y)`` (x right, y
down, in pixels) of pixel ``(r, c)``'s centre is ``(c + 0.5, r + 0.5)``, as
in nerfstudio and instant-ngp, so ``cx = w / 2`` puts the principal point at
the centre of the image. A view-space point ``(X, Y, Z)`` at depth
``d = -Z`` lands at ``x = cx + fl_x X / d``, ``y = cy - fl_y Y / d``; in
clip space that is (:func:`projection_from_intrinsics`)::

    [2 fl_x / w,  0,           1 - 2 cx / w,  0]
    [0,           2 fl_y / h,  2 cy / h - 1,  0]
    [0,           0,           (f + n) / (n - f),  2 f n / (n - f)]
    [0,           0,           -1,            0]

with ``near`` / ``far`` = n / f (transforms.json has no standard keys for
them; this module writes and reads optional top-level ``near`` / ``far``).
The original NeRF code casts rays through integer pixel coordinates, half a
pixel off this convention; its cameras agree otherwise.

What is checked when a capture is loaded, before any fit starts (so that a
long fit does not stop halfway): the JSON's structure, every matrix (4x4,
finite, last row ``0 0 0 1``, invertible), every image file's existence
and size (from its header, without decoding it). A bad frame raises a
ValueError / FileNotFoundError naming the frame by default, since a wrong
folder or a broken export usually spoils many frames and a user wants to
know before hours of fitting; ``on_bad="skip"`` drops it with a
:class:`CaptureWarning` instead (one bad photograph among thousands).
Frames whose camera sees nothing of the mesh are found by
:func:`visible_frames` (they need the mesh, which the capture has not).
"""
from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import torch
from torch import Tensor

from .._checks import check_float, describe
from .files import PathLike, check_path
from .images import load_texture, save_image

__all__ = ["Capture", "CaptureDataset", "CaptureWarning", "Frame", "intrinsics_from_projection", "load_capture",
           "projection_from_intrinsics", "save_capture", "visible_frames"]

CAPTURE_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


class CaptureWarning(UserWarning):
    """A frame of a capture was skipped (its reason is in the message)."""


@dataclass(frozen=True)
class Frame:
    """One photograph of a capture.

    Attributes:
        name: the frame's ``file_path`` as the JSON gives it (used in messages).
        image_path: the image file it resolves to.
        camera_to_world: [4, 4] float64, OpenGL camera axes.
        fl_x, fl_y, cx, cy: intrinsics in pixels.
        width, height: image size in pixels.
    """

    name: str
    image_path: Path
    camera_to_world: Tensor
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    width: int
    height: int

    def mvp(self, near: float, far: float, dtype: torch.dtype = torch.float32) -> Tensor:
        """[4, 4] world -> clip matrix of this frame (computed in float64, returned in ``dtype``)."""
        proj = projection_from_intrinsics(self.fl_x, self.fl_y, self.cx, self.cy, self.width, self.height,
                                          near, far, dtype=torch.float64)
        return (proj @ torch.linalg.inv(self.camera_to_world)).to(dtype)


@dataclass(frozen=True)
class Capture:
    """A loaded capture: its frames (checked) and the depth range of its projections."""

    root: Path
    frames: tuple[Frame, ...]
    near: float = 0.1
    far: float = 100.0

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def resolution(self) -> tuple[int, int]:
        """(H, W) shared by every frame; ValueError if the frames differ in size."""
        sizes = {(f.height, f.width) for f in self.frames}
        if len(sizes) != 1:
            raise ValueError(f"capture {str(self.root)!r}: frames have different sizes {sorted(sizes)}; "
                             "expected one (H, W) for batched rendering")
        return sizes.pop()

    def mvp(self, dtype: torch.dtype = torch.float32) -> Tensor:
        """[N, 4, 4] world -> clip matrices of every frame, in frame order."""
        return torch.stack([f.mvp(self.near, self.far, dtype) for f in self.frames])


def projection_from_intrinsics(fl_x: float, fl_y: float, cx: float, cy: float, w: int, h: int,
                               near: float = 0.1, far: float = 100.0, *,
                               dtype: torch.dtype = torch.float32) -> Tensor:
    """[4, 4] view -> clip matrix of a pinhole camera with intrinsics in pixels (module docstring).

    With ``fl_x = fl_y = w / (2 tan(fov_x / 2))`` and the principal point at
    the centre it equals :func:`difftex.camera.perspective`. Not
    differentiable (numbers in). Raises ValueError for non-finite values,
    non-positive focal lengths or sizes, or not ``0 < near < far``.
    """
    vals = dict(fl_x=fl_x, fl_y=fl_y, cx=cx, cy=cy, w=w, h=h, near=near, far=far)
    for k, v in vals.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"projection_from_intrinsics: {k} must be a finite number, got {v!r}")
    if not (fl_x > 0 and fl_y > 0 and w > 0 and h > 0):
        raise ValueError(f"projection_from_intrinsics: fl_x, fl_y, w, h must be positive, got {vals}")
    if not 0 < near < far:
        raise ValueError(f"projection_from_intrinsics: need 0 < near < far, got near={near!r}, far={far!r}")
    n, f = float(near), float(far)
    return torch.tensor([[2 * fl_x / w, 0.0, 1 - 2 * cx / w, 0.0],
                         [0.0, 2 * fl_y / h, 2 * cy / h - 1, 0.0],
                         [0.0, 0.0, (f + n) / (n - f), 2 * f * n / (n - f)],
                         [0.0, 0.0, -1.0, 0.0]], dtype=torch.float64).to(dtype)


def intrinsics_from_projection(proj: Tensor, w: int, h: int) -> dict:
    """The inverse of :func:`projection_from_intrinsics`: ``{"fl_x", "fl_y", "cx", "cy", "w", "h", "near", "far"}``.

    Args:
        proj: [4, 4] pinhole perspective projection (e.g. from
            :func:`difftex.camera.perspective`).
        w, h: the image size in pixels it renders.

    Raises ValueError naming ``proj`` when it is not of the pinhole form
    (skew, a shear of z, an orthographic last row).
    """
    check_float("proj", proj, 2, shape_doc="[4, 4]")
    if proj.shape != (4, 4):
        raise ValueError(f"proj: expected [4, 4], got {describe(proj)}")
    p = proj.detach().to("cpu", torch.float64)
    form = torch.tensor([[1, 0, 1, 0], [0, 1, 1, 0], [0, 0, 1, 1], [0, 0, 1, 0]], dtype=torch.bool)
    if not bool(torch.isfinite(p).all()) or bool((p[~form] != 0).any()) or p[3, 2] != -1 or p[0, 0] <= 0 or p[1, 1] <= 0:
        raise ValueError(f"proj: expected a pinhole perspective projection (zeros off the pattern, last row "
                         f"[0, 0, -1, 0], positive focal terms), got {p.tolist()}")
    a, b = float(p[2, 2]), float(p[2, 3])
    return {"fl_x": float(p[0, 0]) * w / 2, "fl_y": float(p[1, 1]) * h / 2,
            "cx": (1 - float(p[0, 2])) * w / 2, "cy": (1 + float(p[1, 2])) * h / 2,
            "w": int(w), "h": int(h), "near": b / (a - 1), "far": b / (a + 1)}


# --------------------------------------------------------------------------
# reading


def _json_path(path: PathLike) -> Path:
    path = check_path(path, "capture (a folder with transforms.json, or the JSON itself)")
    if path.is_dir():
        path = path / "transforms.json"
    if not path.is_file():
        raise FileNotFoundError(f"capture: no transforms.json at {str(path)!r}")
    return path


def _image_path(root: Path, name: str) -> Path:
    """The image ``file_path`` names; Blender's scenes leave out the extension."""
    path = (root / name).resolve() if not os.path.isabs(name) else Path(name)
    if path.suffix.lower() in CAPTURE_IMAGE_EXTENSIONS or path.exists():
        return path
    for ext in CAPTURE_IMAGE_EXTENSIONS:
        if path.with_name(path.name + ext).exists():
            return path.with_name(path.name + ext)
    return path


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file's header (Pillow opens lazily; nothing is decoded)."""
    from PIL import Image

    with Image.open(path) as im:
        return im.size


def _number(raw: dict, key: str, where: str) -> float:
    v = raw[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)


def _intrinsics(raw: dict, base: dict, where: str) -> dict:
    """fl_x, fl_y, cx, cy, w, h from ``raw`` over ``base``; ``camera_angle_x`` / ``_y`` give focal lengths."""
    out = dict(base)
    for k in _INTRINSIC_KEYS:
        if k in raw:
            out[k] = _number(raw, k, where)
    for k in _DISTORTION_KEYS:
        if k in raw and _number(raw, k, where) != 0:
            raise ValueError(f"{where}: lens distortion {k}={raw[k]!r} is not supported (difftex renders a pinhole "
                             "camera); undistort the images first (e.g. with COLMAP's image_undistorter)")
    # An angle given here (without its focal length) overrides what ``base`` gave for that axis; one alone,
    # with nothing here for the other axis, also drops the other axis' inherited value (square pixels).
    given = [axis for axis in ("x", "y") if f"fl_{axis}" not in raw and f"camera_angle_{axis}" in raw]
    for axis in given:
        a = _number(raw, f"camera_angle_{axis}", where)
        if not 0 < a < math.pi:
            raise ValueError(f"{where}: camera_angle_{axis} must lie in (0, pi) radians, got {a!r}")
        out[f"angle_{axis}"] = a
        out.pop(f"fl_{axis}", None)
    if len(given) == 1:
        other = "y" if given[0] == "x" else "x"
        if f"fl_{other}" not in raw:
            out.pop(f"fl_{other}", None)
            out.pop(f"angle_{other}", None)
    return out


def _resolve(intr: dict, size: Optional[tuple[int, int]], where: str) -> tuple[float, float, float, float, int, int]:
    """Complete intrinsics: w, h from the image when absent; focal lengths from angles; centred principal point."""
    w, h = intr.get("w"), intr.get("h")
    if (w is None or h is None) and size is None:
        raise ValueError(f"{where}: no image size (w, h) in the JSON and no image to read it from")
    if w is None or h is None:
        w, h = size
    w, h = int(w), int(h)
    fl_x, fl_y = intr.get("fl_x"), intr.get("fl_y")
    if fl_x is None and "angle_x" in intr:
        fl_x = 0.5 * w / math.tan(0.5 * intr["angle_x"])
    if fl_y is None and "angle_y" in intr:
        fl_y = 0.5 * h / math.tan(0.5 * intr["angle_y"])
    if fl_x is None and fl_y is None:
        raise ValueError(f"{where}: expected fl_x (with fl_y, cx, cy), camera_angle_x or camera_angle_y for the "
                         "focal length")
    # One focal length alone: square pixels.
    fl_x, fl_y = (fl_y if fl_x is None else fl_x), (fl_x if fl_y is None else fl_y)
    cx = intr.get("cx", w / 2)
    cy = intr.get("cy", h / 2)
    if not (fl_x > 0 and fl_y > 0 and w > 0 and h > 0):
        raise ValueError(f"{where}: fl_x, fl_y, w, h must be positive, got {fl_x}, {fl_y}, {w}, {h}")
    return fl_x, fl_y, cx, cy, w, h


def _matrix(raw: object, where: str) -> Tensor:
    try:
        m = torch.tensor(raw, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{where}: transform_matrix must be a 4x4 list of numbers, got {str(raw)[:80]}") from None
    if m.shape != (4, 4):
        raise ValueError(f"{where}: transform_matrix must be 4x4, got shape {tuple(m.shape)}")
    if not bool(torch.isfinite(m).all()):
        raise ValueError(f"{where}: transform_matrix has NaN or infinite entries: {m.tolist()}")
    if not torch.equal(m[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)):
        raise ValueError(f"{where}: transform_matrix's last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    if abs(float(torch.linalg.det(m[:3, :3]))) < 1e-12:
        raise ValueError(f"{where}: transform_matrix is singular (its 3x3 part has determinant ~0)")
    return m


def load_capture(path: PathLike, *, near: Optional[float] = None, far: Optional[float] = None,
                 on_bad: str = "raise", check_images: bool = True) -> Capture:
    """Read a ``transforms.json`` capture and check every frame (module docstring).

    Args:
        path: the capture's folder (holding ``transforms.json``) or the JSON file.
        near, far: depth range of the projections; default the JSON's
            ``near`` / ``far`` keys, else 0.1 and 100 (scene units).
        on_bad: "raise" (default): a bad frame raises, naming it. "skip":
            it is dropped with a :class:`CaptureWarning` naming it and why.
        check_images: check each image exists and has the size the
            intrinsics give (reads only the header).

    Returns:
        A :class:`Capture`; no image is decoded (:class:`CaptureDataset` does that lazily).

    Raises FileNotFoundError for a missing JSON or (``on_bad="raise"``) a
    missing image, ValueError naming the frame for a bad matrix, size or
    intrinsics, and ValueError when no usable frame is left.
    """
    if on_bad not in ("raise", "skip"):
        raise ValueError(f"on_bad: expected 'raise' or 'skip', got {on_bad!r}")
    jpath = _json_path(path)
    try:
        meta = json.loads(jpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"capture {str(jpath)!r}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise ValueError(f"capture {str(jpath)!r}: expected an object with a non-empty 'frames' list")
    root = jpath.parent
    near = meta.get("near", 0.1) if near is None else near
    far = meta.get("far", 100.0) if far is None else far
    if not (isinstance(near, (int, float)) and isinstance(far, (int, float)) and 0 < near < far < math.inf):
        raise ValueError(f"capture {str(jpath)!r}: need 0 < near < far (finite), got near={near!r}, far={far!r}")
    shared = _intrinsics(meta, {}, f"capture {str(jpath)!r}")
    frames = []
    for i, raw in enumerate(meta["frames"]):
        name = raw.get("file_path") if isinstance(raw, dict) else None
        where = f"capture {str(jpath)!r} frame {i} ({name!r})"
        try:
            if not isinstance(name, str) or "transform_matrix" not in raw:
                raise ValueError(f"{where}: expected 'file_path' (a string) and 'transform_matrix'")
            c2w = _matrix(raw["transform_matrix"], where)
            intr = _intrinsics(raw, shared, where)
            image = _image_path(root, name)
            size = None
            if check_images:
                if not image.is_file():
                    raise FileNotFoundError(f"{where}: image not found at {str(image)!r}")
                if image.suffix.lower() not in CAPTURE_IMAGE_EXTENSIONS:
                    raise ValueError(f"{where}: unsupported image format {image.suffix!r}; expected "
                                     f"{', '.join(CAPTURE_IMAGE_EXTENSIONS)}")
                size = _image_size(image)
            fl_x, fl_y, cx, cy, w, h = _resolve(intr, size, where)
            if size is not None and size != (w, h):
                raise ValueError(f"{where}: image {str(image)!r} is {size[0]}x{size[1]} pixels, the intrinsics say "
                                 f"{w}x{h} (w x h)")
        except (ValueError, FileNotFoundError) as exc:
            if on_bad == "raise":
                raise
            warnings.warn(f"skipping: {exc}", CaptureWarning, stacklevel=2)
            continue
        frames.append(Frame(name, image, c2w, fl_x, fl_y, cx, cy, w, h))
    if not frames:
        raise ValueError(f"capture {str(jpath)!r}: no usable frame (all {len(meta['frames'])} were skipped)")
    return Capture(root, tuple(frames), float(near), float(far))


# --------------------------------------------------------------------------
# writing


def save_capture(path: PathLike, images: Tensor, world_to_view: Tensor, projection: Tensor, *,
                 masks: Optional[Tensor] = None, ext: str = ".png", prefix: str = "images/frame_") -> Path:
    """Write views as a ``transforms.json`` capture that the NeRF-style tools and :func:`load_capture` read.

    Args:
        path: folder to write (created); the JSON goes to ``path/transforms.json``,
            images to ``path/<prefix>00000<ext>``, ...
        images: [N, C, H, W] float in [0, 1], C = 3 (or 1); written as
            8-bit, so they come back within half a code (1 / 510).
        world_to_view: [N, 4, 4], e.g. :func:`difftex.camera.look_at`; the
            JSON stores its inverse (camera-to-world, OpenGL axes).
        projection: [4, 4] or [N, 4, 4] pinhole perspective projection(s);
            one shared projection becomes top-level intrinsics (plus
            ``camera_angle_x`` for Blender-style readers), different ones per-frame keys.
        masks: optional [N, 1, H, W] in [0, 1], written as the images' alpha
            (PNG only).
        ext: ".png" or ".jpg".

    Returns the JSON's path. Raises ValueError / TypeError naming the argument for bad shapes.
    """
    check_float("images", images, 4, shape_doc="[N, C, H, W]")
    N, C, H, W = images.shape
    check_float("world_to_view", world_to_view, 3, shape_doc="[N, 4, 4]")
    if world_to_view.shape != (N, 4, 4):
        raise ValueError(f"world_to_view: expected [{N}, 4, 4] like images, got {describe(world_to_view)}")
    check_float("projection", projection, (2, 3), shape_doc="[4, 4] or [N, 4, 4]")
    if projection.shape[-2:] != (4, 4) or (projection.dim() == 3 and projection.shape[0] != N):
        raise ValueError(f"projection: expected [4, 4] or [{N}, 4, 4], got {describe(projection)}")
    if masks is not None:
        check_float("masks", masks, 4, shape_doc=f"[{N}, 1, {H}, {W}]")
        if masks.shape != (N, 1, H, W):
            raise ValueError(f"masks: expected [{N}, 1, {H}, {W}], got {describe(masks)}")
        if ext.lower() != ".png":
            raise ValueError(f"ext: masks are written as alpha, which needs '.png', got {ext!r}")
    if ext.lower() not in CAPTURE_IMAGE_EXTENSIONS:
        raise ValueError(f"ext: expected one of {CAPTURE_IMAGE_EXTENSIONS}, got {ext!r}")
    root = check_path(path, "capture folder")
    projs = projection.detach().to("cpu", torch.float64)
    per_frame = projs.dim() == 3 and bool((projs != projs[:1]).any())
    intr = [intrinsics_from_projection(p, W, H) for p in (projs if per_frame else projs.reshape(-1, 4, 4)[:1])]
    c2w = torch.linalg.inv(world_to_view.detach().to("cpu", torch.float64))
    meta: dict = {"w": W, "h": H, "near": intr[0]["near"], "far": intr[0]["far"]}
    if not per_frame:
        meta.update({k: intr[0][k] for k in ("fl_x", "fl_y", "cx", "cy")})
        meta["camera_angle_x"] = 2 * math.atan(0.5 * W / intr[0]["fl_x"])
    frames = []
    for i in range(N):
        name = f"{prefix}{i:05d}{ext}"
        file = root / name
        file.parent.mkdir(parents=True, exist_ok=True)
        img = images[i].detach()
        if masks is not None:
            img = torch.cat([img, masks[i].detach().to(img.dtype)], 0)
        save_image(file, img)
        frame = {"file_path": name, "transform_matrix": c2w[i].tolist()}
        if per_frame:
            frame.update({k: intr[i][k] for k in ("fl_x", "fl_y", "cx", "cy")})
        frames.append(frame)
    meta["frames"] = frames
    jpath = root / "transforms.json"
    jpath.write_text(json.dumps(meta, indent=2) + "\n")
    return jpath


# --------------------------------------------------------------------------
# lazy loading and visibility


class CaptureDataset(torch.utils.data.Dataset):
    """The frames of a :class:`Capture` as a map-style dataset; each image is read when it is asked for.

    ``dataset[i]`` is ``{"index": i, "image": [3, H, W], "mask": [1, H, W],
    "mvp": [4, 4]}`` in ``dtype`` on the CPU (a DataLoader with
    ``pin_memory=True`` pins them for a CUDA copy): values as stored (code /
    255), the mask is the image's alpha (ones without one), ``mvp`` the
    frame's world -> clip matrix. Grey images are repeated to 3 channels.

    Raises ValueError naming the frame when its image no longer has the size
    the capture says (it changed after :func:`load_capture` checked it) or
    has an unsupported channel count.
    """

    def __init__(self, capture: Capture, dtype: torch.dtype = torch.float32,
                 frames: Optional[Sequence[int]] = None) -> None:
        if not isinstance(capture, Capture):
            raise TypeError(f"capture: expected a difftex.io.Capture, got {type(capture).__name__}")
        self.capture = capture
        self.dtype = dtype
        self.frames = list(range(len(capture))) if frames is None else [int(i) for i in frames]
        self._mvp = capture.mvp(dtype)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> dict:
        k = self.frames[i]
        frame = self.capture.frames[k]
        img = load_texture(frame.image_path, dtype=self.dtype)[0]
        where = f"frame {k} ({frame.name!r})"
        if img.shape[1:] != (frame.height, frame.width):
            raise ValueError(f"{where}: image is {img.shape[2]}x{img.shape[1]} pixels, expected "
                             f"{frame.width}x{frame.height} (w x h)")
        C = img.shape[0]
        if C in (2, 4):
            img, mask = img[:-1], img[-1:]
        else:
            mask = torch.ones_like(img[:1])
        if img.shape[0] == 1:
            img = img.expand(3, -1, -1).clone()
        return {"index": k, "image": img, "mask": mask, "mvp": self._mvp[k]}


def visible_frames(mvp: Tensor, positions: Tensor, faces: Tensor, resolution: Sequence[int], *,
                   chunk: int = 16) -> Tensor:
    """[N] int64: covered pixels of each view of the mesh at ``resolution`` (0: the camera sees nothing of it).

    Args:
        mvp: [N, 4, 4] world -> clip matrices (e.g. :meth:`Capture.mvp`).
        positions, faces: the mesh ([V, 3] float, [F, 3] int64).
        resolution: (H, W) to rasterize at (the capture's, so that a sliver
            of the mesh still counts).
        chunk: views rasterized at once; any number of views fits in memory.

    Not differentiable. Raises TypeError / ValueError naming ``mvp`` for a
    bad matrix tensor (the rasterizer checks the rest).
    """
    from ..geometry.camera import transform
    from ..geometry.raster import rasterize

    check_float("mvp", mvp, 3, shape_doc="[N, 4, 4]")
    if mvp.shape[-2:] != (4, 4):
        raise ValueError(f"mvp: expected [N, 4, 4], got {describe(mvp)}")
    counts = []
    with torch.no_grad():
        for m in torch.split(mvp.to(positions), chunk):
            frags = rasterize(transform(positions, m), faces, resolution)
            counts.append(frags.mask.flatten(1).sum(1))
    return torch.cat(counts)

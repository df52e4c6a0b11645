"""A capture's frames held in memory for a fit whose mesh does not move: each frame rasterized once, each image
loaded once.

A fit of the texture (or uv) renders the same fragments for a frame at every step, since only the texture and uv
change and neither moves a triangle on the screen. When the fragments of every frame and the images fit a budget,
:func:`rasterize_frames` keeps the fragments of its one pass over the frames (the pass that finds the frames that
see the mesh) and :meth:`FrameCache.load` reads each image once; each step then gathers its views from
memory, as the in-memory demo does, with no DataLoader and no worker processes. Otherwise the fit rasterizes each
step's views and streams the images (experiments/fit/fit_texture.py).

Memory: fragments are kept for covered pixels only, as the renderer reads them (flat pixel and triangle index,
int32; barycentrics and their two screen derivatives, 3 floats each): :func:`compact_bytes` (44 B in float32)
per covered pixel, a fraction of the dense [N, H, W] fragments where the object fills a fraction of the frame; depth
is not kept (the texture renderer does not read it). Images and masks are dense at the capture's resolution, as
the loss reads every pixel: ``(3 + 1) * 4`` bytes a pixel in float32.

A batch built here equals, bit for bit, the one the per-step path builds for the same frames: the fragments hold
the values :meth:`difftex.TexturedMesh.rasterize` gives (the rasterizer treats each view on its own), and the
images are the Dataset's tensors.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import Tensor

import difftex
from difftex import Fragments


def compact_bytes(dtype: torch.dtype = torch.float32) -> int:
    """Bytes the cache holds per covered pixel: two int32 indices and 9 floats (bary, bary_dx, bary_dy)."""
    return 2 * 4 + 9 * torch.empty((), dtype=dtype).element_size()


def image_bytes(frames: int, resolution: Sequence[int], dtype: torch.dtype = torch.float32) -> int:
    """Bytes the cache holds for ``frames`` images with their masks (3 + 1 channels) at (H, W)."""
    H, W = resolution
    return frames * 4 * H * W * torch.empty((), dtype=dtype).element_size()


@dataclass
class CompactFragments:
    """The covered pixels of N frames, frame after frame: frame k's are rows ``starts[k]:starts[k + 1]``.

    Attributes:
        starts: [N + 1] int64 offsets.
        pixel: [P] int32 flat pixel index ``row * W + column`` within its frame.
        tri_id: [P] int32 visible triangle.
        bary, bary_dx, bary_dy: [P, 3] as in :class:`difftex.Fragments`.
        resolution: (H, W).
    """

    starts: Tensor
    pixel: Tensor
    tri_id: Tensor
    bary: Tensor
    bary_dx: Tensor
    bary_dy: Tensor
    resolution: tuple[int, int]

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.starts, self.pixel, self.tri_id, self.bary,
                                                          self.bary_dx, self.bary_dy))

    def subset(self, frames: Sequence[int]) -> "CompactFragments":
        """The frames ``frames``, in that order."""
        rows = [torch.arange(int(self.starts[k]), int(self.starts[k + 1])) for k in frames]
        rows = torch.cat(rows) if rows else torch.zeros(0, dtype=torch.int64)
        counts = (self.starts[1:] - self.starts[:-1])[torch.as_tensor(list(frames), dtype=torch.int64)]
        starts = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
        pick = lambda t: t.index_select(0, rows.to(t.device))  # noqa: E731
        return CompactFragments(starts, pick(self.pixel), pick(self.tri_id), pick(self.bary), pick(self.bary_dx),
                                pick(self.bary_dy), self.resolution)

    def fragments(self, frames: Sequence[int]) -> Fragments:
        """Dense :class:`difftex.Fragments` [len(frames), H, W] of ``frames``, for ``TexturedMesh(frags=...)``.

        ``depth`` is zero everywhere (not kept; the texture renderer does not read it).
        """
        H, W = self.resolution
        HW = H * W
        B = len(frames)
        dev = self.bary.device
        rows, flat = [], []
        for j, k in enumerate(frames):
            a, b = int(self.starts[k]), int(self.starts[k + 1])
            rows.append(torch.arange(a, b, device=dev))
            flat.append(self.pixel[a:b].to(torch.int64) + j * HW)
        rows, flat = torch.cat(rows), torch.cat(flat)
        tri_id = torch.full((B * HW,), -1, dtype=torch.int64, device=dev)
        tri_id.index_copy_(0, flat, self.tri_id.index_select(0, rows).to(torch.int64))

        def dense(t: Tensor) -> Tensor:
            out = t.new_zeros((B * HW, 3))
            out.index_copy_(0, flat, t.index_select(0, rows))
            return out.view(B, H, W, 3)

        return Fragments(tri_id=tri_id.view(B, H, W), bary=dense(self.bary),
                         depth=self.bary.new_zeros(()).expand(B, H, W), bary_dx=dense(self.bary_dx),
                         bary_dy=dense(self.bary_dy))


def rasterize_frames(model: difftex.TexturedMesh, mvp: Tensor, resolution: Sequence[int], *,
                     budget_bytes: int, chunk: int = 16) -> tuple[Tensor, Optional[CompactFragments]]:
    """Rasterize every frame once: its covered-pixel count, and its fragments while they fit ``budget_bytes``.

    Args:
        model: the textured mesh (its positions and faces are rasterized).
        mvp: [N, 4, 4] world -> clip matrices of the frames.
        resolution: (H, W) of the frames.
        budget_bytes: the most the kept fragments may take; past it the pass goes on counting and
            keeps nothing (0: count only, like :func:`difftex.io.visible_frames`).
        chunk: frames rasterized at once.

    Returns:
        ``(counts [N] int64, fragments or None)``: None when they did not fit the budget.

    Not differentiable (no_grad). Raises ValueError naming ``budget_bytes`` when it is negative.
    """
    if budget_bytes < 0:
        raise ValueError(f"budget_bytes: expected >= 0, got {budget_bytes}")
    H, W = resolution
    if H * W >= 2 ** 31 or model.faces.shape[0] >= 2 ** 31:
        budget_bytes = 0  # int32 indices would not hold them: count only, the fit takes the per-step path
    per_pixel = compact_bytes(model.positions.dtype)
    counts, kept = [], 0
    parts: Optional[list] = [] if budget_bytes > 0 else None
    with torch.no_grad():
        for m in torch.split(mvp, chunk):
            frags = model.rasterize(m, (H, W))
            covered = frags.mask.flatten(1).sum(1)
            counts.append(covered)
            if parts is None:
                continue
            kept += int(covered.sum()) * per_pixel
            if kept > budget_bytes:
                parts = None  # frees what was kept: the caller falls back to the per-step path
                continue
            flat = torch.nonzero(frags.tri_id.reshape(-1) >= 0).squeeze(1)
            local = (flat % (H * W)).to(torch.int32)
            parts.append((local, frags.tri_id.reshape(-1).index_select(0, flat).to(torch.int32),
                          *(t.reshape(-1, 3).index_select(0, flat) for t in (frags.bary, frags.bary_dx,
                                                                             frags.bary_dy))))
    counts = torch.cat(counts)
    if parts is None:
        return counts, None
    cols = [torch.cat(c) for c in zip(*parts)] if parts else []
    starts = torch.cat([counts.new_zeros(1), counts.cumsum(0)]).cpu().to(torch.int64)
    return counts, CompactFragments(starts, *cols, resolution=(H, W))


@dataclass
class FrameCache:
    """Fragments and images of a capture's frames in memory; ``batch(frames)`` is what a step renders and compares.

    Attributes:
        fragments: the frames' covered pixels (:class:`CompactFragments`).
        images: [N, 3, H, W] and masks [N, 1, H, W] as :class:`difftex.io.CaptureDataset` gives them.
    """

    fragments: CompactFragments
    images: Tensor
    masks: Tensor

    @classmethod
    def load(cls, fragments: CompactFragments, dataset: torch.utils.data.Dataset,
             device: torch.device | str = "cpu") -> "FrameCache":
        """Read every image of ``dataset`` once (in this process: no workers), in the order of ``fragments``.

        ``dataset[i]`` must give ``{"image": [3, H, W], "mask": [1, H, W]}`` for frame i of ``fragments``
        (a :class:`difftex.io.CaptureDataset` over the same frames). Raises ValueError naming ``dataset``
        when its length differs from the fragments'.
        """
        N = len(fragments.starts) - 1
        if len(dataset) != N:
            raise ValueError(f"dataset: expected {N} frames like the fragments, got {len(dataset)}")
        H, W = fragments.resolution
        images = masks = None
        for i in range(N):
            item = dataset[i]
            if images is None:  # filled in place: no list of N tensors beside the stacked copy
                images = item["image"].new_empty((N, *item["image"].shape), device=device)
                masks = item["mask"].new_empty((N, *item["mask"].shape), device=device)
            images[i].copy_(item["image"])
            masks[i].copy_(item["mask"])
        return cls(fragments, images, masks)

    @property
    def nbytes(self) -> int:
        return self.fragments.nbytes + sum(t.numel() * t.element_size() for t in (self.images, self.masks))

    def batch(self, frames: Sequence[int]) -> tuple[Fragments, Tensor, Tensor]:
        """``(fragments, images [B, 3, H, W], masks [B, 1, H, W])`` of ``frames``."""
        idx = torch.as_tensor(list(frames), dtype=torch.int64, device=self.images.device)
        return self.fragments.fragments(frames), self.images.index_select(0, idx), self.masks.index_select(0, idx)

"""``TexturedMesh``: the whole pipeline as one ``nn.Module`` for training loops."""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor, nn

from .._checks import check_float, check_same, describe
from ..geometry import camera
from ..geometry.interpolate import interpolate
from ..geometry.mesh import Mesh
from ..geometry.raster import Fragments, rasterize
from ..texture.options import check_number, check_stochastic
from ..texture.sample import sample
from ..texture.wrap import Wrap

class TexturedMesh(nn.Module):
    """A mesh with a texture (and optionally its uv) as learnable parameters.

    Args:
        mesh: a :class:`difftex.Mesh` (positions, faces, face-varying uv).
        texture: [C, H, W] or [1, C, H, W] float initial texture.
        filter: any filter of :func:`difftex.sample`; the minification
            filters ("trilinear", "anisotropic", "ewa", ...) read a mip
            pyramid that sample() rebuilds from the texture at each forward,
            so gradients reach the base texture through every level.
        wrap: wrap mode(s) for the texture lookups.
        max_aniso: longest footprint axis over shortest the anisotropic and
            EWA filters resolve.
        lod_bias: added to the mip level (a plain attribute: a fit may
            schedule it, e.g. coarse to fine).
        learn_texture: register the texture as an ``nn.Parameter``.
        learn_uv: register the uv [T, 2] as an ``nn.Parameter`` too.
        background: value of pixels that no triangle covers (a finite number).
        stochastic: 0 (default) reads the texture with the deterministic
            filter; k >= 1 with stochastic texture filtering, k draws a
            pixel (:func:`difftex.sample`'s ``stochastic``), from the
            module's own generator (``seed``; its state is part of the
            ``state_dict``, so a resumed fit draws what an uninterrupted
            one would).
        decorrelate: with ``stochastic`` and gradients enabled, the image's
            value comes from one set of draws and its gradient from an
            independent one (:func:`difftex.sample`'s ``decorrelate``): the
            gradient of an L2 loss is then ``2 (a - y) db/dθ``, whose
            expectation is the gradient of ``(E a - y)^2``. With one set
            (False), the expectation of the loss is ``(E a - y)^2 + Var a``,
            and the variance term pulls every texel towards its footprint's
            mean (a blur the deterministic filter does not have). No extra
            reads on the CPU's trilinear and anisotropic kernels.
        seed: seeds the draws' generator.

    Raises TypeError naming the argument for a texture that is not float32 /
    float64, a background that is not a number or a ``stochastic`` that is
    not an int, ValueError for shapes, a negative ``stochastic`` or one with
    a filter that has no stochastic mode (``sample``'s check,
    ``difftex.texture.options.check_stochastic``).

    ``forward(mvp, resolution)`` renders images; gradients reach the texture,
    the uv (when learned) and ``mvp`` (through the barycentrics).
    """

    def __init__(self, mesh: Mesh, texture: Tensor, *, filter: str = "trilinear", wrap: Wrap = "clamp",
                 max_aniso: float = 16, lod_bias: float = 0.0, learn_texture: bool = True,
                 learn_uv: bool = False, background: float = 0.0, stochastic: int = 0,
                 decorrelate: bool = True, seed: int = 0) -> None:
        super().__init__()
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh: expected a difftex.Mesh, got {type(mesh).__name__}")
        check_float("texture", texture, (3, 4), shape_doc="[C, H, W] or [1, C, H, W]")
        if texture.dtype not in (torch.float32, torch.float64):
            # The mesh is rasterized in the texture's dtype, which must be one the rasterizer takes.
            raise TypeError(f"texture: expected float32 or float64 [C, H, W] or [1, C, H, W], got {describe(texture)}")
        background = check_number("background", background, -math.inf)
        if texture.dim() == 3:
            texture = texture.unsqueeze(0)
        if texture.shape[0] != 1:
            raise ValueError(f"texture: expected one texture [1, C, H, W], got shape {tuple(texture.shape)}")
        texture = texture.detach().clone()
        uv = mesh.uv.detach().clone().to(texture.dtype)
        self._register("texture", texture, learn_texture)
        self._register("uv", uv, learn_uv)
        self.register_buffer("positions", mesh.positions.detach().clone().to(texture.dtype))
        self.register_buffer("faces", mesh.faces.clone())
        self.register_buffer("uv_faces", mesh.uv_faces.clone())
        self.filter = filter
        self.wrap = wrap
        self.max_aniso = max_aniso
        self.lod_bias = lod_bias
        self.background = background
        self.stochastic = check_stochastic(stochastic, filter)
        self.decorrelate = bool(decorrelate)
        self.generator = torch.Generator(device=texture.device).manual_seed(int(seed))

    def get_extra_state(self) -> dict:
        # The draws' generator travels with the parameters: a checkpoint resumes the same draws.
        return {"generator": self.generator.get_state()}

    def set_extra_state(self, state: dict) -> None:
        self.generator.set_state(state["generator"])

    def _apply(self, fn, recurse: bool = True):
        out = super()._apply(fn, recurse)
        # .to(device) moves the tensors; the generator follows (its draws restart from its seed there).
        if self.texture.device != self.generator.device:
            self.generator = torch.Generator(device=self.texture.device).manual_seed(self.generator.initial_seed())
        return out

    def _register(self, name: str, value: Tensor, learn: bool) -> None:
        if learn:
            self.register_parameter(name, nn.Parameter(value))
        else:
            self.register_buffer(name, value)

    def rasterize(self, mvp: Tensor, resolution: Sequence[int]) -> Fragments:
        """Rasterize the mesh for cameras ``mvp`` [B, 4, 4] (world -> clip) at (H, W).

        The fragments depend only on the geometry and cameras: a loop that
        fits only the texture or uv can compute them once and pass them to
        ``forward``.
        """
        check_float("mvp", mvp, (2, 3), shape_doc="[B, 4, 4] or [4, 4]")
        if mvp.shape[-2:] != (4, 4):
            raise ValueError(f"mvp: expected [B, 4, 4] or [4, 4], got shape {tuple(mvp.shape)}")
        mvp = mvp.to(self.positions)
        pos = camera.transform(self.positions, mvp if mvp.dim() == 3 else mvp.unsqueeze(0))
        return rasterize(pos, self.faces, resolution)

    def forward(self, mvp: Tensor | None = None, resolution: Sequence[int] | None = None, *,
                frags: Fragments | None = None, uv: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Render the textured mesh.

        Args:
            mvp: [B, 4, 4] or [4, 4] world -> clip matrices, e.g.
                ``camera.perspective(...) @ camera.look_at(...)``.
            resolution: (H, W) of the images.
            frags: precomputed fragments (from :meth:`rasterize`) instead
                of ``mvp`` and ``resolution``.
            uv: [T, 2] uv to use instead of the module's own, e.g. the
                output of a user's parametrization (a texture matrix).

        Returns:
            ``(images [B, C, H, W], mask [B, 1, H, W] float coverage)``;
            uncovered pixels hold ``background``.
        """
        if frags is None:
            if mvp is None or resolution is None:
                raise ValueError("forward: expected mvp and resolution, or precomputed frags")
            frags = self.rasterize(mvp, resolution)
        if uv is None:
            uv = self.uv
        else:
            check_float("uv", uv, 2, last=2, shape_doc=f"{tuple(self.uv.shape)} like the mesh's uv")
            if uv.shape != self.uv.shape:
                raise ValueError(f"uv: expected shape {tuple(self.uv.shape)} like the mesh's uv, got {describe(uv)}")
            check_same("uv", uv, "the texture", self.texture)
        mask = frags.mask.unsqueeze(1)
        if not bool(mask.any()):
            # Nothing to read: every pixel is background. The learned tensors
            # (and the geometry, through the barycentrics) stay in the graph with zero gradients, as the filters that read
            # (and pass zero gradients back for) the uncovered pixels give
            # them; sampling here would leave the texture out of the graph
            # where a filter's backward reports "no texel read" as None (the
            # native mip taps do).
            B, _, H, W = mask.shape
            C = self.texture.shape[1]
            image = self.texture.new_full((B, C, H, W), self.background)
            for t in (self.texture, uv, frags.bary):
                image = image + t.reshape(-1)[:0].sum()  # 0, in the graph
            return image, mask.to(image.dtype)
        uv, uv_dx, uv_dy = interpolate(uv, self.faces, frags, derivatives=True, attr_faces=self.uv_faces)
        kw = dict(filter=self.filter, wrap=self.wrap, uv_dx=uv_dx, uv_dy=uv_dy, max_aniso=self.max_aniso,
                  lod_bias=self.lod_bias)
        if self.stochastic:
            kw.update(stochastic=self.stochastic, generator=self.generator,
                      decorrelate=self.decorrelate and torch.is_grad_enabled())
        image = sample(self.texture, uv, **kw)
        image = torch.where(mask, image, image.new_tensor(self.background))
        return image, mask.to(image.dtype)

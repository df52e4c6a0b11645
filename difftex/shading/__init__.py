"""Textures in shading: lighting, texture modes, tangent frames, bump / normal / displacement maps.

* :func:`blinn_phong` (several lights, ambient, ambient occlusion, optional
  energy normalisation) and :func:`combine` ("replace", "modulate", "decal");
* :func:`tangent_frames` (per-vertex T and handedness from uv, seams split),
  :func:`surface_frames` (per-pixel orthonormal T, B, N), :func:`vertex_normals`;
* :func:`bump` (height-map slope from the filtered interpolant, or the
  seed's forward difference), :func:`normal_map` (tangent-space maps),
  :func:`height_slope`;
* :func:`displace` (vertices move along normals) and :func:`subdivide`.

Layouts: geometry and colours are channels-last ([..., 3], [..., C], per
pixel [B, Ho, Wo, ...] like uv); textures stay [B, C, H, W] as for
:func:`difftex.sample` (``sample(...).movedim(1, -1)`` gives channels-last).
"""
from .displace import displace, subdivide
from .frames import TangentFrames, surface_frames, tangent_frames, vertex_normals
from .lighting import MODES, blinn_phong, combine
from .perturb import SLOPE_METHODS, bump, height_slope, normal_map

__all__ = ["MODES", "SLOPE_METHODS", "TangentFrames", "blinn_phong", "bump", "combine", "displace", "height_slope",
           "normal_map", "subdivide", "surface_frames", "tangent_frames", "vertex_normals"]

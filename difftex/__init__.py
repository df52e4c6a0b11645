"""difftex: differentiable texture mapping for PyTorch.

Conventions (uv origin, tensor layouts, clip space, pixel centres) are in
DESIGN.md; this module only re-exports the public API. The subpackages:
``geometry`` (camera, mesh, rasterize, interpolate), ``texture`` (sample,
level of detail, mipmaps, filters, the native kernel), ``mapping`` (uv
generators, texture matrix), ``envmap`` (environment-map directions),
``io`` (images, meshes), ``nn`` (modules), ``metrics``, ``backend``,
``shading`` (Blinn-Phong, texture modes, tangent frames, bump / normal /
displacement maps).
"""

from . import envmap, io, mapping, metrics
from .backend import backend
from .envmap import cube_to_direction, direction_to_cube, direction_to_equirect_uv, equirect_uv_to_direction
from .geometry import Fragments, Mesh, camera, interpolate, rasterize
from .geometry import antialias, composite, depth_peel, painter
from .io import load_mesh, load_texture, save_image
from .mapping import (box_uv, cylindrical_uv, normal_uv, planar_uv, spherical_uv, texture_matrix,
                      uv_transform)
from .nn import TexturedMesh
from . import shading
from .shading import blinn_phong, bump, combine, displace, normal_map, tangent_frames
from .texture import WRAP_MODES, Mipmap, levels_needed, lod, mipmap, sample
from .texture import Ripmap, ambient_occlusion, bake, noise, ripmap, sample3d

__all__ = [
    "backend", "camera", "envmap", "io", "mapping", "metrics",
    "Fragments", "Mesh", "Mipmap", "TexturedMesh", "WRAP_MODES",
    "box_uv", "cube_to_direction", "cylindrical_uv", "direction_to_cube", "direction_to_equirect_uv",
    "equirect_uv_to_direction", "interpolate", "levels_needed", "load_mesh", "load_texture", "lod", "mipmap",
    "normal_uv", "planar_uv", "rasterize", "sample", "save_image", "spherical_uv", "texture_matrix", "uv_transform",
    # textures in shading: baking, solid and 3D textures
    "ambient_occlusion", "bake", "noise", "sample3d",
    # shading (issue 17)
    "shading", "blinn_phong", "bump", "combine", "displace", "normal_map", "tangent_frames",
    # visibility (issue 16)
    "antialias", "composite", "depth_peel", "painter",
    # ripmaps (issue 19)
    "Ripmap", "ripmap",
]

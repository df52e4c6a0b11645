"""difftex: differentiable texture mapping for PyTorch.

Conventions (uv origin, tensor layouts, clip space, pixel centres) are in
DESIGN.md; this module only re-exports the public API.
"""

from .sample import sample
from .wrap import WRAP_MODES
from . import io, mapping
from .io import Mesh, load_mesh, load_texture, save_image
from .mapping import (planar_uv, cylindrical_uv, spherical_uv, box_uv, normal_uv,
                      direction_to_equirect_uv, direction_to_cube, texture_matrix, uv_transform)
from .raster import Fragments, rasterize
from .interpolate import interpolate
from . import camera
from .mipmap import Mipmap, mipmap
from .lod import lod
from .textured_mesh import TexturedMesh
from .lod import levels_needed

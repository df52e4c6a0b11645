"""Geometry: cameras, the mesh type, the rasterizer and attribute interpolation with screen-space derivatives."""
from . import camera
from .interpolate import interpolate
from .mesh import Mesh
from .raster import Fragments, depth_peel, rasterize

__all__ = ["camera", "interpolate", "Mesh", "Fragments", "rasterize", "depth_peel"]

"""Geometry: cameras, the mesh type, the rasterizer and attribute interpolation with screen-space derivatives."""
from . import camera
from .interpolate import interpolate
from .mesh import Mesh, vertex_normals
from .raster import Fragments, rasterize

__all__ = ["camera", "interpolate", "Mesh", "Fragments", "rasterize", "vertex_normals"]

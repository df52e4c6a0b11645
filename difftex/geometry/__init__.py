"""Geometry: cameras, the mesh type, the rasterizer and attribute interpolation with screen-space derivatives."""
from . import camera
from .interpolate import interpolate
from .mesh import Mesh, vertex_normals
from .raster import Fragments, depth_peel, peel, rasterize
from .antialias import antialias, silhouette_edges
from .composite import composite
from .painter import painter

__all__ = ["camera", "interpolate", "Mesh", "Fragments", "rasterize", "depth_peel", "peel", "vertex_normals", "antialias",
           "silhouette_edges", "composite", "painter"]

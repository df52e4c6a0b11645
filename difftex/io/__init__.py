"""Files in difftex's conventions: images as textures, meshes with face-varying uv, captures (transforms.json), bundled data."""
from .capture import (Capture, CaptureDataset, CaptureWarning, Frame, intrinsics_from_projection, load_capture,
                      projection_from_intrinsics, save_capture, visible_frames)
from .files import DATA_DIR, data_path
from .images import IMAGE_EXTENSIONS, load_texture, save_image
from .meshes import MESH_EXTENSIONS, load_mesh
from ..geometry.mesh import Mesh

__all__ = ["Capture", "CaptureDataset", "CaptureWarning", "DATA_DIR", "Frame", "IMAGE_EXTENSIONS", "MESH_EXTENSIONS", "Mesh", "data_path", "load_mesh", "load_texture",
           "save_image", "intrinsics_from_projection", "load_capture", "projection_from_intrinsics",
           "save_capture", "visible_frames"]

"""Files in difftex's conventions: images as textures, meshes with face-varying uv, bundled data."""
from .files import DATA_DIR, data_path
from .images import IMAGE_EXTENSIONS, load_texture, save_image
from .meshes import MESH_EXTENSIONS, load_mesh
from ..geometry.mesh import Mesh

__all__ = ["DATA_DIR", "IMAGE_EXTENSIONS", "MESH_EXTENSIONS", "Mesh", "data_path", "load_mesh", "load_texture",
           "save_image"]

"""``torch.nn`` modules built from difftex's ops."""
from .textured_mesh import TexturedMesh

__all__ = ["TexturedMesh"]

"""Prefiltered pyramids of a texture: mipmaps of any size, with their exact adjoint."""
from .mipmap import Mipmap, level_count, level_size, mipmap

__all__ = ["Mipmap", "level_count", "level_size", "mipmap"]

"""Prefiltered pyramids of a texture: mipmaps and ripmaps of any size, with their exact adjoint."""
from .mipmap import Mipmap, level_count, level_size, mipmap
from .ripmap import Ripmap, ripmap

__all__ = ["Mipmap", "Ripmap", "level_count", "level_size", "mipmap", "ripmap"]

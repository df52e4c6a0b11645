"""Environment maps: directions to equirectangular uv and cube-map faces, and back."""
from .cube import CubeMipmap, cube_mipmap, cubemap
from .directions import cube_to_direction, direction_to_cube, direction_to_equirect_uv, equirect_uv_to_direction

__all__ = ["direction_to_equirect_uv", "equirect_uv_to_direction", "direction_to_cube", "cube_to_direction",
           "cubemap", "cube_mipmap", "CubeMipmap"]

"""Environment maps: directions to equirectangular uv and cube-map faces and back, seamless cube-map and
equirectangular lookups with every filter, and the conversion of a latitude-longitude map to a cube."""
from .cube import CubeMipmap, cube_mipmap, cube_to_equirect, cubemap
from .directions import cube_to_direction, direction_to_cube, direction_to_equirect_uv, equirect_uv_to_direction
from .equirect import equirect, equirect_to_cube

__all__ = ["direction_to_equirect_uv", "equirect_uv_to_direction", "direction_to_cube", "cube_to_direction",
           "equirect", "equirect_to_cube", "cubemap", "cube_mipmap", "CubeMipmap", "cube_to_equirect"]

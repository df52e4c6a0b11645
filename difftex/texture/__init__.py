"""Texture reads: ``sample`` with every filter and wrap mode, the level of detail, mipmaps and ripmaps.

Inside: ``sample`` (checks and dispatch), ``options`` (filter names, caps),
``wrap`` (every wrap rule), ``lod`` (footprint and level formula), ``taps``
(the mip filters' front end), ``pyramid/`` (mipmaps, ripmaps), ``filters/`` (the
gather reference, the grid_sample path and the filters built on them); the
C++ CPU kernels are ``difftex._native`` (``difftex/csrc``); ``difftex.backend`` picks.
Also: ``volume`` (``sample3d``, 3D textures), ``noise`` (Perlin noise, fBm,
wood / marble solid textures) and ``baking`` (``bake``, ambient occlusion).
"""
from . import noise
from .baking import ambient_occlusion, bake
from .lod import lod
from .options import FILTERS, MIP_FILTERS
from .pyramid import Mipmap, Ripmap, mipmap, ripmap
from .sample import sample
from .taps import levels_needed
from .volume import sample3d, volume_mipmap
from .wrap import WRAP_MODES

__all__ = ["sample", "lod", "levels_needed", "Mipmap", "mipmap", "FILTERS", "MIP_FILTERS", "WRAP_MODES",
           "sample3d", "volume_mipmap", "noise", "bake", "ambient_occlusion", "Ripmap", "ripmap"]

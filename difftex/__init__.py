"""difftex: differentiable texture mapping for PyTorch.

Conventions (uv origin, tensor layouts, clip space, pixel centres) are in
DESIGN.md; this module only re-exports the public API.
"""

from .sample import sample
from .wrap import WRAP_MODES

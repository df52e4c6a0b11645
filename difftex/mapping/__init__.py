"""Procedural uv mappings: planar, cylindrical, spherical, box and normal-projection uv
(``uv``) and the texture matrix (``matrix``), with their shared checks and polar angles
(``common``). Environment-map directions (equirectangular, cube map) are in ``difftex.envmap``.

Every generator is a plain differentiable torch function, batched over the
leading dimensions of its inputs (``[..., 3]`` points -> ``[..., 2]`` uv, so
``[B, H, W, 3]`` per-pixel positions give ``[B, H, W, 2]`` uv as DESIGN.md
wants), float32 / float64, any device.

Screen-space derivatives.  Each generator optionally takes the derivatives
of its input with respect to the pixel column / row (``points_dx``,
``points_dy``, as ``interpolate(derivatives=True)`` gives them) and then
returns ``(uv, uv_dx, uv_dy)`` computed by the chain rule with the analytic
Jacobian of the mapping.  This is not a convenience: finite differences of
uv across the atan2 seam of the spherical / cylindrical / equirectangular
maps jump by a whole texture width, which makes mip selection pick the
coarsest level along the seam; the analytic Jacobian is continuous there.

Singular points.  The angle ``phi = atan2(b, a)`` is undefined on the axis
(``a = b = 0``, the poles of a sphere, the axis of a cylinder) and the polar
angle is undefined at the centre.  Closer than :data:`EPS` (in the units of
the points) to the axis, ``phi`` is taken as 0 (so ``u = 0.5``); at the
centre itself the polar angle is pi/2 (``v = 0.5``).  Exactly on the axis
the distance to it is a cone point without a linear derivative, and its
derivative (like phi's) is taken as 0 there, so uv_dx / uv_dy are 0 there
except the cylinder's height term; just off it (r >= EPS) they are exact and grow
like 1 / r, as the true footprint does.  Denominators of the
Jacobians are clamped at ``EPS**2`` and the radius (``hypot``, so no square
overflows float32 past 1.8e19) / atan2 are guarded with the double-``where``
trick, so outputs and gradients stay finite (large near the axis, where the
true derivative diverges) and never NaN.

Non-finite input.  A NaN / inf point (or derivative) of the polar maps
(spherical, cylindrical, normal, equirectangular) gives NaN in its own
output element (derivative element) only, and a loss that leaves those
elements out gets finite gradients for the parameters the points share
(a centre, an axis): the bad elements are replaced by harmless values
before any arithmetic, so backward never forms ``0 * NaN``.
"""
from .common import CUBE_FACES, EPS
from .matrix import texture_matrix, uv_transform
from .uv import box_uv, cylindrical_uv, normal_uv, planar_uv, spherical_uv

__all__ = ["EPS", "CUBE_FACES", "planar_uv", "cylindrical_uv", "spherical_uv", "box_uv", "normal_uv", "texture_matrix",
           "uv_transform"]

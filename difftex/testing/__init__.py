"""Scenes, references, peers and the timing harness shared by difftex's tests and experiments.

Not part of the differentiable API: fixtures, computed without gradients
unless a docstring says otherwise. Modules:

* :mod:`.scenes`: closed-form scenes (the grazing plane, checker textures);
* :mod:`.meshes`: the icosphere and the spot cow's data files;
* :mod:`.references`: the supersampled reference and the checker's closed form;
* :mod:`.suite`: the 17-scene suite of the speed-vs-accuracy study;
* :mod:`.peers`: grid_sample and kornia lookups with difftex's uv and wrap;
* :mod:`.timing`: functions timed interleaved, with a pause between calls, or in
  blocks of back-to-back calls (steady state).

The one PSNR is :func:`difftex.metrics.psnr`.
"""
from .meshes import DATA_DIR, SPOT_MESH, SPOT_TEXTURE, icosphere, spot_mesh, spot_texture
from .peers import grid_sample_lookup, kornia_lookup, pad_and_grid
from .references import checker_footprint_mean, checker_pixel_box_mean, supersampled
from .scenes import checker_noise_texture, checker_texture, grazing_plane, mirror_sphere, reflection_dirs
from .suite import (CHECKER, PITCHES, SPHERE_MINIFICATION, SPOT_VIEWS, Scene, build_scenes, plane_fov, plane_scene,
                    sphere_mvp, sphere_scene, sphere_uv, spot_mvp, spot_scene)
from .timing import Timing, time_blocks, time_interleaved

__all__ = [
    "DATA_DIR", "SPOT_MESH", "SPOT_TEXTURE", "icosphere", "spot_mesh", "spot_texture",
    "grid_sample_lookup", "kornia_lookup", "pad_and_grid",
    "checker_footprint_mean", "checker_pixel_box_mean", "supersampled",
    "checker_noise_texture", "checker_texture", "grazing_plane", "mirror_sphere", "reflection_dirs",
    "CHECKER", "PITCHES", "SPHERE_MINIFICATION", "SPOT_VIEWS", "Scene", "build_scenes", "plane_fov", "plane_scene",
    "sphere_mvp", "sphere_scene", "sphere_uv", "spot_mvp", "spot_scene",
    "Timing", "time_blocks", "time_interleaved",
]

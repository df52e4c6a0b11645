"""Fits through difftex.TexturedMesh: ``python -m experiments.fit.fit_texture``, ``python -m experiments.fit.fit_uv``."""

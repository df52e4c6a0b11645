"""Runnable scripts around difftex, a package so that they import each other and the tests import them.

Run them as modules from the repository root (that puts the root, and so this
checkout's ``difftex``, on ``sys.path``), e.g.::

    python -m experiments.fit.fit_texture --help

* ``experiments.fit``: fit_texture (the main job), fit_uv.
* ``experiments.bench``: bench_sample, bench_minify, bench_raster, bench_auto.
* ``experiments.studies``: speed_vs_accuracy, stability, compare_filters, reference_check.

What the scripts share with the tests (scenes, references, the timing
harness, grid_sample peers) lives in :mod:`difftex.testing`.
"""

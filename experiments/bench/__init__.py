"""Speed benchmarks: ``python -m experiments.bench.bench_sample`` (bench_minify, bench_raster, bench_auto)."""

"""Benchmarks that score the whole chain on SYNTHETIC data: ``frames`` (camera frames -> image
network -> physics fit)."""

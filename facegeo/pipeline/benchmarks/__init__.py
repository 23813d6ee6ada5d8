"""Registered benchmarks, one module per stage; :mod:`facegeo.pipeline.bench` imports them all."""

"""Registered benchmarks, one module per stage; :mod:`facegeo.bench` imports them all."""

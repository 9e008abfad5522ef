"""Benchmarks: ``jaxsync bench`` (MJX against MuJoCo C, the gradient's cost) and the tuner benchmark."""

"""Gain optimisation (installed as ``jaxsync.optimize``)."""

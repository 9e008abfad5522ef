"""The controllers' names, importable without JAX (the CLI's argument parsing uses them)."""

CONTROLLERS = ("classical", "synchronous", "object_impedance", "task_space")
PAPER = ("classical", "synchronous")  # the paper's pair

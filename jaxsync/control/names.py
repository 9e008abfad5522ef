"""The controllers' names, importable without JAX (the CLI's argument parsing uses them)."""

CONTROLLERS = ("classical", "synchronous", "object_impedance", "task_space")  # Cartesian offsets: either stack
PAPER = ("classical", "synchronous")  # the paper's pair
# ros2_controllers' admittance rule run per arm as deployed (jaxsync.control.ros2_loop): it makes joint
# position commands itself, so it runs on position-controlled arms only
POSITION_ONLY = ("ros2_admittance",)
ALL_CONTROLLERS = CONTROLLERS + POSITION_ONLY

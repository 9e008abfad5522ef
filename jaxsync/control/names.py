"""The controllers' names, importable without JAX (the CLI's argument parsing uses them)."""

from jaxsync._errors import ConfigError

CONTROLLERS = ("classical", "synchronous", "object_impedance", "task_space")  # Cartesian offsets: either stack
PAPER = ("classical", "synchronous")  # the paper's pair
# ros2_controllers' admittance rule run per arm as deployed (jaxsync.control.ros2_loop): it makes joint
# position commands itself, so it runs on position-controlled arms only; "ros2_synchronous" is that rule
# plus the paper's coupling (eqs. 12-17) in the reference each arm's rule offsets; "ros2_coupled" the rule plus
# the coupling family (jaxsync.control.coupling), of which the other two are special cases, entering through the
# reference's target; "ros2_coupled_direct" the family put onto the rule's reference joints in the same period
FAMILY = {"ros2_coupled": "reference", "ros2_coupled_direct": "direct"}  # controller: where the family enters
POSITION_ONLY = ("ros2_admittance", "ros2_synchronous", *FAMILY)
ALL_CONTROLLERS = CONTROLLERS + POSITION_ONLY
# the ros2_controllers releases whose admittance rule jaxsync.control.ros2_admittance ports
DISTROS = ("jazzy", "kilted", "rolling", "humble")
DEFAULT_DISTRO = "jazzy"


def check_actuation(controllers, actuation: str) -> None:
    """ConfigError unless ``controllers`` (a name, or several) run on
    ``actuation``: the ros2 admittance rule makes joint position commands, so
    it needs position-controlled arms."""
    for controller in (controllers,) if isinstance(controllers, str) else controllers:
        if controller not in POSITION_ONLY or actuation == "position":
            continue
        raise ConfigError(
            f"controller {controller!r} runs on position-controlled arms only (actuation='position'): it is "
            f"ros2_controllers' admittance rule, which writes joint position commands; got actuation={actuation!r}",
            inputs=("controller", "actuation"),
        )

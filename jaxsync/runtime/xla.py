"""XLA settings for jaxsync's programs: one place, set by scripts, never at import.

XLA's CPU backend compiles fused loops with its newer "fusion emitters" by
default. On this project's programs they cost memory and buy nothing:
compiling the tuner's gradient (the full 4 s task, batch 4) held 2.34-2.49
GiB with them and 0.92-1.12 GiB without, in the same time or less, and the
compiled rollouts and gradients ran as fast (docs/performance.md, "XLA's
fusion emitters"). jaxsync therefore turns them off.

XLA reads ``$XLA_FLAGS`` once, when JAX's backend starts (the first JAX
computation). :func:`set_xla_flags` adds jaxsync's flags to it; the command
line, the benchmark's child processes, the experiments and the tests call it
first thing. Importing jaxsync changes nothing. A flag the user already set
in ``$XLA_FLAGS`` (either value) is left as it is.
"""

from __future__ import annotations

import os
import warnings

from jax._src import xla_bridge

FUSION_EMITTERS = "xla_cpu_use_fusion_emitters"
# name -> value; XLA aborts on a flag it does not know, so each is checked
# against the pinned jaxlib (tests/test_xla.py)
FLAGS = {FUSION_EMITTERS: "false"}


def _backend_started() -> bool:

    return bool(xla_bridge.backends_are_initialized())


def set_xla_flags() -> bool:
    """Add jaxsync's XLA flags to ``$XLA_FLAGS`` for this process and its children.

    Call it before the first JAX computation: XLA reads the variable when
    JAX's backend starts. Returns True when the flags are in place (added now
    or already there). If the backend has already started it changes nothing
    (the persistent cache keys programs by ``$XLA_FLAGS``: adding flags that
    XLA will not read would file programs under the wrong key), warns and
    returns False.

    Example:
      >>> import jaxsync
      >>> jaxsync.set_xla_flags()  # doctest: +SKIP
      True
    """
    current = os.environ.get("XLA_FLAGS", "")
    present = {tok.lstrip("-").split("=", 1)[0] for tok in current.split()}
    missing = [f"--{k}={v}" for k, v in FLAGS.items() if k not in present]
    if not missing:
        return True
    if _backend_started():
        warnings.warn(
            "jaxsync.set_xla_flags(): JAX's backend has already started, so XLA will not read "
            f"{' '.join(missing)}; call it before the first JAX computation (compiling then holds "
            "about twice the memory)",
            stacklevel=2,
        )
        return False
    os.environ["XLA_FLAGS"] = " ".join([current, *missing]).strip()
    return True

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

XLA aborts the process on a flag it does not know, and its flags come and go
between releases (JAX 0.11's XLA no longer has the fusion-emitter switch).
Before adding a flag, :func:`set_xla_flags` therefore looks for its name in
the XLA libraries this process would load (jaxlib's and any PJRT plugin's, such
as CUDA's), without starting XLA: a flag missing from any of them is left out,
with a warning that names it, and jaxsync runs on XLA's default.
"""

from __future__ import annotations

import functools
import importlib.util
import mmap
import os
import pathlib
import re
import warnings

from jax._src import xla_bridge

FUSION_EMITTERS = "xla_cpu_use_fusion_emitters"
# name -> value; XLA aborts on a flag it does not know, so each is checked
# against the pinned jaxlib (tests/test_xla.py)
FLAGS = {FUSION_EMITTERS: "false"}


# XLA's own code is in its large shared libraries (jaxlib's, ~20 MB and more;
# a PJRT plugin's); the small ones are Python bindings that load them
_XLA_LIBRARY_BYTES = 5_000_000


def xla_libraries() -> list[pathlib.Path]:
    """The shared libraries that hold XLA for this process: jaxlib's and installed PJRT plugins'."""
    dirs = []
    for package in ("jaxlib", "jax_plugins"):
        spec = importlib.util.find_spec(package)
        if spec is not None and spec.submodule_search_locations:
            dirs += [pathlib.Path(p) for p in spec.submodule_search_locations]
    libs = set()
    for d in dirs:
        for path in d.rglob("*.so*"):
            try:
                if path.is_file() and path.stat().st_size >= _XLA_LIBRARY_BYTES:
                    libs.add(path.resolve())
            except OSError:
                continue
    return sorted(libs)


@functools.cache
def _library_has(path: pathlib.Path, name: str) -> bool:
    # flag names sit in the library's read-only data as NUL-terminated strings
    pattern = re.compile(re.escape(name.encode()) + rb"(?![A-Za-z0-9_])")
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
        return pattern.search(m) is not None


def flag_known(name: str, libraries: list[pathlib.Path] | None = None) -> bool:
    """Whether every XLA library of this process knows the flag ``name`` (no leading dashes).

    Reads the libraries' bytes; starts nothing. False when no XLA library is found.
    """
    libs = xla_libraries() if libraries is None else libraries
    return bool(libs) and all(_library_has(p, name) for p in libs)


def _backend_started() -> bool:

    return bool(xla_bridge.backends_are_initialized())


def set_xla_flags() -> bool:
    """Add jaxsync's XLA flags to ``$XLA_FLAGS`` for this process and its children.

    Call it before the first JAX computation: XLA reads the variable when
    JAX's backend starts. Returns True when the flags are in place (added now
    or already there). If the backend has already started it changes nothing
    (the persistent cache keys programs by ``$XLA_FLAGS``: adding flags that
    XLA will not read would file programs under the wrong key), warns and
    returns False. A flag the running jaxlib (or a PJRT plugin) does not know
    is left out, with a warning naming it, and the call returns False: XLA
    would abort on it.

    Example:
      >>> import jaxsync
      >>> jaxsync.set_xla_flags()  # doctest: +SKIP
      True
    """
    current = os.environ.get("XLA_FLAGS", "")
    present = {tok.lstrip("-").split("=", 1)[0] for tok in current.split()}
    wanted = {k: v for k, v in FLAGS.items() if k not in present}
    if not wanted:
        return True
    libs = xla_libraries()
    unknown = [k for k in wanted if not flag_known(k, libs)]
    if unknown:
        import jaxlib  # noqa: PLC0415 -- its version, for the message only

        warnings.warn(
            f"jaxsync.set_xla_flags(): this jaxlib ({getattr(jaxlib, '__version__', '?')}) does not know "
            f"{', '.join('--' + k for k in unknown)}; left unset (XLA aborts on a flag it does not know), "
            "XLA's default is used",
            stacklevel=2,
        )
    missing = [f"--{k}={v}" for k, v in wanted.items() if k not in unknown]
    if not missing:
        return not unknown
    if _backend_started():
        warnings.warn(
            "jaxsync.set_xla_flags(): JAX's backend has already started, so XLA will not read "
            f"{' '.join(missing)}; call it before the first JAX computation (compiling then holds "
            "about twice the memory)",
            stacklevel=2,
        )
        return False
    os.environ["XLA_FLAGS"] = " ".join([current, *missing]).strip()
    return not unknown

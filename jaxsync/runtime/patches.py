"""The one place where jaxsync changes its dependencies' private internals.

Each patch is a workaround for one measured problem (``docs/performance.md``
names them), guarded by the version it was written and tested against: on any
other version it changes nothing, warns once, and returns False, so a new
release can never be patched blindly. Nothing here runs at import; the
functions that need a patch call it.

- :func:`mjx_elliptic_gradient`: finite reverse-mode gradients through MJX's
  elliptic-cone solver (the unrolled solver's gradients need it);
- :func:`mujoco_deferred_gl` and :func:`mujoco_gl_context`: ``import mujoco``
  that a ``MUJOCO_GL`` which cannot load does not break, its OpenGL backend
  loaded by the first ``mujoco.Renderer`` (``jaxsync.runtime.gl``);
- :func:`stable_lowering`: a program's persistent-cache key that does not
  depend on what the process traced before it;
- :func:`clear_compiled_executables`: JAX's compiled programs dropped, its
  traces kept (the test suite's memory between modules).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import sys
import types
import warnings

import jax
import jax.numpy as jnp

# No ``import mujoco`` here: jaxsync.runtime.gl imports this module before
# mujoco, which mujoco_deferred_gl imports with its OpenGL backend deferred.

MJX_VERSION = "3.17.0"
"""The MuJoCo and MJX release the MuJoCo patches were written for (pyproject.toml pins it)."""
JAX_VERSIONS = ("0.10.",)
"""The JAX releases (prefixes) the JAX patches were written for."""

_warned: set[str] = set()


def _mujoco_version() -> str:
    return importlib.metadata.version("mujoco")


def _supported(name: str, have: str, want: tuple[str, ...]) -> bool:
    if any(have.startswith(w) for w in want):
        return True
    if name not in _warned:
        _warned.add(name)
        warnings.warn(
            f"jaxsync: {name} is written for {' or '.join(want)}, found {have}; left unpatched",
            RuntimeWarning,
            stacklevel=3,
        )
    return False


# ------------------------------------------------------------ MJX: elliptic cone


@jax.custom_jvp
def sqrt_zero_safe(x: jax.Array) -> jax.Array:
    """sqrt with derivative 0 at x <= 0 instead of inf (same values)."""
    return jnp.sqrt(x)


@sqrt_zero_safe.defjvp
def _sqrt_zero_safe_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    y = jnp.sqrt(x)
    pos = x > 0
    return y, jnp.where(pos, dx / (2.0 * jnp.where(pos, y, 1.0)), 0.0)


class _JnpSafeSqrt(types.ModuleType):
    """jax.numpy with :func:`sqrt_zero_safe` as ``sqrt``."""

    sqrt = staticmethod(sqrt_zero_safe)

    def __getattr__(self, name):
        return getattr(jnp, name)


def mjx_elliptic_gradient() -> bool:
    """Make reverse-mode gradients through MJX's elliptic-cone solver finite.

    MJX 3.17's Newton line search takes ``t = jp.sqrt(tsqr)`` of each
    contact's tangential force and only then guards ``t == 0``; a contact
    with no tangential force (every contact that is not touching: MJX keeps
    their rows, zeroed) has ``tsqr = 0``, the derivative of sqrt there is
    inf, and inf * 0 made every gradient NaN (measured: the tuning loss's
    gradient on the elliptic cone, NaN without this, finite with it and equal
    to central differences, tests/test_tune.py). Values are unchanged; only
    the derivative at 0 becomes 0. Applied to ``mujoco.mjx._src.solver``
    (whose ``sqrt`` calls are all in the solver's cost and line search).
    Called by :func:`jaxsync.load_model`. Only the unrolled solver needs it:
    the implicit adjoint (``jaxsync.physics.step.solve_implicit``) never
    differentiates the line search. Returns whether the patch is in place.
    """
    if not _supported("the MJX elliptic-cone patch", _mujoco_version(), (MJX_VERSION,)):
        return False
    from mujoco.mjx._src import solver  # private: imported only on the MJX version it was written for

    if not isinstance(solver.jp, _JnpSafeSqrt):
        solver.jp = _JnpSafeSqrt("jax.numpy with a zero-safe sqrt (jaxsync)")
    return True


# ------------------------------------------------------- MuJoCo: OpenGL context

_GL_CONTEXT = "mujoco.rendering.classic.gl_context"  # private: where MuJoCo keeps its GLContext
MUJOCO_GL_OFF = ("disable", "disabled", "off", "false", "0")
"""``MUJOCO_GL`` values that turn MuJoCo's rendering off (as its ``gl_context`` reads them)."""


def mujoco_deferred_gl(stand_in: type) -> bool:
    """``import mujoco`` without loading the OpenGL backend ``MUJOCO_GL`` names.

    MuJoCo 3.17 loads that backend when ``mujoco`` is first imported (its
    private ``mujoco.rendering.classic.gl_context``), so a backend that is not
    installed, or a name MuJoCo does not know, makes ``import mujoco`` itself
    fail. Here mujoco is imported with rendering off, ``MUJOCO_GL`` is put
    back and recorded in ``gl_context`` as the value it was loaded with, and,
    unless that value turns rendering off, ``stand_in`` becomes the
    ``GLContext`` every ``mujoco.Renderer`` creates (and ``mujoco.GLContext``):
    a class whose first instance loads the backend (``jaxsync.runtime.gl``).
    Called by ``jaxsync.runtime.gl.import_mujoco``. If mujoco is already
    imported, nothing changes. Returns whether mujoco was imported this way;
    on another MuJoCo version it is imported as it is.
    """
    if "mujoco" in sys.modules:
        return False
    if not _supported("the MuJoCo deferred-OpenGL patch", _mujoco_version(), (MJX_VERSION,)):
        importlib.import_module("mujoco")
        return False
    requested = os.environ.get("MUJOCO_GL")
    os.environ["MUJOCO_GL"] = "disable"
    try:
        importlib.import_module("mujoco")
    finally:
        if requested is None:
            del os.environ["MUJOCO_GL"]
        else:
            os.environ["MUJOCO_GL"] = requested
    value = (requested or "").strip().lower()
    mujoco_gl_context(stand_in if value not in MUJOCO_GL_OFF else None, mujoco_gl=value)
    return True


def mujoco_gl_context(context: type | None = None, mujoco_gl: str | None = None) -> bool:
    """Set what MuJoCo's renderer reads from its private ``gl_context``:
    ``context``, where given, becomes the ``GLContext`` every
    ``mujoco.Renderer`` creates (and ``mujoco.GLContext``); ``mujoco_gl``,
    where given, is recorded as the ``MUJOCO_GL`` it was loaded with. Returns
    whether they were set (mujoco imported, on the version this was written for).
    """
    if "mujoco" not in sys.modules or not _supported(
        "the MuJoCo OpenGL-context patch", _mujoco_version(), (MJX_VERSION,)
    ):
        return False
    gl_context = importlib.import_module(_GL_CONTEXT)
    if mujoco_gl is not None:
        gl_context._MUJOCO_GL = mujoco_gl
    if context is not None:
        gl_context.GLContext = context
        sys.modules["mujoco"].GLContext = context
    return True


def mujoco_gl_loaded() -> tuple[type | None, str | None]:
    """The ``GLContext`` class MuJoCo's renderer creates and the ``MUJOCO_GL``
    recorded as loaded (None where absent, or mujoco not imported)."""
    if "mujoco" not in sys.modules:
        return None, None
    gl_context = importlib.import_module(_GL_CONTEXT)
    return getattr(gl_context, "GLContext", None), getattr(gl_context, "_MUJOCO_GL", None)


# ------------------------------------------------- JAX: cache keys, compiled code

_DCE_CACHES = (
    ("jax._src.pjit", "_dce_jaxpr_pjit"),
    ("jax._src.interpreters.partial_eval", "_dce_jaxpr"),
    ("jax._src.interpreters.partial_eval", "_cached_closed_call_dce"),
)
_stable = False


def stable_lowering() -> bool:
    """Make a program's lowered form, and so its persistent-cache key, not
    depend on what the process traced before it.

    JAX memoises dead-code elimination of inner jaxprs in caches of 2048
    entries. Tracing a gradient of this model fills them (one trace of the
    tuner's gradient: 2048 of 2048), so a program lowered afterwards gets
    fresh copies of inner functions that it would otherwise share, e.g. a
    second ``remainder`` inside ``jnp.take``: the same program, a different
    module, a cache miss. A cold test suite (it traces the tuner's gradient)
    and the warm one after it (it reads that traced gradient from disk) keyed
    six programs differently, which the warm run compiled again; a cold and a
    warm ``jaxsync tune`` differ the same way. Here each of those caches gets
    an unbounded memo in front of it (entries still go when their jaxpr does:
    weak keys), so equal inputs give the same object for the whole process.
    Called by ``jaxsync.enable_compilation_cache``; returns whether it is on.
    """
    global _stable
    if _stable:
        return True
    if not _supported("stable_lowering", jax.__version__, JAX_VERSIONS):
        return False
    from jax._src import util  # private: imported only on the JAX versions it was written for

    try:
        targets = [(importlib.import_module(m), name) for m, name in _DCE_CACHES]
        inners = [getattr(mod, name) for mod, name in targets]
    except (ImportError, AttributeError):
        return False
    for (mod, name), inner in zip(targets, inners, strict=True):
        setattr(mod, name, util.weakref_lru_cache(_forwarding(inner), maxsize=None))
    _stable = True
    return True


def _forwarding(inner):
    def call(*args, **kwargs):
        return inner(*args, **kwargs)

    return call


def clear_compiled_executables() -> bool:
    """``jax.clear_caches()`` less the traces: the compiled executables and
    lowered modules go, the traced jaxprs stay, so that the MJX physics traced
    once (``jaxsync.physics.step``'s jitted stages) is not traced again by the
    next program (4-5 s each time). Returns whether anything was cleared."""
    if not _supported("clear_compiled_executables", jax.__version__, JAX_VERSIONS):
        return False
    # private: imported only on the JAX versions they were written for
    from jax._src import pjit
    from jax._src.interpreters import pxla
    from jax._src.lib import _jax

    pxla._cached_compilation.cache_clear()
    pxla._cached_lowering_to_hlo.cache_clear()
    pjit._pjit_lower.cache_clear()
    pjit._cpp_pjit_cache_fun_only.clear()
    pjit._cpp_pjit_cache_explicit_attributes.clear()
    _jax.PjitFunctionCache.clear_all()
    return True

"""An OpenGL backend for offscreen rendering (headless: EGL or OSMesa).

MuJoCo's ``mujoco.Renderer`` needs an OpenGL context. On a machine without a
GPU or a display, that is EGL (Mesa's software renderer, llvmpipe) or OSMesa.
MuJoCo loads the backend named by the ``MUJOCO_GL`` environment variable when
``mujoco`` is first imported, and a backend that is not installed (or a name
it does not know) makes ``import mujoco`` itself fail. ``import jaxsync``
therefore imports ``mujoco`` through :func:`import_mujoco`, which defers the
OpenGL part to the first ``Renderer``: only rendering needs OpenGL (a
workaround that changes MuJoCo's private internals, so it lives in
``jaxsync.runtime.patches``).
:func:`select_gl_backend` chooses a backend that works (probing each in a
subprocess, so a failing backend cannot break this process) and activates it
for the next ``Renderer``. See docs/rendering.md.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys

from jaxsync._errors import JaxsyncError
from jaxsync.runtime import patches

# Tried in this order when MUJOCO_GL is not set: both work without a display.
GL_BACKENDS = ("egl", "osmesa")

# Debian packages that provide each backend (MuJoCo loads them through PyOpenGL).
SYSTEM_PACKAGES = {
    "egl": ("libegl1", "libegl-mesa0", "libgl1-mesa-dri", "libopengl0"),
    "osmesa": ("libosmesa6",),
}


class RenderUnavailableError(JaxsyncError):
    """No OpenGL backend for offscreen rendering works on this machine."""


# The mujoco module that holds each backend's GLContext.
_BACKEND_MODULES = {"egl": "mujoco.egl", "osmesa": "mujoco.osmesa", "glfw": "mujoco.glfw"}


def _backend_module(value: str) -> str:
    """The mujoco module whose GLContext MUJOCO_GL=value uses on Linux (as
    mujoco.rendering.classic.gl_context picks it)."""
    value = value.strip().lower()
    if value in _BACKEND_MODULES:
        return _BACKEND_MODULES[value]
    if value in ("", "enable", "enabled", "on", "true", "1", "glx"):
        return "mujoco.glfw"
    raise RenderUnavailableError(
        f"MUJOCO_GL={value} is not an OpenGL backend MuJoCo knows: unset it to let jaxsync try "
        f"{' and '.join(GL_BACKENDS)}, or set MUJOCO_GL=egl (on Debian/Ubuntu: apt-get install -y "
        f"{' '.join(SYSTEM_PACKAGES['egl'])}) or MUJOCO_GL=osmesa (apt-get install -y "
        f"{' '.join(SYSTEM_PACKAGES['osmesa'])})"
    )


class _DeferredGLContext:
    """Stands in for mujoco's GLContext until the first ``mujoco.Renderer``:
    then loads the backend ``MUJOCO_GL`` names (as ``import mujoco`` would have)
    and puts its GLContext in place."""

    def __new__(cls, *args, **kwargs):
        real = importlib.import_module(_backend_module(os.environ.get("MUJOCO_GL", ""))).GLContext
        patches.mujoco_gl_context(real)
        return real(*args, **kwargs)


def import_mujoco():
    """``import mujoco`` without loading OpenGL: whatever ``MUJOCO_GL`` says
    (a backend that is not installed, a name MuJoCo does not know), the import
    works, and the backend is loaded by the first ``mujoco.Renderer``
    (:class:`_DeferredGLContext`). If ``mujoco`` is already imported, nothing
    changes (``jaxsync.runtime.patches.mujoco_deferred_gl``). Returns the module."""
    patches.mujoco_deferred_gl(_DeferredGLContext)
    return sys.modules["mujoco"]


_selected_backend: str | None = None
_failure: tuple[str, str] | None = None  # (MUJOCO_GL at the time, message): not probed twice

_PROBE = """
import mujoco
m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size="0.1"/></worldbody></mujoco>')
d = mujoco.MjData(m)
mujoco.mj_forward(m, d)
r = mujoco.Renderer(m, 8, 8)
r.update_scene(d)
img = r.render()
r.close()
assert img.shape == (8, 8, 3), img.shape
print("ok")
"""


def _probe_backend(backend: str, timeout: float = 120.0) -> tuple[bool, str]:
    """Render one tiny frame with MUJOCO_GL=backend in a fresh interpreter."""
    env = dict(os.environ)
    env["MUJOCO_GL"] = backend
    env.pop("PYOPENGL_PLATFORM", None)
    if backend in ("egl", "osmesa"):
        env["PYOPENGL_PLATFORM"] = backend
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            close_fds=False,  # lets Python use posix_spawn instead of fork (JAX warns on fork)
        )
    except (OSError, subprocess.TimeoutExpired) as err:
        return False, f"{type(err).__name__}: {err}"
    if proc.returncode == 0 and proc.stdout.strip().endswith("ok"):
        return True, ""
    lines = [ln for ln in (proc.stderr or proc.stdout).strip().splitlines() if ln.strip()]
    return False, lines[-1] if lines else f"exit code {proc.returncode}"


def _activate(backend: str) -> None:
    """Make this process's next mujoco.Renderer use ``backend``."""
    os.environ["MUJOCO_GL"] = backend
    if "mujoco" not in sys.modules:
        return  # mujoco reads MUJOCO_GL when it is imported
    context, loaded = patches.mujoco_gl_loaded()
    if context is _DeferredGLContext:
        patches.mujoco_gl_context(mujoco_gl=backend)
        return  # the first Renderer loads it (import_mujoco)
    if loaded == backend:
        return  # mujoco was imported with this backend already
    if backend not in GL_BACKENDS:
        raise RenderUnavailableError(
            f"mujoco was imported before MUJOCO_GL={backend} was set; set it before starting Python"
        )
    platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    if "OpenGL" in sys.modules and platform != backend:
        raise RenderUnavailableError(
            f"PyOpenGL was already imported for platform {platform or 'default'!r}, so the {backend} "
            f"backend cannot be switched to; run with MUJOCO_GL={backend} set before starting Python"
        )
    try:
        module = importlib.import_module(f"mujoco.{backend}")
    except ImportError as err:
        raise RenderUnavailableError(f"cannot switch mujoco to MUJOCO_GL={backend}: {err}") from None
    patches.mujoco_gl_context(module.GLContext)


def select_gl_backend() -> str:
    """Choose a working OpenGL backend for offscreen rendering and activate it.

    Respects an existing ``MUJOCO_GL`` (checked, not replaced); otherwise tries
    ``egl`` then ``osmesa``, each by rendering a tiny frame in a subprocess.
    The choice is cached for the process. Call it before rendering; the
    rendering functions here call it themselves.

    Returns:
      The backend name, as put in ``os.environ["MUJOCO_GL"]``.

    Raises:
      RenderUnavailableError: no backend works; the message names what was
        tried, why each failed, and the Debian packages to install.
    """
    global _selected_backend, _failure
    if _selected_backend is not None:
        return _selected_backend
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    if _failure is not None and _failure[0] == requested:
        raise RenderUnavailableError(_failure[1])
    if requested and requested not in GL_BACKENDS:
        _backend_module(requested)  # a name MuJoCo does not know: say so, with what to set
    candidates = (requested,) if requested else GL_BACKENDS
    failures = []
    for backend in candidates:
        ok, why = _probe_backend(backend)
        if ok:
            _activate(backend)
            _selected_backend = backend
            return backend
        failures.append(f"MUJOCO_GL={backend}: {why}")
    packages = " ".join(SYSTEM_PACKAGES.get(requested) or [p for b in GL_BACKENDS for p in SYSTEM_PACKAGES[b]])
    hint = f"unset MUJOCO_GL to let jaxsync try {' and '.join(GL_BACKENDS)}, or " if requested else ""
    message = (
        "no OpenGL backend for offscreen rendering works here (tried "
        + "; ".join(failures)
        + f"). {hint}install the system libraries, e.g. on Debian/Ubuntu: "
        f"apt-get install -y {packages}"
    )
    _failure = (requested, message)
    raise RenderUnavailableError(message)

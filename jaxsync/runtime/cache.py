"""JAX's persistent compilation cache, and traced functions kept on disk.

Not called at import (no side effects on import); entry points call it.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata as md
import os

import jax
from jax import export

from jaxsync._errors import ConfigError
from jaxsync.runtime import patches, programs
from jaxsync.runtime.files import atomic_write_bytes

ENV_VAR = "JAXSYNC_CACHE_DIR"


def default_cache_dir() -> str:
    base = os.environ.get("XDG_CACHE_HOME", os.path.join(os.path.expanduser("~"), ".cache"))
    return os.path.join(base, "jaxsync", "xla")


_MIN_COMPILE_TIME_S = 0.5
_chosen_min_compile_time_s: float | None = None  # what a caller of this process asked for


def enable_compilation_cache(path: str | None = None, min_compile_time_s: float | None = None) -> str | None:
    """Point JAX's persistent compilation cache at ``path``.

    A rollout of this model compiles for tens of seconds, its gradient for
    minutes; with the cache a later process (a script run again, the CLI, the
    tests) reads the compiled program back instead. Call it once, before the
    first compile. ``path`` defaults to ``$JAXSYNC_CACHE_DIR`` or
    ``~/.cache/jaxsync/xla``; the string ``"off"`` disables it. Programs that
    compile in less than ``min_compile_time_s`` are not kept (0 keeps every
    one, also the hundreds of small programs of eager operations, each 20-100
    ms to compile and a few ms to read back: the test suite does that). When
    not given: what an earlier call in this process chose, else 0.5 s (so a
    command run in-process, ``jaxsync.cli.main([...])``, keeps its caller's
    choice).
    Returns the directory used, or None.

    Example:
      >>> import jaxsync
      >>> jaxsync.enable_compilation_cache()  # doctest: +SKIP
      '/home/me/.cache/jaxsync/xla'
    """
    path = path or os.environ.get(ENV_VAR) or default_cache_dir()
    if path == "off":
        return None
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"compilation cache folder {path}: cannot create it: {err.strerror or err}") from None
    if not os.access(path, os.W_OK):
        raise ConfigError(f"compilation cache folder {path}: not writable (--cache-dir, $JAXSYNC_CACHE_DIR or 'off')")
    jax.config.update("jax_compilation_cache_dir", path)
    global _chosen_min_compile_time_s
    if min_compile_time_s is None:
        min_compile_time_s = _MIN_COMPILE_TIME_S if _chosen_min_compile_time_s is None else _chosen_min_compile_time_s
    elif not min_compile_time_s >= 0:
        raise ConfigError(f"min_compile_time_s must be a number of seconds >= 0, got {min_compile_time_s!r}")
    else:
        _chosen_min_compile_time_s = float(min_compile_time_s)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    patches.stable_lowering()
    return path


# ------------------------------------------------------------- compiling, measured


_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"  # a compile, or a read from the cache
_RETRIEVAL_EVENT = "/jax/compilation_cache/cache_retrieval_time_sec"  # a read from the cache


class CompileWatch:
    """What JAX compiled inside a ``with compile_watch() as w:`` block:
    ``w.compile_s`` seconds of XLA compiling of programs that take at least
    0.5 s (or the persistent cache's minimum compile time, if higher) to
    compile: the many small programs of eager operations are left out, also
    when the cache keeps them (``min_compile_time_s=0``), and ``w.cache_hits``
    programs read back from that cache."""

    def __init__(self):
        self.compile_s = 0.0
        self.cache_hits = 0
        self._read_s = 0.0  # the cache read inside the compile event that follows it
        self._min_s = max(float(jax.config.jax_persistent_cache_min_compile_time_secs), _MIN_COMPILE_TIME_S)

    def _on_duration(self, event, seconds, **_):
        if event == _RETRIEVAL_EVENT:
            self.cache_hits += 1
            self._read_s += seconds
        elif event == _COMPILE_EVENT:
            compiling = seconds - self._read_s
            self._read_s = 0.0
            if compiling >= self._min_s:
                self.compile_s += compiling

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self._on_duration)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._on_duration)
        return False

    def describe(self) -> str:
        """' (12.3 s of it compiling)', ' (compiled program read from the cache)' or ''."""
        if self.compile_s:
            cached = jax.config.jax_compilation_cache_dir
            return f" ({self.compile_s:.1f} s of it compiling" + (
                "; the compilation cache keeps it for later runs)" if cached else ")"
            )
        if self.cache_hits:
            return " (compiled program read from the compilation cache)"
        return ""


def compile_watch() -> CompileWatch:
    """Measure compiling in a block: ``with compile_watch() as w: ...; w.compile_s``."""
    return CompileWatch()


# ------------------------------------------------------------- traced functions


# The packages whose code a traced function can run: the library, the tuning
# code (cost and loss) and the models. In a checkout or an editable install
# jaxsync.optimize and jaxsync.mjcf live outside jaxsync/, so each is found
# from its own import location, wherever it was installed from.
SOURCE_PACKAGES = ("jaxsync", "jaxsync.optimize", "jaxsync.mjcf")


def source_files() -> list[str]:
    """Every source file (``.py``, ``.xml``) of :data:`SOURCE_PACKAGES`, sorted."""
    files = set()
    for name in SOURCE_PACKAGES:
        for root in importlib.import_module(name).__path__:
            for dirpath, _, names in os.walk(root):
                files.update(os.path.join(dirpath, f) for f in names if f.endswith((".py", ".xml")))
    return sorted(os.path.realpath(f) for f in files)


def _source_fingerprint(files: list[str] | None = None) -> str:
    """Hash of jaxsync's source files (the library, ``jaxsync.optimize`` and the
    packaged models, :func:`source_files`) and of the versions it traces
    against: a traced function kept on disk is valid only for exactly this
    code. A model file outside the package is hashed by its caller's key."""
    h = hashlib.sha256()
    for path in source_files() if files is None else files:
        with open(path, "rb") as f:
            h.update(path.encode() + b"\0" + f.read())
    for dist in ("jax", "jaxlib", "mujoco", "mujoco-mjx"):
        try:
            h.update(f"{dist}={md.version(dist)}".encode())
        except md.PackageNotFoundError:
            h.update(dist.encode())
    return h.hexdigest()


def _named_tuple_types(tree, found: set) -> set:
    """The NamedTuple classes (``Gains``, ``Scenario``, ...) inside ``tree``."""
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):
        found.add(type(tree))
    if isinstance(tree, (tuple, list)):
        for x in tree:
            _named_tuple_types(x, found)
    elif isinstance(tree, dict):
        for x in tree.values():
            _named_tuple_types(x, found)
    return found


def _register_export_types(args) -> None:
    """Let ``jax.export`` serialise the NamedTuples among ``args``."""
    for cls in sorted(_named_tuple_types(args, set()), key=lambda c: c.__name__):
        try:
            export.register_namedtuple_serialization(cls, serialized_name=f"jaxsync.{cls.__name__}")
        except ValueError:
            pass  # already registered


def _one_placement(jitted):
    """``jitted`` called with every argument committed to the first device.

    A jitted function compiles once per argument placement: arrays fresh from
    a jitted computation are uncommitted, arrays that went through
    ``device_put`` (an optax update, a checkpoint) are committed, and the two
    lower to different programs (measured: a cold ``jaxsync tune`` compiled
    its gradient a second time at its second iteration, 79 s). Committing
    every argument first gives one program.
    """
    device = jax.local_devices()[0]

    def call(*args):
        return jitted(*jax.device_put(args, device))

    call.lower = lambda *args: jitted.lower(*jax.device_put(args, device))
    return call


# The traced functions this process has loaded (or exported), newest last, by
# their file: a second ``traced_on_disk`` of the same function (a second
# ``tune()`` call in one session) gets the same jitted callable back, whose
# compiled program is already in memory. Reading a full-task gradient's
# compiled program back from the persistent cache takes 6-8 s on 2 cores.
_LOADED: dict = {}
_LOADED_MAX = 4


def traced_on_disk(fn, args: tuple, key: str, log=None, cache_dir: str | None = None):
    """``jax.jit(fn)``, with its traced and lowered form kept on disk (``jax.export``).

    Tracing and differentiating a rollout of this model costs about 15 s of
    Python each time a process starts, which the persistent XLA cache cannot
    save (docs/performance.md). The exported form is stored next to that cache,
    under a hash of ``key``, the argument shapes, jaxsync's source files and the
    JAX and MuJoCo versions; a later process deserialises it instead of tracing
    (and the XLA compile then hits the persistent cache). Without a persistent
    cache, without the ``flatbuffers`` package, or if exporting fails, this is
    plain ``jax.jit(fn)``. ``cache_dir`` overrides the folder.
    """
    raw = jax.jit(fn)
    jitted = _one_placement(raw)
    cache = cache_dir or jax.config.jax_compilation_cache_dir
    if not cache:
        return jitted
    try:  # jax.export serialises with flatbuffers: without it, plain jit
        import flatbuffers  # noqa: F401
    except ImportError:
        return jitted
    avals = jax.tree_util.tree_map(lambda x: (jax.numpy.shape(x), str(jax.numpy.result_type(x))), args)
    digest = hashlib.sha256(f"{key}|{avals}|{jax.tree_util.tree_structure(args)}|{_source_fingerprint()}".encode())
    path = os.path.join(cache, f"jaxsync-export-{digest.hexdigest()[:32]}.bin")
    if path in _LOADED:  # this process has it already: no deserialising, no reading the executable again
        _LOADED[path] = _LOADED.pop(path)
        return _LOADED[path]
    try:
        _register_export_types(args)
        if os.path.exists(path):
            with open(path, "rb") as f:
                exp = export.deserialize(bytearray(f.read()))
        else:
            exp = export.export(raw)(*args)
            atomic_write_bytes(path, exp.serialize())
        loaded = _one_placement(jax.jit(exp.call))
    except Exception as err:  # noqa: BLE001  (an optimisation only: fall back to tracing)
        if log is not None:
            log(f"(not keeping the traced function on disk: {type(err).__name__}: {err})")
        return jitted
    _LOADED[path] = loaded
    while len(_LOADED) > _LOADED_MAX:
        _LOADED.pop(next(iter(_LOADED)))
    return loaded


@programs.on_clear
def forget_loaded() -> None:
    """Drop the traced functions held by :func:`traced_on_disk` (their compiled
    programs go with them once nothing else holds them)."""
    _LOADED.clear()

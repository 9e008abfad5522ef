"""Tuning checkpoints: the loop's state on disk, as data only.

A checkpoint is one ``.npz`` file (numpy's zip of arrays, read with
``allow_pickle=False``): the arrays, and a JSON document holding everything
else (history rows, validation entries, counters, the options fingerprint),
in which each array is a reference ``{"$array": "a0"}``. Nothing in it is
code, so reading a checkpoint cannot run any: a file that is not such a
document is refused. Writes are atomic (a temporary file, then a rename).

JSON keeps what the loop's records are: ints stay ints, floats floats (also
NaN and inf), tuples tuples (``{"$tuple": [...]}``) and dicts with integer keys
(``{"$dict": [[key, value], ...]}``), so a resumed run's records equal an
uninterrupted run's.
"""

from __future__ import annotations

import io
import json
import zipfile

import jax
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.io import results as _results

FORMAT = "jaxsync-checkpoint-1"
DOCUMENT = "__document__"


def _encode(x, arrays: dict):
    if isinstance(x, np.generic):  # a numpy scalar: the Python number it holds
        x = x.item()
    if isinstance(x, (np.ndarray, jax.Array)):
        key = f"a{len(arrays)}"
        arrays[key] = np.asarray(x)
        return {"$array": key}
    if x is None or isinstance(x, (bool, int, float, str)):
        return x
    if isinstance(x, tuple) and not hasattr(x, "_fields"):
        return {"$tuple": [_encode(v, arrays) for v in x]}
    if isinstance(x, list):
        return [_encode(v, arrays) for v in x]
    if isinstance(x, dict):
        if all(isinstance(k, str) and not k.startswith("$") for k in x):
            return {k: _encode(v, arrays) for k, v in x.items()}
        return {"$dict": [[_encode(k, arrays), _encode(v, arrays)] for k, v in x.items()]}
    raise TypeError(f"a checkpoint holds data only (arrays, numbers, strings, lists, dicts), got {type(x).__name__}")


def _decode(x, arrays):
    if isinstance(x, list):
        return [_decode(v, arrays) for v in x]
    if isinstance(x, dict):
        if set(x) == {"$array"}:
            return arrays[x["$array"]]
        if set(x) == {"$tuple"}:
            return tuple(_decode(v, arrays) for v in x["$tuple"])
        if set(x) == {"$dict"}:
            return {_decode(k, arrays): _decode(v, arrays) for k, v in x["$dict"]}
        return {k: _decode(v, arrays) for k, v in x.items()}
    return x


def save(path: str, state: dict) -> None:
    """Write ``state`` (nested dicts, lists, tuples, numbers, strings and arrays)."""
    arrays: dict = {}
    doc = json.dumps({"format": FORMAT, "state": _encode(state, arrays)})
    buf = io.BytesIO()
    np.savez(buf, **arrays, **{DOCUMENT: np.frombuffer(doc.encode(), dtype=np.uint8)})
    _results.atomic_write_bytes(path, buf.getvalue())


def load(path: str) -> dict:
    """Read what :func:`save` wrote; anything else is a ConfigError naming the file."""
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except FileNotFoundError:
        raise ConfigError(f"no checkpoint at {path} to resume from", inputs=("resume",)) from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise ConfigError(
            f"{path} is not a jaxsync checkpoint (a numpy .npz of data; it is never unpickled): {err}"
        ) from None
    try:
        doc = json.loads(bytes(arrays.pop(DOCUMENT)).decode())
        if doc.get("format") != FORMAT:
            raise ValueError(f"format {doc.get('format')!r}, expected {FORMAT!r}")
        return _decode(doc["state"], arrays)
    except (KeyError, ValueError, TypeError, AttributeError) as err:
        raise ConfigError(f"{path} is not a jaxsync checkpoint: {err}", inputs=("resume",)) from None

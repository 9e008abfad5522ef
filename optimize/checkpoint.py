"""Tuning checkpoints: the loop's state on disk, written atomically (pickle of numpy leaves)."""

from __future__ import annotations

import pickle

import jax
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.io import results as _results

# the fields holding JAX arrays; the rest (history rows, validation entries,
# counters, the options fingerprint) are plain Python and are pickled as they
# are, so that a resumed run's records equal an uninterrupted run's (turning
# them into numpy scalars made a resumed run crash at its end: a 0-d array
# iteration is not a dict key)
ARRAY_FIELDS = ("theta", "opt_state", "kept")


def save(path: str, state: dict) -> None:
    state = {k: jax.tree_util.tree_map(np.asarray, v) if k in ARRAY_FIELDS else v for k, v in state.items()}
    _results.atomic_write_bytes(path, pickle.dumps(state))


def load(path: str) -> dict:
    try:
        with open(path, "rb") as f:
            return pickle.load(f)
    except FileNotFoundError:
        raise ConfigError(f"--resume: no checkpoint at {path}") from None
    except (OSError, pickle.UnpicklingError, EOFError) as err:
        raise ConfigError(f"--resume: cannot read checkpoint {path}: {err}") from None

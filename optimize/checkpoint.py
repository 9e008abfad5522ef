"""Tuning checkpoints: the loop's state on disk, written atomically (pickle of numpy leaves)."""

from __future__ import annotations

import pickle

import jax
import numpy as np

from jaxsync import _io
from jaxsync._errors import ConfigError


def save(path: str, state: dict) -> None:
    _io.atomic_write_bytes(path, pickle.dumps(jax.tree_util.tree_map(np.asarray, state)))


def load(path: str) -> dict:
    try:
        with open(path, "rb") as f:
            return pickle.load(f)
    except FileNotFoundError:
        raise ConfigError(f"--resume: no checkpoint at {path}") from None
    except (OSError, pickle.UnpicklingError, EOFError) as err:
        raise ConfigError(f"--resume: cannot read checkpoint {path}: {err}") from None

"""Argument types shared by the commands."""

from __future__ import annotations

import argparse


def positive(kind):
    """An argparse type: ``kind(text)``, which must be > 0."""

    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        if v == float("inf"):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        return v

    return parse


def add_model_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default=None, help="MJCF file (default: the packaged paper model)")

"""argparse ``type=`` functions for the numeric options of the ``floxels`` commands.

Plain ``type=float`` accepts ``nan`` and ``inf``, which then slip past range checks written
as ``if x < 0`` (a NaN compares false) and turn up as a traceback, NaN in a JSON file or a
silently ignored option (issue 30). These refuse them when the command line is parsed:
``floxels: error: argument --radius: must be a finite number > 0, got 'nan'`` (exit 2)."""

from __future__ import annotations

import argparse
import math

__all__ = ["finite_float", "positive_float", "nonnegative_float", "nonnegative_int", "positive_int"]


def _number(text: str, kind=float):
    try:
        v = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                         f"got {text!r}") from None
    if kind is float and not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return v


def finite_float(text: str) -> float:
    return _number(text)


def positive_float(text: str) -> float:
    v = _number(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return v


def nonnegative_float(text: str) -> float:
    v = _number(text)
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return v


def nonnegative_int(text: str) -> int:
    v = _number(text, int)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return v


def positive_int(text: str) -> int:
    v = _number(text, int)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return v

"""argparse value types shared by the ``confnav`` command line and the service processes' own
parsers (``type=``): a mistake is one line at parse time, before any long work."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def positive_float(text: str) -> float:
    """An argparse ``type=``: a finite number > 0 (gains, speeds, tolerances, times)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (0.0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return value


def positive_int(text: str) -> int:
    """An argparse ``type=``: an integer >= 1 (counts)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be at least 1")
    return value


def output_path(text: str) -> Path:
    """An argparse ``type=`` for files a command writes: the directory must exist, checked at
    parse time so a mistake costs one line, not the whole computation."""
    parent = os.path.dirname(os.path.abspath(text))
    if not os.path.isdir(parent):
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: no directory {parent!r}")
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: it is a directory")
    if not os.access(parent, os.W_OK):
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: {parent!r} is not writable")
    return Path(text)


__all__ = ["output_path", "positive_float", "positive_int"]

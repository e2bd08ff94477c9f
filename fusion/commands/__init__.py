"""One module per ``visuotactile`` subcommand; each defines ``register(subparsers)`` (see :mod:`fusion.cli`)."""

from __future__ import annotations

import json
import sys


def print_json(result) -> None:
    """A ``--json`` result: one JSON document on stdout (logs and progress go to stderr)."""
    # strict JSON (no NaN or Infinity), made whole before writing: a refusal prints nothing, not half a document
    sys.stdout.write(json.dumps(result, indent=2, default=str, allow_nan=False) + "\n")


def positive_int(text: str) -> int:
    """An argparse ``type`` for counts: a positive integer, else argparse's one-line error naming the option."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text[:40]!r}")
    return value


def positive_seconds(text: str) -> float:
    """An argparse ``type`` for durations: a finite number of seconds above 0, else argparse's one-line error."""
    import argparse

    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds above 0, got {text[:40]!r}")
    return value

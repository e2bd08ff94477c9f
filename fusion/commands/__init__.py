"""One module per ``visuotactile`` subcommand; each defines ``register(subparsers)`` (see :mod:`fusion.cli`)."""

from __future__ import annotations

import json
import sys


def print_json(result) -> None:
    """A ``--json`` result: one JSON document on stdout (logs and progress go to stderr)."""
    json.dump(result, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")


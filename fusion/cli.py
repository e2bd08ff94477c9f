"""The ``visuotactile`` command line.

Each subcommand lives in its own module under :mod:`fusion.commands` and defines
``register(subparsers)``, which adds its parser and sets ``func(args, rest) -> exit code``. This file only
assembles them, gives every subcommand ``--no-progress`` (the one progress switch,
:func:`perception.runtime.set_progress`; ``--json`` turns the bars off too), sets up logging and turns a
:class:`VisuotactileError` into one line on stderr and exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading

from perception.errors import VisuotactileError

log = logging.getLogger(__name__)

#: Subcommand modules, in the order ``--help`` lists them; a missing module is skipped.
COMMANDS = ("demo", "generate", "verify", "train", "evaluate", "reproduce", "recognize", "camera", "bench")


class _Parser(argparse.ArgumentParser):
    """argparse with the toolkit's one-line errors: a bad option prints one line on stderr (not the whole usage,
    which runs to many lines for some subcommands) and exits 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="visuotactile", description="Visually guided tactile object recognition toolkit."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"fusion.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"fusion.commands.{name}":
                raise
            continue
        module.register(sub)
    for command in sub.choices.values():
        command.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


#: Seeds every subcommand takes: what NumPy's legacy seeding and scikit-learn accept (32 bits, unsigned). A
#: subcommand whose seed reaches a narrower generator sets ``seed_max`` (``camera``: Open3D's C int, 31 bits).
SEED_MAX = 2**32 - 1


def check_common(args: argparse.Namespace) -> None:
    """Checks of options several subcommands share, before any work: ``--seed`` (an integer in [0, 2**32 - 1], or
    the subcommand's own ``seed_max``).

    Raises:
        InvalidArgumentError: naming the option, the value and the range.
    """
    from perception.errors import InvalidArgumentError

    seed = getattr(args, "seed", None)
    if seed is None:
        return
    most = getattr(args, "seed_max", SEED_MAX)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= most:
        raise InvalidArgumentError(f"--seed must be a non-negative integer, at most {most} "
                                   f"(2**{most.bit_length()} - 1), got {seed}")


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default: this process's) and return its exit code. While a command runs, SIGTERM
    raises :class:`Terminated` in the main thread, so that it unwinds as on Ctrl-C, and returns 143; the caller's
    own SIGTERM handler is set back before this returns (a library calling ``main`` sees the 143, not the signal)."""
    parser = build_parser()
    try:  # a bad option (one line on stderr) or --help returns its exit code, as every other outcome does
        args, rest = parser.parse_known_args(argv)
        if rest and not getattr(args, "passes_extra_args", False):
            parser.error(f"unrecognized arguments: {' '.join(rest)}")
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 2
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from perception.runtime import set_progress

    set_progress(False if args.no_progress or getattr(args, "json", False) else None)
    handler = _on_sigterm_unwind()
    try:
        check_common(args)
        code = int(args.func(args, rest) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not at exit
        return code
    except VisuotactileError as exc:
        print(f"visuotactile {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of stdout went away (`... | head -2`): say so once; Python must not print it again at exit.
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        print(f"visuotactile {args.command}: error: the output pipe was closed before all output was written",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        # Only commands that resume (set resumable=True) promise it; others say what an interruption loses.
        what = ("finished work is kept, re-run to resume" if getattr(args, "resumable", False)
                else "nothing was saved")
        terminated = isinstance(exc, Terminated)
        print(f"visuotactile {args.command}: {'terminated' if terminated else 'interrupted'}; {what}", file=sys.stderr)
        return 143 if terminated else 130
    finally:
        if handler is not None:  # first: a SIGTERM from here on is the caller's again
            signal.signal(signal.SIGTERM, handler[0] if handler[0] is not None else signal.SIG_DFL)
        set_progress(None)


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a batch scheduler, ``docker stop``) while a command runs: raised in the main
    thread so that the command unwinds as on Ctrl-C (workers stopped, temporary files removed); exit 143."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated(f"signal {signum}")


def _on_sigterm_unwind() -> tuple | None:
    """Make SIGTERM raise :class:`Terminated` in the main thread; returns (the handler to restore,) or None off the
    main thread, where Python sets no handlers."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return (signal.signal(signal.SIGTERM, _raise_terminated),)


if __name__ == "__main__":
    sys.exit(main())

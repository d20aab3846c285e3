"""The ``monotracker`` command line.

Each area contributes its sub-commands from a ``commands`` module exposing
``register(subparsers)``; the handler stored with ``set_defaults(func=...)`` returns an exit
code. Expected failures (:class:`~monotracker.errors.MonoTrackerError`) print one line
``error: ...`` and exit 2; anything unexpected prints one line naming the log file that holds
the traceback and exits 3. The operator never sees a raw traceback.

Arguments are checked where they enter (:mod:`monotracker.cli_args`); on top of that, any float
argument that is NaN or infinite is refused here for every sub-command (exit 2). Output piped
into a reader that stops early (``detect-ct --json | head``) ends quietly: a ``BrokenPipeError``
exits 141 (as a shell reports SIGPIPE) without a message.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
import tempfile
import traceback
from pathlib import Path

from monotracker import __version__
from monotracker.errors import MonoTrackerError

#: Modules that add sub-commands, in the order they appear in ``--help``.
COMMAND_MODULES: tuple[str, ...] = (
    "monotracker.ct.commands",
    "monotracker.planning.commands",
    "monotracker.vision.commands",
    "monotracker.sim.commands",
    "monotracker.robot.commands",
    "monotracker.demo.commands",
    "monotracker.engine.commands",
    "monotracker.ui.commands",
    "monotracker.interop.commands",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="monotracker",
        description="Monocular CT-to-camera registration and UR10 tracking for neurosurgery.",
    )
    parser.add_argument("--version", action="version", version=f"monotracker {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def _log_internal_error() -> str:
    """Append the current traceback to the error log (the data folder's, else the temp folder's)."""
    from monotracker.paths import data_dir

    candidates = []
    try:
        candidates.append(data_dir() / "monotracker-errors.log")
    except OSError:
        pass
    candidates.append(Path(tempfile.gettempdir()) / "monotracker-errors.log")
    for path in candidates:
        try:
            with open(path, "a", encoding="utf-8") as fh:
                fh.write(traceback.format_exc())
                fh.write("\n")
            return str(path)
        except OSError:
            continue
    return "nowhere: no writable log folder"


def _quiet_broken_pipe() -> int:
    """The reader of stdout went away: point stdout at /dev/null so the final flush is silent."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return 141


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from monotracker.cli_args import non_finite_floats

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    bad = non_finite_floats(args)
    if bad:
        print(f"error: --{bad[0].replace('_', '-')} must be a finite number", file=sys.stderr)
        return 2
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        return _quiet_broken_pipe()
    except MonoTrackerError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - last line of defence for the operator
        where = _log_internal_error()
        print(f"internal error: {type(exc).__name__}: {exc} (traceback in {where})", file=sys.stderr)
        return 3

"""The ``monotracker`` command line.

Each area contributes its sub-commands from a ``commands`` module exposing
``register(subparsers)``; the handler stored with ``set_defaults(func=...)`` returns an exit
code. Expected failures (:class:`~monotracker.errors.MonoTrackerError`) print one line
``error: ...`` and exit 2; anything unexpected prints one line naming the log file that holds
the traceback and exits 3. The operator never sees a raw traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback

from monotracker import __version__
from monotracker.errors import MonoTrackerError

#: Modules that add sub-commands, in the order they appear in ``--help``.
COMMAND_MODULES: tuple[str, ...] = (
    "monotracker.ct.commands",
    "monotracker.vision.commands",
    "monotracker.robot.commands",
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
    from monotracker.paths import data_dir

    path = data_dir() / "monotracker-errors.log"
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(traceback.format_exc())
        fh.write("\n")
    return str(path)


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
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

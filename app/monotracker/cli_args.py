"""Argument types for the command line: every value is checked where it enters.

Each function is an ``argparse`` ``type=`` (it returns the parsed value or raises
``argparse.ArgumentTypeError`` with a one-line reason, which argparse prints as
``monotracker <cmd>: error: argument --x: <reason>`` and exits 2). The same checks serve the engine
where it takes the same kind of value (:func:`check_ip` checks the ``ur:`` robot spec of
``robot/backends.py`` for the ``--robot`` flag and ``SessionConfig.validate``), so a flag and a
setting refuse the same things.

:func:`monotracker.cli.main` also refuses any float argument that is NaN or infinite, for every
sub-command, whatever type its parser declared.
"""

from __future__ import annotations

import argparse
import ipaddress
import math
from pathlib import Path


def _ranged(convert, kind: str, lo, hi, lo_open: bool = False):
    """An argparse type: ``convert(text)``, finite, within ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``)."""

    def parse(text: str):
        try:
            x = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {kind}") from None
        if isinstance(x, float) and not math.isfinite(x):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
        if lo is not None and (x <= lo if lo_open else x < lo):
            raise argparse.ArgumentTypeError(f"{text} must be {'>' if lo_open else '>='} {lo:g}")
        if hi is not None and x > hi:
            raise argparse.ArgumentTypeError(f"{text} must be <= {hi:g}")
        return x

    parse.__name__ = kind.split()[-1]
    return parse


def finite_float(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False):
    """A float type: finite, and within ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``)."""
    return _ranged(float, "a number", lo, hi, lo_open)


def int_range(lo: int | None = None, hi: int | None = None):
    """An int type within ``[lo, hi]``."""
    return _ranged(int, "an integer", lo, hi)


def check_ip(text: str) -> str | None:
    """None when ``text`` is an IPv4/IPv6 address (no DNS lookup is made), else a reason."""
    try:
        ipaddress.ip_address(str(text).strip())
    except ValueError:
        return f"{text!r} is not an IP address (e.g. 192.168.1.10; host names are not looked up)"
    return None


def ip_address(text: str) -> str:
    """An IP address type (no DNS)."""
    why = check_ip(text)
    if why:
        raise argparse.ArgumentTypeError(why)
    return str(text).strip()


def home_folder(text: str) -> Path:
    """A session folder: an existing folder, or a path whose nearest existing parent is a folder."""
    p = Path(text).expanduser()
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text} exists and is not a folder")
    parent = p
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {parent} is not a folder")
    return p


def existing_file(text: str) -> Path:
    p = Path(text).expanduser()
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"file not found: {text}")
    return p


def float_list(count: int, what: str = "X,Y,Z"):
    """A type for ``count`` comma-separated finite numbers (``"12.5,-40,88"``) -> tuple of floats."""

    def parse(text: str) -> tuple:
        parts = [t.strip() for t in str(text).split(",")]
        try:
            vals = tuple(float(t) for t in parts)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {count} numbers {what}") from None
        if len(vals) != count:
            raise argparse.ArgumentTypeError(f"{text!r} is not {count} numbers {what}")
        if not all(math.isfinite(v) for v in vals):
            raise argparse.ArgumentTypeError(f"{text!r} holds a number that is not finite")
        return vals

    parse.__name__ = what
    return parse


def non_finite_floats(ns: argparse.Namespace) -> list[str]:
    """Names of float attributes of ``ns`` that are NaN or infinite."""
    return [k for k, v in vars(ns).items() if isinstance(v, float) and not math.isfinite(v)]

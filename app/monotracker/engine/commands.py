"""``monotracker audit verify`` and ``monotracker compile-kernels``.

    monotracker audit verify [HOME]
    monotracker compile-kernels [--side-by-side] [GROUP ...]

Checks the audit log of a session folder (default ``$MONOTRACKER_HOME``, else your
``~/.monotracker``): the protective triggers are present, every row's hash chains to the one
before, and the ``robot_state`` rows follow each other (each goes from the state the one before
went to). Exit 0 when intact, 1 naming the first bad row.

``compile-kernels`` compiles the package's numba kernels into their disk cache ahead of first use
(:mod:`monotracker.engine.kernels`; ``scripts/setup.sh`` runs it after an install with
``--side-by-side``: one process per group, all at once). Exit 0 when done.
"""

from __future__ import annotations

import argparse

from monotracker.cli_args import home_folder
from monotracker.errors import InputError


def register(subparsers) -> None:
    a = subparsers.add_parser("audit", help="the session's audit log: verify its hash chain",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    asub = a.add_subparsers(dest="audit_command", metavar="ACTION", required=True)
    v = asub.add_parser("verify", help="check the audit log's hash chain, protective triggers and robot state rows")
    v.add_argument("home", nargs="?", type=home_folder, default=None,
                   help="session folder (default $MONOTRACKER_HOME, else your ~/.monotracker)")
    v.add_argument("--json", action="store_true", help="print one JSON object")
    v.set_defaults(func=_audit_verify)
    from monotracker.engine.kernels import GROUPS

    k = subparsers.add_parser(
        "compile-kernels", help="compile the numba kernels ahead of first use (after an install)",
        description="Compile the package's numba kernels into their disk cache, so that the first CT "
                    "detection and the first camera frames do not wait for it (~50 CPU s after an "
                    "install; milliseconds once cached). Groups: "
                    + "; ".join(f"{g.name}: {g.what}" for g in GROUPS) + ".")
    k.add_argument("groups", nargs="*", metavar="GROUP",
                   help="groups to compile (default: all): " + ", ".join(g.name for g in GROUPS))
    k.add_argument("--quiet", action="store_true", help="print nothing when all went well")
    k.add_argument("--side-by-side", action="store_true",
                   help="one process per group, all at once (the groups are of about equal cost: "
                        "~31 s instead of ~50 s on 2 cores after an install)")
    k.set_defaults(func=_compile_kernels)


def _compile_kernels(args) -> int:
    from monotracker.engine.kernels import checked_groups, compile_groups

    try:
        wanted = checked_groups(args.groups or None)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if args.side_by_side:
        return _compile_side_by_side(list(wanted), args.quiet)

    def done(name, seconds):
        if not args.quiet:
            print(f"compiled kernels: {name} ({seconds:.1f} s)", flush=True)

    compile_groups(wanted, on_done=done)
    return 0


def _compile_side_by_side(names: list, quiet: bool) -> int:
    """``compile-kernels [--quiet] NAME`` in one child process per group, all started before any
    is waited for; exit 0 when every child exited 0, else the first other exit status (each
    child says its own error)."""
    import subprocess
    import sys

    children = [subprocess.Popen([sys.executable, "-m", "monotracker", "compile-kernels", *(["--quiet"] if quiet else []),
                                  name]) for name in names]
    codes = [c.wait() for c in children]
    return next((c for c in codes if c != 0), 0)


def _audit_verify(args) -> int:
    import json
    from dataclasses import asdict

    from monotracker.engine.audit import verify
    from monotracker.engine.session import AUDIT_FILE

    if args.home is None:
        from monotracker.paths import default_home

        home = default_home()
    else:
        home = args.home
    if not (home / AUDIT_FILE).is_file():
        raise InputError(f"no audit log in {home} (expected {AUDIT_FILE})")
    r = verify(home / AUDIT_FILE)
    if args.json:
        print(json.dumps(asdict(r)))
    else:
        print(("OK: " if r.ok else "TAMPERED: ") + r.reason)
    return 0 if r.ok else 1

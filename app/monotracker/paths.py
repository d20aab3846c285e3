"""Where things live on disk.

* ``repo_root()``: the checkout (``sample_data/`` and ``static/`` sit there).
* ``data_dir()``: the operator's working folder for saved plans, the audit log and logs;
  ``$MONOTRACKER_HOME``, else ``.monotracker`` in the home folder of the user running it (from
  the user database, not ``$HOME``: ``sudo`` or a shared ``$HOME`` never makes two users share
  one folder; :func:`default_home`). Created on first use. A running session locks its folder
  (``engine/session_lock.py``).
* ``key_dir()``: where this machine's integrity key and the audit logs' anchors live, outside
  every session folder (``engine/integrity.py``): ``$MONOTRACKER_KEY_DIR``, else
  ``$XDG_CONFIG_HOME/monotracker``, else ``~/.config/monotracker``. Not created here.
"""

from __future__ import annotations

import os
from pathlib import Path


def repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def sample_data_dir() -> Path:
    return repo_root() / "sample_data"


def static_dir() -> Path:
    return repo_root() / "static"


def sample_ct_path() -> Path:
    """The bundled synthetic head CT (compressed NIfTI, LPS, anisotropic, oblique)."""
    return sample_data_dir() / "phantom_ct.nii.gz"


def default_home() -> Path:
    """``$MONOTRACKER_HOME``, else ``<this user's home>/.monotracker`` (the home folder of the
    process's user id in the user database; ``$HOME`` only where there is none)."""
    env = os.environ.get("MONOTRACKER_HOME")
    if env:
        return Path(env)
    home = None
    try:
        import pwd

        home = pwd.getpwuid(os.getuid()).pw_dir
    except (ImportError, KeyError, AttributeError):
        pass
    return Path(home or Path.home()) / ".monotracker"


def data_dir() -> Path:
    """:func:`default_home`, created if missing. The per-user default must belong to this user:
    one owned by another user (made by ``sudo`` with a kept ``$HOME``, say) is refused with one
    line (``InputError``) rather than shared."""
    from monotracker.errors import InputError

    d = default_home()
    d.mkdir(parents=True, exist_ok=True)
    if not os.environ.get("MONOTRACKER_HOME") and hasattr(os, "getuid"):
        owner = d.stat().st_uid
        if owner != os.getuid():
            raise InputError(f"the default session folder {d} belongs to another user (uid {owner}); "
                             "use your own with --home or MONOTRACKER_HOME")
    return d


def key_dir() -> Path:
    """Folder of the integrity key and audit anchors (see the module docstring); not created."""
    env = os.environ.get("MONOTRACKER_KEY_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "monotracker"

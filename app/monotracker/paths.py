"""Where things live on disk.

* ``repo_root()``: the checkout (``sample_data/`` and ``static/`` sit there).
* ``data_dir()``: the operator's working folder for saved plans, the audit log and logs;
  ``$MONOTRACKER_HOME`` or ``~/.monotracker``. Created on first use.
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


def data_dir() -> Path:
    d = Path(os.environ.get("MONOTRACKER_HOME", Path.home() / ".monotracker"))
    d.mkdir(parents=True, exist_ok=True)
    return d

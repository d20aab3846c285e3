"""Lazy package exports (PEP 562): a package's public names are imported on first use, not when
the package is imported.

Why: every ``monotracker`` command imports its package's ``commands`` module to build the
parser, and an eager ``__init__`` pulled in scikit-learn, SciPy, numba, SimpleITK and the whole
engine first: ``monotracker --help`` or a mistyped argument took ~4 s (issue 35). With this,
``from monotracker.ct import detect_fiducials`` still works (the name is imported then), and so
does ``monotracker.ct.Volume``.
"""

from __future__ import annotations

import importlib


def lazy_exports(package: str, exports: dict[str, str]):
    """``(__getattr__, __dir__)`` for ``package`` whose public names ``exports`` maps to the
    module (relative to ``package``, e.g. ``".fiducials"``) that defines each.

    A name may not be its own module's name (``"visibility": "pkg.visibility"``): once that
    module is imported, the import system sets the package's attribute of that name to the
    module, and this ``__getattr__`` is never asked; import such a name eagerly instead."""
    for name, where in exports.items():
        if where.rsplit(".", 1)[-1] == name:
            raise ValueError(f"{package}.{name}: a lazy name may not be its own module's name ({where}); import it eagerly")

    def __getattr__(name: str):
        where = exports.get(name)
        if where is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(where, package), name)
        globals_ = importlib.import_module(package).__dict__
        globals_[name] = value  # once imported, a plain attribute
        return value

    def __dir__():
        return sorted(set(importlib.import_module(package).__dict__) | set(exports))

    return __getattr__, __dir__

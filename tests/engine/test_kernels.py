"""``monotracker compile-kernels`` and its table (:mod:`monotracker.engine.kernels`): every module
of compiled kernels belongs to a group, and the command says what it did or what was wrong."""

from __future__ import annotations

import ast
from types import SimpleNamespace
from pathlib import Path

import pytest

from monotracker.cli import main
from monotracker.engine import kernels

APP = Path(kernels.__file__).resolve().parents[1]   # app/monotracker


def _module_file(name: str) -> Path:
    return APP.parent / (name.replace(".", "/") + ".py")


def _imported_monotracker_modules(path: Path) -> set[str]:
    """The ``monotracker.*`` modules a file imports (``import a.b``, ``from a.b import c``, and
    ``from a import b`` where ``a.b`` is a module)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("monotracker.")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("monotracker"):
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names if _module_file(f"{node.module}.{a.name}").is_file()}
    return out


def test_every_module_of_compiled_kernels_is_compiled_by_a_group():
    """A module that compiles kernels (it uses ``registration.compiled``) is either a group's
    warm-up module or imported by one (whose warm-up calls it: ``sphere_fit.warm_up`` compiles
    ``fit_kernels`` and ``label_kernels``); a new module of kernels left out of the table would
    compile at first use again."""
    kernel_modules = set()
    for f in APP.rglob("*.py"):
        if f.name == "compiled.py":
            continue
        if "monotracker.registration.compiled" in _imported_monotracker_modules(f):
            kernel_modules.add(".".join(f.relative_to(APP.parent).with_suffix("").parts))
    assert {"monotracker.vision.edge_kernels", "monotracker.ct.label_kernels"} <= kernel_modules  # the scan works
    covered = set()
    for g in kernels.GROUPS:
        for ref in g.warm_ups:
            mod = ref.split(":")[0]
            covered.add(mod)
            covered |= _imported_monotracker_modules(_module_file(mod))
    assert kernel_modules <= covered, f"not compiled by any group: {sorted(kernel_modules - covered)}"


def test_compile_kernels_says_what_it_compiled(capsys):
    assert main(["compile-kernels", "camera"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith("compiled kernels: camera (")
    assert main(["compile-kernels", "--quiet", "camera"]) == 0
    assert capsys.readouterr().out == ""


def test_an_unknown_group_is_one_line_and_compiles_nothing(capsys, monkeypatch):
    imported = []
    monkeypatch.setattr(kernels, "importlib", SimpleNamespace(import_module=imported.append))
    assert main(["compile-kernels", "camera", "gpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: unknown kernel group 'gpu' (groups: camera, ct)"]
    with pytest.raises(ValueError, match="unknown kernel group 'gpu'"):
        kernels.compile_groups(["gpu"])
    assert imported == []     # checked before any group is compiled


def test_side_by_side_starts_one_process_per_group_before_waiting(monkeypatch):
    """``--side-by-side``: every group's child is started before the first is waited for (so they
    run at once), with the group's name and the quiet flag; the first failing child's exit status
    is the command's."""
    import subprocess

    events = []

    class Child:
        def __init__(self, argv):
            self.argv = argv
            events.append(("start", argv[-1]))

        def wait(self):
            events.append(("wait", self.argv[-1]))
            return 3 if self.argv[-1] == "ct" and fail else 0

    monkeypatch.setattr(subprocess, "Popen", Child)
    fail = False
    assert main(["compile-kernels", "--side-by-side", "--quiet"]) == 0
    names = list(kernels.group_names())
    assert len(names) >= 2
    assert events == [("start", n) for n in names] + [("wait", n) for n in names]
    events.clear()
    fail = True
    assert main(["compile-kernels", "--side-by-side", "ct", "camera"]) == 3
    assert events == [("start", "ct"), ("start", "camera"), ("wait", "ct"), ("wait", "camera")]


def test_side_by_side_really_compiles_each_group():
    """The children are real ``python -m monotracker`` processes: one group's run ends 0 and says
    what it compiled (numba's cache already holds it after the suite's own warm-up)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "monotracker", "compile-kernels", "--side-by-side", "camera"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("compiled kernels: camera (")

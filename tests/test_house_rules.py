"""House rules a machine checks (CONTRIBUTING.md): ruff's rule set and the import contracts.

``scripts/test.sh`` runs both before the suite; these tests run them too (so ``pytest`` alone
cannot pass on a tree that breaks them) and show, on a planted violation in a scratch copy, that
each check fails when it should: a contract that cannot fail checks nothing.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINTED = ["app", "tests", "benchmarks", "examples", "scripts"]


def _tool(name: str) -> str:
    """The tool installed beside this interpreter (the project's .venv), else on PATH."""
    here = Path(sys.executable).parent / name
    found = str(here) if here.exists() else shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: run `bash scripts/setup.sh` (it is in the test extras)")
    return found


def _run(args, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    """The tool's output read as UTF-8 whatever the locale (import-linter draws its banner in
    box characters; CI once ran with an ASCII locale, and decoding that failed the test)."""
    env = {**(os.environ if env is None else env), "PYTHONIOENCODING": "utf-8"}
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, encoding="utf-8",
                          errors="replace", timeout=300)


def test_ruff_finds_nothing():
    r = _run([_tool("ruff"), "check", "--no-cache", *LINTED], ROOT)
    assert r.returncode == 0, r.stdout + r.stderr


def test_import_contracts_are_kept():
    r = _run([_tool("lint-imports"), "--no-cache"], ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


def _scratch_copy(tmp_path: Path) -> Path:
    """The package and the project's configuration in a scratch folder (nothing of it imported)."""
    shutil.copytree(ROOT / "app" / "monotracker", tmp_path / "monotracker",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_layer_contract_fails_on_an_upward_import(tmp_path):
    work = _scratch_copy(tmp_path)
    geometry = work / "monotracker" / "geometry.py"
    geometry.write_text(geometry.read_text() + "\nfrom monotracker.engine import Session  # planted\n")
    env = {**os.environ, "PYTHONPATH": str(work)}
    r = _run([_tool("lint-imports"), "--no-cache"], work, env)
    assert r.returncode != 0, r.stdout
    assert "monotracker.geometry is not allowed to import monotracker.engine" in r.stdout, r.stdout
    assert "monotracker.geometry -> monotracker.engine" in r.stdout


def test_ruff_fails_on_an_unexplained_blind_except(tmp_path):
    work = _scratch_copy(tmp_path)
    bad = work / "monotracker" / "planted.py"
    bad.write_text('"""Planted."""\n\n\ndef f(g):\n    try:\n        g()\n    except Exception:\n        pass\n')
    r = _run([_tool("ruff"), "check", "--no-cache", str(bad)], work)
    assert r.returncode != 0, r.stdout
    assert "BLE001" in r.stdout

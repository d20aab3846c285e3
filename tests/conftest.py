"""Test-wide fixtures.

CPU hogs beside the tests: ``MONOTRACKER_TEST_HOGS=4 .venv/bin/python -m pytest tests/ui/test_e2e.py``
runs 4 busy loops (``benchmarks/_hogs.py``: nice 0, whatever priority the engine gave the test
process) for the whole pytest session, as a loaded machine would. The tests must hold on such a
machine (they wait on state, never on wall-clock guesses); this is how to check it. The hogs are killed when the
session ends and end by themselves if pytest dies (each watches its parent). Default: none.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest


def _hogs_module():
    """``benchmarks/_hogs.py``: the one way the benchmarks and the tests start CPU hogs (loaded by
    path: ``benchmarks/`` is no package)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "_hogs.py"
    spec = importlib.util.spec_from_file_location("monotracker_bench_hogs", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _hog_count() -> int:
    raw = os.environ.get("MONOTRACKER_TEST_HOGS", "").strip() or "0"
    try:
        n = int(raw)
    except ValueError:
        raise pytest.UsageError(f"MONOTRACKER_TEST_HOGS must be a whole number of CPU hogs, not {raw!r}") from None
    if not 0 <= n <= 64:
        raise pytest.UsageError(f"MONOTRACKER_TEST_HOGS must be between 0 and 64, not {n}")
    return n


@pytest.fixture(scope="session", autouse=True)
def cpu_hogs():
    """The hog processes (empty without ``MONOTRACKER_TEST_HOGS``)."""
    with _hogs_module().hogs(_hog_count()) as procs:
        yield procs


def pytest_report_header(config):
    n = os.environ.get("MONOTRACKER_TEST_HOGS", "").strip()
    return f"MONOTRACKER_TEST_HOGS={n}: CPU hogs beside every test" if n and n != "0" else None


@pytest.fixture(scope="session", autouse=True)
def integrity_key_dir(tmp_path_factory):
    """Every test (and the processes it starts) uses a private integrity-key folder
    (``MONOTRACKER_KEY_DIR``, ``engine/integrity.py``), never the user's ``~/.config``."""
    d = tmp_path_factory.mktemp("integrity-keys")
    old = os.environ.get("MONOTRACKER_KEY_DIR")
    os.environ["MONOTRACKER_KEY_DIR"] = str(d)
    yield d
    if old is None:
        os.environ.pop("MONOTRACKER_KEY_DIR", None)
    else:
        os.environ["MONOTRACKER_KEY_DIR"] = old

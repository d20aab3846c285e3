"""Test-wide fixtures.

CPU hogs beside the tests: ``MONOTRACKER_TEST_HOGS=4 .venv/bin/python -m pytest tests/ui/test_e2e.py``
runs 4 busy loops (nice 0, whatever priority the engine gave the test process) for the whole
pytest session, as a loaded machine would. The tests must hold on such a machine (they wait on
state, never on wall-clock guesses); this is how to check it. The hogs are killed when the
session ends and end by themselves if pytest dies (each watches its parent). Default: none.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

#: a busy loop at nice 0 that ends when its parent (pytest) is gone
HOG = ("import os\n"
       "os.setpriority(os.PRIO_PROCESS, 0, 0)\n"
       "parent = os.getppid()\n"
       "while os.getppid() == parent:\n"
       "    for _ in range(1000000):\n"
       "        pass\n")


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
    procs = [subprocess.Popen([sys.executable, "-c", HOG, "hog-monotracker-test"]) for _ in range(_hog_count())]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait(10)


def pytest_report_header(config):
    n = os.environ.get("MONOTRACKER_TEST_HOGS", "").strip()
    return f"MONOTRACKER_TEST_HOGS={n}: CPU hogs beside every test" if n and n != "0" else None

"""Test-wide fixtures.

CPU hogs beside the tests: ``MONOTRACKER_TEST_HOGS=4 .venv/bin/python -m pytest tests/ui/test_e2e.py``
runs 4 busy loops (``benchmarks/_hogs.py``: nice 0, whatever priority the engine gave the test
process) for the whole pytest session, as a loaded machine would (4 in all, also when pytest-xdist
runs several workers: the controller starts them). The tests must hold on such a
machine (they wait on state, never on wall-clock guesses); this is how to check it. The hogs are killed when the
session ends and end by themselves if pytest dies (each watches its parent). Default: none.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

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


def _is_xdist_worker(config) -> bool:
    """True in a pytest-xdist worker (the controller, or a plain pytest run, starts the hogs)."""
    return hasattr(config, "workerinput")


def pytest_sessionstart(session):
    """Start the hogs once per run: in the controller when pytest-xdist runs workers (each
    worker starting its own would multiply them), else in this process."""
    config = session.config
    config._mt_hogs = []
    if not _is_xdist_worker(config):
        n = _hog_count()
        if n:
            config._mt_hogs = _hogs_module().start_hogs(n)


def pytest_sessionfinish(session):
    procs = getattr(session.config, "_mt_hogs", [])
    if procs:
        _hogs_module().stop_hogs(procs)
        session.config._mt_hogs = []


@pytest.fixture(scope="session", autouse=True)
def cpu_hogs(pytestconfig):
    """The hog processes this process started (empty without ``MONOTRACKER_TEST_HOGS``, and in a
    pytest-xdist worker: the controller runs them for all workers)."""
    _hog_count()  # a bad value is a usage error in every process
    return list(getattr(pytestconfig, "_mt_hogs", []))


#: Test files that run in the serial lane (one pytest-xdist worker, one test after another; see
#: scripts/test.sh): the browser tests (each drives chromium, which renders the 3D view in
#: software, against an engine on the real clock) and the files that drive the engine, a pose
#: stream or a recording on the real clock against the engine's own limits (a pose older than
#: 0.15 s holds the arm), which failed in the suite at high load before (issue 35). The other
#: worker runs the rest beside them: the serial lane shares the machine with one test at a time,
#: never with another browser or real-clock test. A file with a ``realtime`` test belongs here
#: (collection says so otherwise).
SERIAL_LANE = (
    "tests/ui/",
    "tests/examples/",
    "tests/engine/test_digital_twin.py",
    "tests/engine/test_pose_pipeline.py",
    "tests/vision/test_pose_stream.py",
    "tests/interop/test_recording_replay.py",
    "tests/interop/test_replay_camera.py",
)


def in_serial_lane(nodeid: str) -> bool:
    """True for a test (pytest node id, relative to the repository) of :data:`SERIAL_LANE`."""
    return nodeid.split("::", 1)[0].startswith(SERIAL_LANE)


def pytest_collection_modifyitems(config, items):
    """A ``realtime`` test outside the serial lane is a usage error: it would share the machine
    with any other test."""
    for item in items:
        if item.get_closest_marker("realtime") is not None:
            rel = Path(str(item.path)).resolve().relative_to(ROOT).as_posix()
            if not rel.startswith(SERIAL_LANE):
                raise pytest.UsageError(f"{item.nodeid} is marked realtime: add {rel} to SERIAL_LANE in tests/conftest.py")


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist: unknown (and unused) without it
def pytest_xdist_make_scheduler(config, log):
    """With ``--dist loadgroup`` (scripts/test.sh): pytest-xdist's group scheduling, with the
    serial lane as one group, sent first (the largest unit) to one worker while the other workers
    take the remaining tests one by one. (Grouping by node id here: pytest-xdist 3.8's
    ``xdist_group`` marker does not group on pytest 9.2, which made node ids read-only.)"""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class SerialLaneScheduling(LoadGroupScheduling):
        def _split_scope(self, nodeid: str) -> str:
            if in_serial_lane(nodeid):
                return "serial-lane"
            return super()._split_scope(nodeid)

    return SerialLaneScheduling(config, log)


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

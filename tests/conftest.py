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
            # in the tests' own session (``own_session=False``): the app under test competes with
            # them thread by thread, harder than a neighbour's session would load it
            config._mt_hogs = _hogs_module().start_hogs(n, own_session=False)


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


#: Test files of the serial lane (scripts/test.sh runs them one after another, alone, after the
#: rest has run on 2 pytest-xdist workers): the files that drive the engine, a pose stream or a
#: recording on the real clock against the engine's own limits (a pose older than 0.15 s holds
#: the arm), which failed in the suite at high load before (issue 35). A file with a ``realtime``
#: test belongs here (collection says so otherwise). Every test that uses the ``browser`` fixture
#: (tests/ui/conftest.py: chromium renders the 3D view in software beside an engine on the real
#: clock) is in the serial lane too, wherever it lives (:func:`in_serial_lane`); the view-level
#: tests of tests/ui/ (doubles, fake clocks, no browser) run 2-wide with the rest. A file that
#: mixes such tests with pure logic (a manual clock, no thread, no wall time) lists no file here:
#: its lane tests carry ``@pytest.mark.serial`` and the rest run 2-wide.
SERIAL_LANE = (
    "tests/engine/test_pose_pipeline.py",
    "tests/interop/test_replay_camera.py",
    "tests/ui/test_viser_threads.py",
)


def pytest_addoption(parser):
    parser.addoption("--lane", choices=("all", "parallel", "serial", "alone"), default="all",
                     help="run only the tests of tests/conftest.py's SERIAL_LANE (serial) but those "
                          "marked alone, only the tests marked alone (alone), only the others "
                          "(parallel), or all (default); scripts/test.sh runs the parallel part on "
                          "2 workers beside the serial lane, then the tests marked alone")


def _rel(item) -> str:
    return Path(str(item.path)).resolve().relative_to(ROOT).as_posix()


def in_serial_lane(item) -> bool:
    """True for a test of a :data:`SERIAL_LANE` file, one marked ``serial`` or ``alone``, or one
    that uses the ``browser`` fixture."""
    return (_rel(item).startswith(SERIAL_LANE) or item.get_closest_marker("serial") is not None
            or runs_alone(item) or "browser" in getattr(item, "fixturenames", ()))


def runs_alone(item) -> bool:
    """True for a test marked ``alone``: it holds a live pose stream, a browser and the simulated
    camera to the engine's real-time limits together, which on 2 cores takes the whole machine
    (the end-to-end workflow: beside two busy loops in a nice-19 session, as the suite's parallel
    part runs, the arm reached the entry in 1 of 5 runs; docs/performance.md "The end-to-end test
    on a machine too slow"). scripts/test.sh runs these last, after both parts (``--lane alone``)."""
    return item.get_closest_marker("alone") is not None


def pytest_collection_modifyitems(config, items):
    """A ``realtime`` test outside the serial lane's files is a usage error: it would share the
    machine with any other test. ``--lane`` keeps one side of the lane (the rest is deselected)."""
    for item in items:
        if item.get_closest_marker("realtime") is not None and not _rel(item).startswith(SERIAL_LANE):
            raise pytest.UsageError(f"{item.nodeid} is marked realtime: add {_rel(item)} to SERIAL_LANE in tests/conftest.py")
    lane = config.getoption("--lane")
    if lane == "all":
        return
    keep, drop = [], []
    for item in items:
        if lane == "alone":
            mine = runs_alone(item)
        else:
            mine = in_serial_lane(item) == (lane == "serial") and not runs_alone(item)
        (keep if mine else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


def _kind(item) -> str:
    """What a test's time is spent on, for the profile at the end of a run (issue 35 item 1)."""
    rel = _rel(item)
    if "browser" in getattr(item, "fixturenames", ()):
        return "browser (chromium + served app)"
    if in_serial_lane(item):  # a realtime test is in it too (collection refuses one outside)
        return "real clock / measured CPU (serial lane)"
    if rel.startswith("tests/ct/"):
        return "CT detection"
    if rel.startswith(("tests/vision/", "tests/sim/")):
        return "camera frames and detection"
    if rel.startswith("tests/examples/"):
        return "examples (subprocesses)"
    return "engine, robot, UI logic, other"


def pytest_itemcollected(item):
    """Each test carries its kind in its reports (they reach the controller from xdist's workers)."""
    item.user_properties.append(("mt_kind", _kind(item)))


#: seconds per folder and per kind (setup + call + teardown of every test), collected in the
#: process that writes the terminal summary
_TIME_BY = {"folder": {}, "kind": {}}


def pytest_runtest_logreport(report):
    folder = report.nodeid.split("::")[0].rsplit("/", 1)[0]
    kind = dict(report.user_properties).get("mt_kind", "?")
    for table, key in (("folder", folder), ("kind", kind)):
        n, s = _TIME_BY[table].get(key, (0, 0.0))
        _TIME_BY[table][key] = (n + (report.when == "call"), s + float(report.duration))


def pytest_terminal_summary(terminalreporter):
    """Where the run's time went, by test folder and by kind (issue 35 item 1): the tests' own
    setup + call + teardown seconds summed (with several workers the sum exceeds the wall time;
    collection, start-up and the workers' idle time are not in it)."""
    total = sum(s for _, s in _TIME_BY["folder"].values())
    if total <= 0:
        return
    tr = terminalreporter
    for table in ("folder", "kind"):
        tr.write_sep("-", f"test time by {table} (s summed over tests; {total:.0f} s in all)")
        for key, (n, s) in sorted(_TIME_BY[table].items(), key=lambda kv: -kv[1][1]):
            tr.write_line(f"{s:8.1f} s {100 * s / total:5.1f} %  {n:4d} tests  {key}")


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

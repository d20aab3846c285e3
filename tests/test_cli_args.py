"""Every CLI argument is checked where it enters (issue 17 item 6).

Each case runs the real ``python -m monotracker`` in a child process, the way an operator types
it: the answer must be one ``error:`` line (argparse's usage + error, or ours) and exit 2, never a
traceback nor ``internal error``.
"""

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(args, tmp_path, timeout=120, **kw):
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"), MONOTRACKER_HOME=str(tmp_path / "home"))
    return subprocess.run([sys.executable, "-m", "monotracker", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, encoding="utf-8", errors="replace", timeout=timeout, **kw)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("args,word", [
    (["demo", "--headless", "--seconds", "inf"], "finite"),
    (["demo", "--headless", "--seconds", "0"], "> 0"),
    (["demo", "--headless", "--seed", "-1"], ">= 0"),
    (["demo", "--headless", "--fault-at", "nan"], "finite"),
    (["demo", "--headless", "--home", "/etc/passwd"], "not a folder"),
    (["robot-check", "not_an_ip"], "not an IP address"),
    (["robot-check", "10.0.0.1", "--rate", "inf"], "finite"),
    (["serve", "--robot", "ur:"], "not an IP address"),
    (["serve", "--robot", "ur:robot.local"], "not an IP address"),
    (["serve", "--port", "0"], ">= 1"),
    (["serve", "--home", "/etc/passwd"], "not a folder"),
    (["serve", "--calibration", "/nonexistent/cam.yml"], "not found"),
    (["detect-image", "x.png", "--radius-mm", "nan"], "finite"),  # the central check: any float flag
    (["audit", "verify", "/etc/passwd"], "not a folder"),
])
def test_bad_arguments_are_one_line_errors(tmp_path, args, word):
    r = _run(args, tmp_path)
    assert r.returncode == 2, (r.returncode, r.stdout[-500:], r.stderr[-1500:])
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr
    assert word in r.stderr, r.stderr
    assert "error:" in r.stderr.strip().splitlines()[-1]


def test_the_parser_imports_no_heavy_library(tmp_path):
    """Building the parser (``--help``, any argument error) imports none of the science stack nor
    the engine: every package's public names load on first use (monotracker/_lazy.py). Before,
    each command paid ~4 s of imports (scikit-learn, SciPy, numba, SimpleITK) before argparse
    looked at a single argument (issue 35: ~50 CLI children in the suite)."""
    code = ("import sys; from monotracker.cli import build_parser; build_parser(); "
            "heavy = ('sklearn', 'scipy', 'numba', 'SimpleITK', 'trimesh', 'cv2', 'viser'); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy or m == 'monotracker.engine.session'))")
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"), MONOTRACKER_HOME=str(tmp_path / "home"))
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-1500:]
    assert r.stdout.strip() == "[]", r.stdout[-1500:]


def test_a_bad_calibration_file_is_refused_at_start(tmp_path):
    cal = tmp_path / "cam.json"
    cal.write_text('{"camera_matrix": [[-5, 0, 320], [0, 800, 240], [0, 0, 1]], '
                   '"distortion_coefficients": [0, 0, 0, 0, 0], "image_width": 640, "image_height": 480}')
    r = _run(["serve", "--port", str(_free_port()), "--camera", "device:0", "--calibration", str(cal)], tmp_path,
             timeout=120)
    assert r.returncode == 2, r.stderr[-1500:]
    assert r.stderr.strip().startswith("error:") and "focal" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "home" / "audit.sqlite").exists()  # refused before a session began


def test_broken_pipe_is_quiet(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"), MONOTRACKER_HOME=str(tmp_path / "home"))
    p = subprocess.Popen([sys.executable, "-m", "monotracker", "detect-ct", str(ROOT / "sample_data" / "phantom_ct.nii.gz"),
                          "--json"], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # the reader is gone before anything is written (`| head -0`)
    err = p.stderr.read().decode()
    p.wait(300)
    assert "Traceback" not in err and "BrokenPipe" not in err and "internal error" not in err, err
    assert p.returncode == 141


def test_audit_verify_command(tmp_path):
    import sqlite3

    from monotracker.engine.audit import AuditLog

    home = tmp_path / "h"
    home.mkdir()
    log = AuditLog(home / "audit.sqlite", "s")
    for i in range(3):
        log.record("event", "info", f"c{i}", f"m{i}")
    log.close()
    r = _run(["audit", "verify", str(home)], tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("OK:"), (r.stdout, r.stderr)
    db = sqlite3.connect(home / "audit.sqlite", isolation_level=None)
    db.execute("DROP TRIGGER audit_no_update")
    db.execute("UPDATE audit SET message='forged' WHERE id=2")
    db.close()
    r = _run(["audit", "verify", str(home)], tmp_path)
    assert r.returncode == 1 and "row 2" in r.stdout, (r.stdout, r.stderr)


_WAITER = textwrap.dedent("""
    import signal, sys, threading
    from monotracker.ui.commands import StopSignals
    signals = StopSignals()
    print("READY", flush=True)
    sig = signals.wait(poll_s=0.05)
    print("STOPPING", sig, flush=True)
""")


def test_stop_signals_cannot_deadlock_the_shutdown():
    """Three signals in a burst (as a supervisor that repeats SIGTERM): the handler only records
    them, the main thread stops once."""
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"))
    p = subprocess.Popen([sys.executable, "-c", _WAITER], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, encoding="utf-8", errors="replace")
    try:
        assert p.stdout.readline().strip() == "READY"
        for _ in range(3):
            p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    assert f"STOPPING {int(signal.SIGTERM)}" in out


def test_session_refuses_a_home_that_is_a_file(tmp_path):
    from monotracker.engine import Session, SessionConfig
    from monotracker.errors import InputError

    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        Session(SessionConfig(home=f, clock="sim"))
    with pytest.raises(InputError, match="IP address"):
        SessionConfig(robot="ur:").validate()
    t0 = time.monotonic()
    with pytest.raises(InputError, match="IP address"):
        SessionConfig(robot="ur:no-such-host.invalid").validate()
    assert time.monotonic() - t0 < 30  # no DNS lookup (generous bound)


def test_serve_stops_on_repeated_sigterm(tmp_path):
    """The real web app: SIGTERM three times in a burst; it shuts down (disarmed, threads stopped)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"), MONOTRACKER_HOME=str(tmp_path / "home"), MONOTRACKER_PIN="2468")
    p = subprocess.Popen([sys.executable, "-m", "monotracker", "serve", "--port", str(_free_port())], cwd=ROOT, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, encoding="utf-8", errors="replace")
    try:
        seen = []
        while not any("MonoTracker is running" in x for x in seen):  # viser prints its banner first
            line = p.stdout.readline()
            assert line, ("".join(seen), p.stderr.read() if p.poll() is not None else "")
            seen.append(line)
        for _ in range(3):
            p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err[-2000:]
    assert "stopping" in out and "Traceback" not in err

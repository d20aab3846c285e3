"""One session per folder (issue 34): a running session locks its folder, a second one (another
process, the web server too) is refused with one line naming the holder, a lock left by a
killed process does not block the next session (which records whose lock it took over), and
the default folder belongs to the user running it."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.engine.session_lock import SessionFolderBusy, SessionFolderLock

ROOT = Path(__file__).resolve().parents[2]

HOLDER = """
import sys, time
from monotracker.engine import Session, SessionConfig
s = Session(SessionConfig(home=sys.argv[1], clock="sim"))
print("ready", flush=True)
sys.stdin.readline()  # "close": shut down cleanly; killed otherwise
s.shutdown()
print("closed", flush=True)
"""


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT / "app"))


@pytest.fixture
def holder(tmp_path):
    """Another process running a session on ``tmp_path / 'home'``; yields (process, home)."""
    home = tmp_path / "home"
    script = tmp_path / "holder.py"
    script.write_text(HOLDER)
    p = subprocess.Popen([sys.executable, str(script), str(home)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    line = p.stdout.readline()  # blocks until the session is up (or the process died)
    assert line.strip() == "ready", p.stderr.read()[-2000:]
    yield p, home
    if p.poll() is None:
        p.kill()
    p.wait(30)


def test_a_second_session_on_a_held_folder_is_refused_naming_the_holder(holder, tmp_path):
    p, home = holder
    with pytest.raises(SessionFolderBusy) as exc:
        Session(SessionConfig(home=home, clock="sim"))
    msg = str(exc.value)
    assert f"pid {p.pid}" in msg and f"host {socket.gethostname()}" in msg and "since" in msg and "\n" not in msg
    # the web server says the same, in one line, and exits without serving
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    r = subprocess.run([sys.executable, "-m", "monotracker", "serve", "--home", str(home), "--port", str(port),
                        "--pin", "2468"], capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=300)
    out = (r.stdout + r.stderr).strip()
    assert r.returncode != 0, out
    assert f"pid {p.pid}" in out and "in use" in out and "Traceback" not in out
    assert "MonoTracker is running" not in out


def test_a_lock_left_by_a_killed_process_does_not_block_and_is_recorded(holder):
    p, home = holder
    p.send_signal(signal.SIGKILL)
    p.wait(30)
    s = Session(SessionConfig(home=home, clock="sim"))  # the kernel dropped the dead holder's lock
    try:
        with pytest.raises(SessionFolderBusy):  # and this session holds it now
            Session(SessionConfig(home=home, clock="sim"))
        rows = [e for e in s.audit_entries(code="session_lock_recovered") if e.session_id == s.session_id]
        assert len(rows) == 1 and rows[0].data["previous"]["pid"] == p.pid
        assert f"pid {p.pid}" in rows[0].message
    finally:
        s.shutdown()


def test_a_cleanly_closed_session_frees_the_folder_with_nothing_to_recover(holder):
    p, home = holder
    p.stdin.write("close\n")
    p.stdin.flush()
    assert p.stdout.readline().strip() == "closed"
    p.wait(60)
    assert SessionFolderLock(home).read_holder() is None  # a clean release clears the holder line
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        assert not [e for e in s.audit_entries(code="session_lock_recovered") if e.session_id == s.session_id]
    finally:
        s.shutdown()
    # and, in one process, a second session after the first shut down is fine too
    Session(SessionConfig(home=home, clock="sim")).shutdown()


def test_the_default_folder_is_the_users_own(tmp_path, monkeypatch):
    """``$HOME`` does not decide (sudo keeps it); the user database does, and a default folder
    that belongs to another user is refused, not shared."""
    import pwd

    from monotracker import paths
    from monotracker.errors import InputError

    monkeypatch.delenv("MONOTRACKER_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "someone-elses-home"))
    mine = tmp_path / "my-home"
    mine.mkdir()
    from types import SimpleNamespace

    real = pwd.getpwuid
    monkeypatch.setattr(pwd, "getpwuid", lambda uid: SimpleNamespace(pw_dir=str(mine)) if uid == os.getuid() else real(uid))
    assert paths.default_home() == mine / ".monotracker"
    assert paths.data_dir() == mine / ".monotracker" and (mine / ".monotracker").is_dir()
    monkeypatch.setenv("MONOTRACKER_HOME", str(tmp_path / "chosen"))
    assert paths.default_home() == tmp_path / "chosen"
    monkeypatch.delenv("MONOTRACKER_HOME")
    if os.geteuid() == 0:  # only root can give the folder to another user
        os.chown(mine / ".monotracker", 65534, 65534)
        with pytest.raises(InputError) as exc:
            paths.data_dir()
        assert "belongs to another user" in str(exc.value) and "\n" not in str(exc.value)

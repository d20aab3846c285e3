"""The page login of ``serve --allow-remote`` (ui/remote_login.py): nothing of the app passes
before it.

Checked on the wire, not only in the browser: an unauthenticated HTTP request gets the login
page or 401, an unauthenticated websocket upgrade gets 401 and not one byte of viser's messages
(the same raw handshake *with* a login cookie receives the page's GUI messages, so the check can
fail); wrong passwords lock the login (audit rows, the ``login_lockout`` alarm); a real browser
logs in, reaches the app, logs out and is cut off when its login expires.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
from browser_helpers import APP_OPTIONS, T_PAGE_MS, _wait

pytestmark = pytest.mark.timeout(600)

PASSWORD = "correct-horse-7"
#: a string the first scene messages carry (the app sets the world axes of the broadcast scene)
APP_MARKER = b"/WorldAxes"


class FakeClock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


# ---------------------------------------------------------------------------- the gate (no network)
def test_gate_lockout_expiry_logout():
    from monotracker.ui.remote_login import LoginGate

    clock, rows, alarms = FakeClock(), [], []
    gate = LoginGate(PASSWORD, ttl_s=60.0, max_tries=3, lockout_s=30.0, clock=clock,
                     audit=lambda c, m, lvl: rows.append((c, m)), lockout=lambda s, m: alarms.append(s))
    for _k in range(2):
        r, tok = gate.try_login("nope", "10.0.0.9")
        assert not r.ok and tok is None and "wrong password" in r.message
    r, tok = gate.try_login("nope", "10.0.0.9")
    assert not r.ok and "locked for 30 s" in r.message
    assert alarms and alarms[-1] == pytest.approx(30.0)
    r, tok = gate.try_login(PASSWORD, "10.0.0.9")  # the right password while locked: refused
    assert not r.ok and tok is None and "locked" in r.message
    assert [c for c, _ in rows] == ["login_refused"] * 4
    assert all(PASSWORD not in m for _, m in rows)  # never the password
    clock.t += 31.0
    gate.sync_alarm()
    assert alarms[-1] == 0.0  # the alarm cleared with the lockout
    r, tok = gate.try_login(PASSWORD, "10.0.0.9")
    assert r.ok and tok and gate.valid(tok)
    assert not gate.valid("forged" + tok) and not gate.valid(None)
    clock.t += 59.0
    assert gate.valid(tok) and gate.expire() == []
    clock.t += 2.0
    assert not gate.valid(tok) and gate.expire() == [tok]
    assert rows[-1][0] == "login_expired"
    r, tok2 = gate.try_login(PASSWORD)
    assert gate.logout(tok2) and not gate.valid(tok2) and not gate.logout(tok2)
    assert rows[-1][0] == "logout"


def test_lockout_is_global_so_many_addresses_do_not_multiply_the_tries():
    """The lockout holds for every address (docs/ui-remote.md; issue 36: with one guard per
    address, 33 guesses from several addresses got in). A station already logged in keeps its
    session; the alarm names the lockout."""
    from monotracker.ui.remote_login import LoginGate

    clock, alarms = FakeClock(), []
    gate = LoginGate(PASSWORD, max_tries=5, lockout_s=30.0, clock=clock, lockout=lambda s, m: alarms.append((s, m)))
    r, station = gate.try_login(PASSWORD, "10.0.0.2")  # an OR station logged in before
    assert r.ok
    tried = 0
    for k in range(33):  # rotating addresses, as in the adversarial pass
        r, tok = gate.try_login("guess%d" % k, "10.9.9.%d" % (k % 7))
        assert not r.ok and tok is None
        tried += 1
        if gate.locked_for() > 0:
            break
    assert tried == 5  # five wrong tries in all, from any mix of addresses, start the lockout
    assert gate.locked_for("10.0.0.3") == pytest.approx(30.0)  # every address is locked
    assert alarms and alarms[-1][0] > 0 and "30 s" in alarms[-1][1] and "every address" in alarms[-1][1]
    r, tok = gate.try_login(PASSWORD, "10.0.0.3")  # even the right password, from a fresh address
    assert not r.ok and tok is None and "locked" in r.message
    assert gate.valid(station)  # the station already in keeps its session
    clock.t += 31.0
    r, tok = gate.try_login(PASSWORD, "10.0.0.3")
    assert r.ok and gate.valid(tok)


def test_password_file_errors(tmp_path):
    from monotracker.errors import InputError
    from monotracker.ui.remote_login import read_password_file

    with pytest.raises(InputError, match="file not found"):
        read_password_file(tmp_path / "none.txt")
    (tmp_path / "short.txt").write_text("abc\n")
    with pytest.raises(InputError, match="at least 8 characters"):
        read_password_file(tmp_path / "short.txt")
    (tmp_path / "empty.txt").write_text("\n")
    with pytest.raises(InputError, match="first line is empty"):
        read_password_file(tmp_path / "empty.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00abcdefgh")
    with pytest.raises(InputError, match="not a UTF-8"):
        read_password_file(tmp_path / "bin.txt")
    with pytest.raises(InputError, match="is a folder"):
        read_password_file(tmp_path)
    (tmp_path / "ok.txt").write_text("  " + PASSWORD + "  \nsecond line\n")
    assert read_password_file(tmp_path / "ok.txt") == PASSWORD


def test_cli_one_line_errors(tmp_path, port):
    """Bad password file, --password-file without --allow-remote, a port in use: one line, exit 2."""
    exe = [sys.executable, "-m", "monotracker", "serve", "--home", str(tmp_path), "--port", str(port)]
    env = {"PYTHONPATH": str(Path(__file__).resolve().parents[2] / "app"), "PATH": "/usr/bin:/bin",
           "HOME": str(tmp_path)}
    (tmp_path / "short.txt").write_text("abc\n")
    cases = [(["--allow-remote", "--password-file", str(tmp_path / "short.txt")], "at least 8 characters"),
             (["--allow-remote", "--password-file", str(tmp_path / "missing")], "file not found"),
             (["--password-file", str(tmp_path / "short.txt")], "--password-file is for --allow-remote"),
             (["--tre-confidence", "0.3"], "tre_confidence must be 0 (off) or a probability from 0.5"),
             (["--ball-finish", "shiny"], "ball finish must be one of read, matte, glossy"),
             (["--average-still-frames", "99"], "average_still_frames must be a whole number of frames from 0")]
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        cases.append((["--allow-remote", "--port", str(busy.getsockname()[1])], "cannot listen on"))
        for extra, want in cases:
            p = subprocess.run(exe + extra, capture_output=True, text=True, encoding="utf-8", errors="replace", env=env, timeout=300)
            lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
            assert p.returncode == 2, p.stderr
            assert len(lines) == 1 and want in lines[0] and "Traceback" not in p.stderr, p.stderr


# ---------------------------------------------------------------------------- on the wire
@pytest.fixture
def remote(tmp_path, port):
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp
    from monotracker.ui.remote_login import for_session

    s = Session(SessionConfig(home=tmp_path, arm_pin="2468"))
    gate = for_session(s, PASSWORD, ttl_s=3600.0, max_tries=3, lockout_s=5.0)
    app = MonoTrackerApp(s, "127.0.0.1", port, login=gate, **APP_OPTIONS)
    app.start()
    yield s, app, gate
    app.stop()
    s.shutdown()


def _viser_payload(got: bytes) -> bytes:
    """The decompressed msgpack of every complete websocket frame after the HTTP header of
    ``got`` (viser's wire format: 8 bytes size, 8 bytes compressed size, zstd msgpack, buffers)."""
    import zstandard

    head, sep, rest = got.partition(b"\r\n\r\n")
    out, i = b"", 0
    while sep and i + 2 <= len(rest):
        op, n = rest[i] & 0x0F, rest[i + 1] & 0x7F
        j = i + 2
        if n == 126:
            n, j = int.from_bytes(rest[j:j + 2], "big"), j + 2
        elif n == 127:
            n, j = int.from_bytes(rest[j:j + 8], "big"), j + 8
        if j + n > len(rest):
            break
        frame = rest[j:j + n]
        if op == 2 and len(frame) >= 16:
            csize = int.from_bytes(frame[8:16], "little")
            out += zstandard.ZstdDecompressor().decompress(frame[16:16 + csize],
                                                           max_output_size=int.from_bytes(frame[:8], "little"))
        i = j + n
    return out


def _refusal_end(got: bytes) -> int | None:
    """Where a complete HTTP response other than ``101`` ends in ``got`` (its header and the body
    its Content-Length gives), or None (not complete yet, an upgrade, or no Content-Length)."""
    head, sep, body = got.partition(b"\r\n\r\n")
    if not sep or head.startswith(b"HTTP/1.1 101"):
        return None
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            n = int(value.strip())
            return len(head) + 4 + n if len(body) >= n else None
    return None


def _raw_ws(port: int, cookie: str | None = None, origin: str | None = None, read_s: float = 3.0) -> bytes:
    """A websocket upgrade by hand; every byte the server sends within ``read_s`` (or until it closes).

    A refusal (a complete response other than ``101``) is not waited on for ``read_s`` (issue 35:
    the server keeps the connection open, so each refused handshake cost the whole 3 s): once it
    has come, a second request (``HEAD /login``) is sent on the same connection and the bytes are
    read until that one's answer begins. The server answers a connection's requests in order, so
    whatever the refused handshake sent after its response (a relayed viser stream) comes before
    it: when the next bytes are not that answer, reading goes on for ``read_s`` and all is
    returned; else the refusal alone is (the second answer is not)."""
    import viser

    hdr = ["GET / HTTP/1.1", f"Host: 127.0.0.1:{port}", "Upgrade: websocket", "Connection: Upgrade",
           "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==", "Sec-WebSocket-Version: 13",
           f"Sec-WebSocket-Protocol: viser-v{viser.__version__}"]
    if cookie:
        hdr.append(f"Cookie: mt_session={cookie}")
    if origin:
        hdr.append(f"Origin: {origin}")
    got = b""
    probe = f"HEAD /login HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode()
    end = None  # where the refusal's response ends, once the second request is sent
    probing = True  # False once something else than the second answer followed the refusal
    with socket.create_connection(("127.0.0.1", port), timeout=30) as so:
        so.sendall(("\r\n".join(hdr) + "\r\n\r\n").encode())
        so.settimeout(0.5)
        t0 = time.monotonic()
        while time.monotonic() - t0 < read_s:
            if probing and end is None and (end := _refusal_end(got)) is not None:
                so.sendall(probe)
            if probing and end is not None and len(got) - end >= 12:
                nxt = got[end:]
                if nxt.startswith(b"HTTP/1.1 ") and not nxt.startswith(b"HTTP/1.1 101"):
                    return got[:end]  # the second request's answer came next: nothing else was sent
                probing = False  # something else came first: read on for read_s, as for any other reply
            try:
                b = so.recv(65536)
            except socket.timeout:
                if got and APP_MARKER in _viser_payload(got):
                    break
                continue
            if not b:
                break
            got += b
    return got


def _request(port: int, path: str, data: bytes | None = None):
    """(status, body, session cookie or None) of one request (no redirects followed)."""

    class NoRedirect(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *a, **k):
            return None

    op = urllib.request.build_opener(NoRedirect)
    try:
        r = op.open(f"http://127.0.0.1:{port}{path}", data=data, timeout=60)
        return r.status, r.read(), None
    except urllib.error.HTTPError as e:
        cookie = None
        for v in e.headers.get_all("Set-Cookie") or []:
            if v.startswith("mt_session=") and not v.startswith('mt_session=""'):
                cookie = v.split(";")[0].split("=", 1)[1]
                assert "HttpOnly" in v and "SameSite=Strict" in v and "Max-Age=" in v
        return e.code, e.read(), cookie


def _post_login(port: int, password: str):
    """(status, body text, session cookie or None) of one POST /login."""
    status, body, cookie = _request(port, "/login", urllib.parse.urlencode({"password": password}).encode())
    return status, body.decode(errors="replace"), cookie


def test_unauthenticated_gets_nothing_of_the_app(remote, port):
    s, app, gate = remote
    # viser itself is only on loopback, on another port
    assert app.server.get_port() != port
    # HTTP: the page redirects to the login form; anything else is 401
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=60) as r:
        body = r.read()
        assert r.url.endswith("/login") and b"Session password" in body and b"viser" not in body.lower()
    for path in ("/index.html", "/assets/index.js", "/manifest.json", "/?x=1", "/logout"):
        status, body, _ = _request(port, path)
        assert status in (401, 303) and len(body) < 100, (path, status)
    assert _request(app.server.get_port(), "/")[0] == 200  # (viser itself would serve it)
    # websocket: 401 before any upgrade, no scene/GUI bytes
    got = _raw_ws(port)
    assert got.startswith(b"HTTP/1.1 401") and b"101 Switching" not in got and _viser_payload(got) == b""
    assert APP_MARKER not in got and len(got) < 1000
    got = _raw_ws(port, cookie="forged-session-id")
    assert got.startswith(b"HTTP/1.1 401") and _viser_payload(got) == b"" and len(got) < 1000
    # the same handshake with a login cookie gets the app's messages (so the checks above can fail)
    status, _, cookie = _post_login(port, PASSWORD)
    assert status == 303 and cookie
    got = _raw_ws(port, cookie=cookie, read_s=60.0)
    assert got.startswith(b"HTTP/1.1 101") and APP_MARKER in _viser_payload(got)
    # a page of another origin cannot use the cookie's websocket
    got = _raw_ws(port, cookie=cookie, origin="http://evil.example:80")
    assert got.startswith(b"HTTP/1.1 403") and _viser_payload(got) == b"" and len(got) < 1000
    assert [e.code for e in s.audit_entries(code="login_ok")] == ["login_ok"]


def test_wrong_passwords_lock_the_login(remote, port):
    s, app, gate = remote
    for k in range(2):
        status, body, cookie = _post_login(port, f"wrong-{k}-password")
        assert status == 401 and cookie is None and "wrong password" in body
    status, body, cookie = _post_login(port, "wrong-again-pw")
    assert status == 401 and "locked for 5 s" in body
    status, body, cookie = _post_login(port, PASSWORD)  # right, but locked
    assert status == 401 and cookie is None and "locked" in body
    assert any(a.code == "login_lockout" for a in s.snapshot().alarms)
    assert len(s.audit_entries(code="login_refused")) == 4
    assert any(e.code == "login_lockout" for e in s.audit_entries(code="login_lockout"))
    assert all(PASSWORD not in e.message for e in s.audit_entries())
    # after the lockout the right password works and the alarm clears (the proxy's sweep)
    _wait(lambda: gate.locked_for() == 0, timeout=60, what="lockout end")
    status, _, cookie = _post_login(port, PASSWORD)
    assert status == 303 and cookie
    _wait(lambda: not any(a.code == "login_lockout" for a in s.snapshot().alarms), timeout=60,
          what="login_lockout alarm cleared")


# ---------------------------------------------------------------------------- a real browser
def test_browser_login_logout_expiry(remote, port, browser):
    s, app, gate = remote
    ctx = browser.new_context(viewport={"width": 1280, "height": 800})
    page = ctx.new_page()
    page.set_default_timeout(T_PAGE_MS)
    page.goto(app.url)
    page.locator("#mt-password").wait_for()
    assert page.locator("#mt-robot-state").count() == 0
    page.fill("#mt-password", "not-the-password")
    page.click("#mt-login")
    page.locator("#mt-login-error").wait_for()
    assert "wrong password" in page.locator("#mt-login-error").inner_text()
    page.fill("#mt-password", PASSWORD)
    page.click("#mt-login")
    page.locator("#mt-robot-state").wait_for()  # the app, over the proxied websocket
    assert page.get_by_role("button", name="STOP", exact=True).first.is_visible()
    assert not any(c["name"] == "mt_session" and not c["httpOnly"] for c in ctx.cookies())
    assert page.evaluate("document.cookie").find("mt_session") < 0  # HttpOnly: scripts cannot read it
    _wait(lambda: len(app.views()) == 1, what="the tab's view")
    # log out: back at the login page; the app is gone
    page.locator("#mt-logout").click()
    page.locator("#mt-password").wait_for()
    page.goto(app.url)
    page.locator("#mt-password").wait_for()
    _wait(lambda: len(app.views()) == 0, what="the logged-out tab's websocket closed")
    assert s.audit_entries(code="logout")
    # expiry: an open page is cut off when its login expires
    gate.ttl_s = 4.0
    page.fill("#mt-password", PASSWORD)
    page.click("#mt-login")
    page.locator("#mt-robot-state").wait_for()
    _wait(lambda: len(app.views()) == 1, what="the tab's view")
    _wait(lambda: s.audit_entries(code="login_expired"), what="the login expired")
    _wait(lambda: len(app.views()) == 0, what="the expired tab's websocket closed")
    page.locator("#mt-conn-lost").wait_for(state="visible")
    page.reload()
    page.locator("#mt-password").wait_for()
    ctx.close()


def test_serve_allow_remote_prints_password_and_gates(tmp_path, port):
    """``serve --allow-remote`` without a password: a random one on the console, the page gated."""
    import signal

    env = {"PYTHONPATH": str(Path(__file__).resolve().parents[2] / "app"), "PATH": "/usr/bin:/bin",
           "HOME": str(tmp_path), "PYTHONUNBUFFERED": "1"}
    p = subprocess.Popen([sys.executable, "-m", "monotracker", "serve", "--home", str(tmp_path), "--port", str(port),
                          "--allow-remote", "--host", "127.0.0.1", "--pin", "2468"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, encoding="utf-8", errors="replace", env=env)
    try:
        lines = []
        while not any(ln.startswith("session password for the page:") for ln in lines):
            ln = p.stdout.readline()
            assert ln, "serve ended early:\n" + "".join(lines)
            lines.append(ln)
        password = [ln for ln in lines if ln.startswith("session password")][0].split(":", 1)[1].split()[0]
        assert any("needs a login" in ln for ln in lines)
        assert len(password) >= 12
        assert _request(port, "/")[0] == 303
        assert _post_login(port, "wrong-password")[0] == 401
        status, _, cookie = _post_login(port, password)
        assert status == 303 and cookie
    finally:
        p.send_signal(signal.SIGTERM)
        p.wait(timeout=120)


"""viser's message buffer fed from several threads: the ``deque mutated during iteration`` race
(``render failed ...`` in the server log under load) and its fix (ui/viser_threads.py).

The race is reproduced on the call viser makes (``asyncio.Event.set()`` from a thread that is not
the event loop's, while the loop's tasks wait on the event): with a tiny thread switch interval
the plain event fails within seconds (checked here, so the test can fail); the fixed event never
does and still wakes its waiters. viser's own ``AsyncMessageBuffer`` with the fix, fed from two
threads with six senders, raises nothing and every sender drains it; the web app installs the fix
on the broadcast buffer and on every tab's buffer.
"""

from __future__ import annotations

import asyncio
import os
import sys
import threading
import time

import pytest
from browser_helpers import APP_OPTIONS, open_page

pytestmark = pytest.mark.timeout(300)
CLIENTS = 6
#: how long (s) the unfixed event is hammered to show the race. On some machines/Pythons the race
#: never shows (CI: none in 415984 tries over 120 s, none in 41024 tries over 15 s here; the test
#: skips), so a long default only costs suite time there: the fix is proven deterministically by
#: :func:`test_set_from_another_thread_leaves_the_waiters_to_the_loop` (issue 35: this hunt and the
#: two stress runs of the fixed event took 40 s of the serial lane at 15 + 15 + 10 s). Hunt longer
#: with MONOTRACKER_RACE_HUNT_S=120.
RACE_HUNT_S = float(os.environ.get("MONOTRACKER_RACE_HUNT_S", "5"))
#: how long (s) the fixed event and the fixed buffer are hammered from threads: a stress check that
#: they keep waking and draining under thread switches every microsecond (thousands of calls); the
#: race's cause is checked deterministically (below); MONOTRACKER_RACE_HUNT_S makes these longer too
STRESS_S = max(3.0, float(os.environ.get("MONOTRACKER_RACE_HUNT_S", "3")))


def _cancel_and_stop(loop, tasks: list, thread) -> None:
    """From another thread: cancel ``tasks`` and stop ``loop`` (one call on the loop), then join
    the loop's ``thread``, which ends them with :func:`_end_tasks_and_close`."""
    def stop():
        for t in tasks:
            t.cancel()
        loop.stop()

    loop.call_soon_threadsafe(stop)
    thread.join(30)


def _end_tasks_and_close(loop, tasks: list) -> None:
    """On the loop's thread once ``run_forever()`` returned: the cancelled tasks end on the loop,
    then it closes (a task left pending printed "Task was destroyed but it is pending!" when the
    serial lane's process exited)."""
    loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
    loop.close()


def _hammer(fixed: bool, seconds: float) -> tuple[list[str], int, int]:
    """Push updates from 2 threads into a buffer whose sender runs on its loop; (errors, pushed, received)."""
    from viser import _messages
    from viser.infra._async_message_buffer import AsyncMessageBuffer

    from monotracker.ui.viser_threads import LoopSafeEvent, make_thread_safe

    loop = asyncio.new_event_loop()
    ready = threading.Event()
    buf_box = {}
    received = [0]

    async def consume(buf, client_id):
        try:
            async for window in buf.window_generator(client_id):
                received[0] += len(window)
        except asyncio.CancelledError:
            pass

    def run_loop():
        asyncio.set_event_loop(loop)
        # like the broadcast buffer (server.gui / server.scene) with several tabs: one sender each
        buf = AsyncMessageBuffer(loop, persistent_messages=True)
        if fixed:
            assert make_thread_safe(buf) and isinstance(buf.message_event, LoopSafeEvent)
        buf_box["buf"] = buf
        buf_box["tasks"] = [loop.create_task(consume(buf, k)) for k in range(CLIENTS)]
        ready.set()
        loop.run_forever()
        _end_tasks_and_close(loop, buf_box["tasks"])

    th = threading.Thread(target=run_loop, daemon=True)
    th.start()
    assert ready.wait(30)
    buf = buf_box["buf"]
    errors: list[str] = []
    pushed = [0]
    stop = threading.Event()

    def pusher(k):
        i = 0
        while not stop.is_set():
            try:
                buf.push(_messages.GuiUpdateMessage(f"elem{k}-{i % 50}", {"content": str(i)}))
                pushed[0] += 1
            except RuntimeError as exc:
                errors.append(str(exc))
            i += 1
            time.sleep(0.002 * (i % 10))  # idle gaps: the senders go back to waiting on the event

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        ps = [threading.Thread(target=pusher, args=(k,), daemon=True) for k in range(2)]
        for p in ps:
            p.start()
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds and not errors:
            time.sleep(0.05)
        stop.set()
        for p in ps:
            p.join(30)
    finally:
        sys.setswitchinterval(old)
    # the sender still drains what was pushed (nothing left waiting for a wake-up that never comes)
    t0 = time.monotonic()
    def behind():
        return [k for k in range(CLIENTS) if buf.generator_cursors.get(k, -1) < buf.message_counter - 1]

    while time.monotonic() - t0 < 30 and behind():
        time.sleep(0.05)
    drained = not behind()
    _cancel_and_stop(loop, buf_box["tasks"], th)
    assert drained, "the sender stopped draining the buffer"
    return errors, pushed[0], received[0]


def _event_race(fixed: bool, seconds: float) -> tuple[int, int, int]:
    """``Event.set()`` from this thread (as viser's ``push()`` does) while 8 tasks on the loop wait
    on the event with timeouts (their waiter futures come and go); (calls, errors, wake-ups)."""
    from monotracker.ui.viser_threads import LoopSafeEvent

    loop = asyncio.new_event_loop()
    ev = asyncio.Event()
    if fixed:
        ev.__class__ = LoopSafeEvent
        ev._mt_loop = loop
    woken = [0]

    async def waiter():
        while True:
            try:
                await asyncio.wait_for(ev.wait(), 0.001)
                woken[0] += 1
            except asyncio.TimeoutError:
                pass
            ev.clear()

    tasks: list = []

    def run():
        asyncio.set_event_loop(loop)
        for _ in range(8):
            tasks.append(loop.create_task(waiter()))
        loop.run_forever()
        _end_tasks_and_close(loop, tasks)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    calls = errors = 0
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds and not (errors and not fixed):
            try:
                ev.set()
                loop.call_soon_threadsafe(ev.set)  # what push() does next
            except asyncio.InvalidStateError:
                errors += 1  # the same race seen from the other side: a waiter's future was
                # cancelled (its wait_for timed out) on the loop between done() and set_result()
            except RuntimeError as exc:
                assert "deque mutated during iteration" in str(exc)
                errors += 1
            calls += 1
            time.sleep(0.0002)
    finally:
        sys.setswitchinterval(old)
        _cancel_and_stop(loop, tasks, th)
    return calls, errors, woken[0]


def _set_from(ev, thread_loop=None):
    """``ev.set()`` called from a new thread (which runs ``thread_loop`` while it calls, if given)."""
    async def on_loop():
        ev.set()

    th = threading.Thread(target=lambda: ev.set() if thread_loop is None else thread_loop.run_until_complete(on_loop()))
    th.start()
    th.join(30)


@pytest.mark.parametrize("other_loop", [False, True], ids=["plain-thread", "thread-running-another-loop"])
def test_set_from_another_thread_leaves_the_waiters_to_the_loop(other_loop):
    """The race's cause, checked without hunting for it: ``set()`` from a thread that is not the
    event loop's touches the waiters (``_waiters``, the deque the loop thread mutates) there, where
    the loop's own tasks add and remove them; the fixed event only marks the flag and the loop
    wakes them. Deterministic: the plain ``asyncio.Event`` fails this at once (the hunt below needs
    the race to show within its time, which it never did in CI). The loop is not running while
    the other thread calls ``set()``, so nothing but that thread can touch the waiter."""
    from monotracker.ui.viser_threads import LoopSafeEvent

    loop = asyncio.new_event_loop()
    other = asyncio.new_event_loop() if other_loop else None
    try:
        ev = asyncio.Event()
        ev.__class__ = LoopSafeEvent
        ev._mt_loop = loop
        waiter = loop.create_future()
        ev._waiters.append(waiter)  # what ``await ev.wait()`` on the loop leaves there
        _set_from(ev, other)
        assert ev.is_set()  # viser's synchronous readers see the flag at once
        assert not waiter.done(), "set() from another thread woke a waiter there (the race)"
        # the loop wakes it (push() asks for this with call_soon_threadsafe(message_event.set)); run
        # on a thread of its own: this one may have a loop running already (Playwright's, when a
        # browser test ran before in this process)
        loop.call_soon_threadsafe(ev.set)
        woke = {}

        def run_loop():
            woke["result"] = loop.run_until_complete(asyncio.wait_for(waiter, 5))

        th = threading.Thread(target=run_loop)
        th.start()
        th.join(30)
        assert woke.get("result") is True
    finally:
        loop.close()
        if other is not None:
            other.close()


@pytest.mark.realtime
def test_unfixed_event_races():
    """The race is real (else the fix below is not proven by anything). Real time: hammers the
    event for :data:`RACE_HUNT_S` s of wall clock (never retried)."""
    calls, errors, woken = _event_race(fixed=False, seconds=RACE_HUNT_S)
    if not errors:
        pytest.skip(f"no race in {calls} tries on this machine/Python (asyncio.Event.set from another thread)")
    assert errors >= 1


@pytest.mark.realtime
def test_loop_safe_event_does_not_race_and_wakes():
    calls, errors, woken = _event_race(fixed=True, seconds=STRESS_S)
    assert errors == 0 and calls > 1000
    assert woken > 0  # waiters are still woken (by the loop)


@pytest.mark.realtime
def test_fixed_viser_buffer_does_not_race():
    """viser's buffer with the fix, fed from 2 threads with 6 senders: no error, every sender drains it."""
    errors, pushed, received = _hammer(fixed=True, seconds=STRESS_S)
    assert errors == []
    assert pushed > 100 and received > 0


def test_app_protects_its_buffers(tmp_path, port, browser):
    """The web app puts the fix on the broadcast buffer and on every tab's own buffer."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp
    from monotracker.ui.viser_threads import LoopSafeEvent

    s = Session(SessionConfig(home=tmp_path, arm_pin="2468"))
    app = MonoTrackerApp(s, "127.0.0.1", port, **APP_OPTIONS)
    app.start()
    try:
        assert isinstance(app.server._websock_server._broadcast_buffer.message_event, LoopSafeEvent)
        page = open_page(browser, app, (1280, 800), ready="#mt-robot-state")
        views = app.views()
        assert len(views) == 1
        buf = views[0].client._websock_connection.get_message_buffer()
        assert isinstance(buf.message_event, LoopSafeEvent)
        # the page still follows the session (updates pushed from the render thread reach it)
        assert "nobody" in page.locator("#mt-control").inner_text()
        assert s.claim_control("desk-9", "2468", "nurse desk").ok
        page.wait_for_function("document.querySelector('#mt-control').innerText.includes('nurse desk')",
                               timeout=120_000)
        page.close()
    finally:
        app.stop()
        s.shutdown()


def test_tab_caught_up_reads_the_tabs_buffer():
    """The overlay encodes a new frame only when some tab has taken what was queued for it."""
    from types import SimpleNamespace as NS

    from monotracker.ui.viser_threads import tab_caught_up

    def client(counter, cursor):
        buf = NS(message_counter=counter, generator_cursors={} if cursor is None else {7: cursor})
        return NS(client_id=7, _websock_connection=NS(get_message_buffer=lambda: buf))

    assert tab_caught_up(client(10, 9))  # message ids 0..9 all taken
    assert not tab_caught_up(client(10, 8))  # one still queued
    assert not tab_caught_up(client(10, None))  # its sender has taken nothing yet
    assert tab_caught_up(NS(client_id=7))  # unreadable (another viser): never wait on it

"""A thread-safety fix for viser's message buffers (the ``deque mutated during iteration`` race).

viser (1.1.x) wakes a connection's sender with ``AsyncMessageBuffer.message_event``, an
``asyncio.Event``. Its ``push()`` - run by whichever thread assigns a GUI or scene property, here
the render thread, the overlay thread and viser's callback workers - calls
``message_event.set()`` directly, and ``asyncio.Event.set`` is not thread-safe: it iterates the
event's ``_waiters`` deque while the event-loop thread adds and removes waiters
(``await message_event.wait()``, cancelled flush waits). Under load a thread switch lands inside
that loop and the assigning thread gets ``RuntimeError: deque mutated during iteration`` (the
``render failed ...`` / ``overlay failed`` lines in the server log; the tab misses that update),
or, when the switch lands between ``fut.done()`` and ``fut.set_result()`` while the loop cancels
that waiter, ``asyncio.InvalidStateError`` (seen once in CI).

:func:`make_thread_safe` switches one buffer's event to :class:`LoopSafeEvent` (same object, so
a sender already waiting on it stays woken): called from the event loop's own thread it is the
plain ``asyncio.Event``; from any other thread ``set()`` only marks the flag (what viser's
synchronous readers look at) and leaves waking the waiters to the loop, which ``push()`` already
asks for with ``call_soon_threadsafe(message_event.set)`` (or ``atomic_end()`` / ``set_done()``
do).

:func:`tab_caught_up` reads the same buffer: whether a tab's connection has taken everything
queued for it (the overlay stream encodes a new frame only when some tab can take it).
"""

from __future__ import annotations

import asyncio
import logging

log = logging.getLogger(__name__)


class LoopSafeEvent(asyncio.Event):
    """An ``asyncio.Event`` whose ``set()`` may be called from any thread (see module docstring).
    ``loop``: the event loop whose thread may wake the waiters (``_mt_loop``)."""

    _mt_loop: asyncio.AbstractEventLoop | None = None

    def set(self) -> None:
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is not None and (self._mt_loop is None or running is self._mt_loop):
            self._value = True  # on the loop: wake every waiter (even if another thread set the flag first)
            for fut in list(self._waiters):
                if not fut.done():
                    fut.set_result(True)
            return
        self._value = True  # another thread: the flag only; the loop wakes the waiters


def make_thread_safe(buffer) -> bool:
    """Make viser ``AsyncMessageBuffer`` ``buffer``'s ``message_event`` a :class:`LoopSafeEvent`
    (in place). True when done (or already so); False if the buffer does not look as expected
    (another viser version: logged once, nothing changed)."""
    ev = getattr(buffer, "message_event", None)
    if isinstance(ev, LoopSafeEvent):
        return True
    if type(ev) is not asyncio.Event:
        log.warning("viser message buffer without an asyncio.Event (%r): thread-safety fix not applied", type(ev))
        return False
    ev.__class__ = LoopSafeEvent
    ev._mt_loop = getattr(buffer, "event_loop", None)
    return True


def protect_server(server) -> bool:
    """The fix on a ``viser.ViserServer``'s broadcast buffer (``server.scene`` / ``server.gui``)."""
    try:
        return make_thread_safe(server._websock_server._broadcast_buffer)
    except AttributeError:
        log.warning("viser server layout changed: broadcast buffer not found, thread-safety fix not applied")
        return False


def protect_client(client) -> bool:
    """The fix on one ``viser.ClientHandle``'s own buffer (``client.gui`` / ``client.scene``)."""
    try:
        return make_thread_safe(client._websock_connection.get_message_buffer())
    except AttributeError:
        log.warning("viser client layout changed: message buffer not found, thread-safety fix not applied")
        return False


def tab_caught_up(client) -> bool:
    """True when viser has handed everything queued for ``client`` (a ``viser.ClientHandle``) to
    its connection (the tab is keeping up); True as well when that cannot be read (another
    viser version), so the caller never waits on it."""
    try:
        buf = client._websock_connection.get_message_buffer()
        return buf.generator_cursors.get(client.client_id, -1) >= buf.message_counter - 1
    except (AttributeError, TypeError):
        return True

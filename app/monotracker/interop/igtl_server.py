"""The OpenIGTLink TCP server under :class:`~monotracker.interop.igtl.IGTLStreamer`: many clients,
none of which can slow the engine or another client.

pyigtl's own server handles one connection at a time on a blocking socket and reads whatever body
size a header declares into a growing ``bytes`` (a client declaring a 1 GB body held the GIL
copying it: tracking fell from 90 % to 10 % of frames; a client that connected and never read
blocked every other client). This server keeps pyigtl for the messages (``pack``) and replaces
the transport with one :mod:`asyncio` event loop on its own thread:

* **bound**: 127.0.0.1 unless the caller allows every interface (as the web app); at most
  ``max_clients`` at a time (more are closed at once, logged).
* **reads bounded**: the server never needs a client's messages; it reads each 58-byte header
  and skips the body, but a header declaring more than ``max_body`` bytes (64 KiB) ends the
  connection. Nothing a client sends is kept.
* **per-client queues**: :meth:`IGTLServer.broadcast` (any thread) only hands the packed bytes to
  the loop; each client has its own bounded queue (``queue_len`` messages, the oldest dropped
  first and counted); a client that accepts no bytes for ``send_timeout_s`` (2 s) is dropped.
* ``on_event(code, message, data)``: connections, departures and drops (the streamer writes them
  to the audit log: who received patient data, and when).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import socket
import struct
import threading

from monotracker.errors import InputError

log = logging.getLogger(__name__)

HEADER_SIZE = 58  # OpenIGTLink v1/v2 header: version, type, device, timestamp, body size, CRC
MAX_BODY = 64 * 1024
SEND_TIMEOUT_S = 2.0
#: messages per client queue: ~10 s of the stream at 30 poses/s (3 messages each), so a client
#: that falls behind during a burst loses none; one that stops reading is dropped after 2 s anyway
QUEUE_LEN = 1024
MAX_CLIENTS = 8


class _Refused(Exception):
    """A client broke a rule (one line): the connection is closed."""


class _Client:
    def __init__(self, peer: str, queue_len: int):
        self.peer = peer
        self.queue: collections.deque = collections.deque(maxlen=queue_len)
        self.wake = asyncio.Event()
        self.dropped = 0  # messages dropped from this client's full queue
        self.sent = 0


class IGTLServer:
    """See the module docstring. ``host``: the interface to bind; ``port`` (0: any free one)."""

    def __init__(self, host: str, port: int, *, max_clients: int = MAX_CLIENTS, queue_len: int = QUEUE_LEN,
                 send_timeout_s: float = SEND_TIMEOUT_S, max_body: int = MAX_BODY, on_event=None):
        self.host, self.port = host, int(port)
        self.max_clients = int(max_clients)
        self.queue_len = int(queue_len)
        self.send_timeout_s = float(send_timeout_s)
        self.max_body = int(max_body)
        self.on_event = on_event or (lambda code, message, data: None)
        self.on_connect = None  # called (loop thread) when a client connects
        self._clients: set[_Client] = set()
        self._n = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server = None
        self._sock = self._bind()

    def _bind(self) -> socket.socket:
        try:
            sock = socket.create_server((self.host, self.port), reuse_port=False)
        except OSError as exc:
            raise InputError(f"cannot serve OpenIGTLink on {self.host}:{self.port}: {exc.strerror or exc}; choose "
                             "another --igtl-port") from None
        self.port = sock.getsockname()[1]
        return sock

    # ------------------------------------------------------------------ life cycle
    def start(self) -> "IGTLServer":
        ready = threading.Event()

        def run() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            asyncio.set_event_loop(loop)

            async def main():
                self._server = await asyncio.start_server(self._handle, sock=self._sock)
                ready.set()

            loop.run_until_complete(main())
            loop.run_forever()
            loop.close()

        self._thread = threading.Thread(target=run, name="monotracker-igtl-server", daemon=True)
        self._thread.start()
        ready.wait(10.0)
        return self

    def stop(self) -> None:
        loop = self._loop
        if loop is None:
            return

        async def shutdown():
            if self._server is not None:
                self._server.close()
            for task in [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]:
                task.cancel()

        try:
            asyncio.run_coroutine_threadsafe(shutdown(), loop).result(5.0)
        except Exception:  # closing must not raise at shutdown
            log.exception("stopping the OpenIGTLink server failed")
        loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(5.0)
        self._loop = None

    # ------------------------------------------------------------------ any thread
    def is_connected(self) -> bool:
        """True while at least one client is connected."""
        return self._n > 0

    @property
    def clients(self) -> int:
        return self._n

    def broadcast(self, data: bytes) -> None:
        """Queue one packed message for every connected client (never blocks)."""
        loop = self._loop
        if loop is None or self._n == 0:
            return
        try:
            loop.call_soon_threadsafe(self._fanout, data)
        except RuntimeError:  # the loop closed meanwhile
            pass

    # ------------------------------------------------------------------ the loop's thread
    def _fanout(self, data: bytes) -> None:
        for c in self._clients:
            if len(c.queue) == c.queue.maxlen:
                c.dropped += 1
            c.queue.append(data)
            c.wake.set()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        addr = writer.get_extra_info("peername")
        peer = f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr)
        if len(self._clients) >= self.max_clients:
            self.on_event("igtl_client_refused", f"OpenIGTLink client {peer} refused: {self.max_clients} clients "
                          "connected already", {"peer": peer})
            writer.close()
            return
        c = _Client(peer, self.queue_len)
        self._clients.add(c)
        self._n = len(self._clients)
        self.on_event("igtl_client_connected", f"OpenIGTLink client {peer} connected", {"peer": peer})
        if self.on_connect is not None:
            self.on_connect()
        reading = asyncio.ensure_future(self._read(reader))
        why = "left"
        try:
            while True:
                waiting = asyncio.ensure_future(c.wake.wait())
                done, _ = await asyncio.wait({waiting, reading}, return_when=asyncio.FIRST_COMPLETED)
                if reading in done:
                    waiting.cancel()
                    exc = reading.exception()
                    why = str(exc) if isinstance(exc, _Refused) else "left"
                    break
                c.wake.clear()
                while c.queue:
                    writer.write(c.queue.popleft())
                    try:
                        await asyncio.wait_for(writer.drain(), self.send_timeout_s)
                    except asyncio.TimeoutError:
                        raise _Refused(f"it accepted no data for {self.send_timeout_s:g} s (not reading)") from None
                    c.sent += 1
        except _Refused as exc:
            why = str(exc)
        except (ConnectionError, OSError):
            why = "left"
        except asyncio.CancelledError:
            # the server stops: end normally (Python 3.11's stream callback calls exception() on
            # a cancelled handler task and prints a traceback)
            why = "left"
        finally:
            reading.cancel()
            self._clients.discard(c)
            self._n = len(self._clients)
            try:
                writer.transport.abort()
            except Exception:  # noqa: BLE001
                pass
            level = "info" if why == "left" else "warning"
            code = "igtl_client_left" if why == "left" else "igtl_client_dropped"
            msg = (f"OpenIGTLink client {peer} " + ("disconnected" if why == "left" else f"dropped: {why}")
                   + (f" ({c.dropped} messages dropped from its queue)" if c.dropped else ""))
            self.on_event(code, msg, {"peer": peer, "sent": c.sent, "dropped": c.dropped, "level": level})

    async def _read(self, reader: asyncio.StreamReader) -> None:
        """Read and discard what the client sends, header by header; returns when it leaves,
        raises :class:`_Refused` for a body over ``max_body``."""
        while True:
            try:
                header = await reader.readexactly(HEADER_SIZE)
            except (asyncio.IncompleteReadError, ConnectionError, OSError):
                return
            (body,) = struct.unpack(">Q", header[42:50])
            if body > self.max_body:
                raise _Refused(f"it declared a message body of {body} bytes (the server reads at most "
                               f"{self.max_body})")
            left = body
            while left:
                try:
                    chunk = await reader.read(min(left, 65536))
                except (ConnectionError, OSError):
                    return
                if not chunk:
                    return
                left -= len(chunk)

"""The digital twin's camera as hardware: rendered in its own process, frames handed over in
shared memory, the way a real camera delivers them by DMA without costing the app CPU or GIL.

clock="real" only (clock="sim" renders in lock-step on the engine thread, deterministically).
Rendering a 1280x720 frame of the twin costs ~11 ms of CPU (~20 ms on a loaded machine); inside
the engine process it competed with detection, registration, the web server and the overlay for
the one GIL and pushed every pose older. Here a ``spawn``-ed child renders the scene at the
camera rate on the shared monotonic clock (``time.monotonic`` is system-wide on Linux):

* at each camera tick ``T`` it renders the exposure ``t = T - transport_delay_s + r`` (``r`` the
  running estimate of its render time, at most the transport delay) and hands the frame over at
  ``t + transport_delay_s`` at the earliest: never sooner than a real camera would deliver it,
  later only when the render overran (that lateness is pose age, as it would be);
* frames go into a ring of ``SLOTS`` shared-memory slots, each guarded by a sequence number
  written before and after the pixels (a reader that was overtaken discards the frame instead
  of reading a torn image); a pipe carries ``(slot, index, t_capture, truth)``;
* the reader (:meth:`SimCameraProcess.next_frame`) always takes the newest frame and drops older
  ones, like a camera driver's ring buffer;
* the child runs at normal priority or below (``nice`` >= 0; never real-time: the priority
  policy, ``engine/pipeline_priority.py``), and ends when its parent closes the pipe or dies.

Faults that the engine injects (freeze, occlusion) are applied by the rig to the frame it reads,
as before; the child renders the scene only, with the camera moved in the room when a
camera-motion fault (``camera-bump``, ``camera-sag``) is set (:meth:`SimCameraProcess.set_camera_motion`:
control words 2-3, the fault's index in ``CAMERA_MOTION_FAULTS`` + 1 and its start, monotonic us).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import threading
import time

import numpy as np

from monotracker.errors import MonoTrackerError

log = logging.getLogger(__name__)

#: frames in the shared ring (4 at 30 fps: a reader may be ~100 ms late before it is overtaken)
SLOTS = 4
_CTRL = 64  # control block: int64 [newest index, stop flag, ...]
_META = 32  # per slot: int64 sequence, float64 t_capture, float64 render s, int64 truth bytes
_TRUTH_MAX = 16384  # per slot: the pickled FrameTruth (~1.2 kB)


def _slot_layout(size: int, slot: int) -> tuple[int, int, int, int]:
    """Offsets of one slot: (meta, truth, image, tail sequence)."""
    base = _CTRL + slot * (_META + _TRUTH_MAX + size + 8)
    return base, base + _META, base + _META + _TRUTH_MAX, base + _META + _TRUTH_MAX + size


def _total_size(size: int) -> int:
    return _CTRL + SLOTS * (_META + _TRUTH_MAX + size + 8)


def _child(wake_fd_holder, shm_name: str, shape: tuple, cam_kwargs: dict, fps: float, delay_s: float,
           nice: int) -> None:
    """The camera process: render at ``fps`` on the monotonic clock until the parent says stop
    (control flag) or dies. It never waits on the parent: the wake-up byte is written without
    blocking (a reader that is behind wants only the newest frame anyway)."""
    import pickle
    from multiprocessing import shared_memory

    from monotracker.engine.pipeline_priority import normal_priority
    from monotracker.sim.camera_sim import SimulatedCamera

    priority = normal_priority(nice)  # hardware's stand-in: never above the web server or the STOP path
    parent = os.getppid()
    shm = shared_memory.SharedMemory(name=shm_name)
    # (the spawn-ed child shares its parent's resource tracker: the parent's unlink unregisters it)
    conn = wake_fd_holder
    cam = None
    try:
        ctrl = np.ndarray((8,), np.int64, shm.buf, 0)
        cam = SimulatedCamera(**cam_kwargs)
        h, w, c = shape
        size = h * w * c
        img, _ = cam.render(time.monotonic())  # warm up (first-call costs, the ring's pages)
        for slot in range(SLOTS):
            np.ndarray(shape, np.uint8, shm.buf, _slot_layout(size, slot)[2])[...] = img
        conn.send(("ready", os.getpid(), priority))
        fd = conn.fileno()
        os.set_blocking(fd, False)
        period = 1.0 / fps
        t_next = time.monotonic()
        render_s = 0.0
        index = 0
        motion_word = 0
        while ctrl[1] == 0 and os.getppid() == parent:
            if ctrl[2] != motion_word:   # the parent set (or cleared) a camera-motion fault
                from monotracker.sim.faults import CAMERA_MOTION_FAULTS, CameraMotion

                motion_word = int(ctrl[2])
                cam.camera_motion = (None if motion_word <= 0 else
                                     CameraMotion(CAMERA_MOTION_FAULTS[motion_word - 1], float(ctrl[3]) * 1e-6))
            now = time.monotonic()
            if now < t_next:
                time.sleep(min(t_next - now, 0.05))
                continue
            t_next = max(t_next + period, now)  # drop frames rather than queue them
            ahead = min(render_s, delay_s)
            t_exp = now - delay_s + ahead
            w0 = time.monotonic()
            img, truth = cam.render(t_exp)
            w1 = time.monotonic()
            render_s = (w1 - w0) if render_s == 0.0 else 0.8 * render_s + 0.2 * (w1 - w0)
            blob = pickle.dumps(truth, protocol=pickle.HIGHEST_PROTOCOL)
            if len(blob) > _TRUTH_MAX:
                blob = b""  # never expected (~1.2 kB); the reader then refuses the frame
            index += 1
            slot = index % SLOTS
            m, tpos, ipos, tail = _slot_layout(size, slot)
            meta_i = np.ndarray((4,), np.int64, shm.buf, m)
            meta_f = np.ndarray((4,), np.float64, shm.buf, m)
            meta_i[0] = -1  # being written
            meta_f[1], meta_f[2] = t_exp, w1 - w0
            meta_i[3] = len(blob)
            shm.buf[tpos:tpos + len(blob)] = blob
            np.ndarray(shape, np.uint8, shm.buf, ipos)[...] = img
            np.ndarray((1,), np.int64, shm.buf, tail)[0] = index
            meta_i[0] = index
            hold = t_exp + delay_s - time.monotonic()
            if hold > 0:  # rendered faster than the camera delivers: wait for the hand-over
                time.sleep(hold)
            ctrl[0] = index
            try:
                os.write(fd, b"f")
            except BlockingIOError:
                pass  # the reader is behind: it takes the newest frame when it comes back
    except (EOFError, BrokenPipeError, OSError):
        return  # the parent went away
    finally:
        del cam
        try:
            shm.close()
        except BufferError:
            pass  # views still alive in this frame; the process ends anyway


class SimCameraProcess:
    """A rendering child process for a :class:`~monotracker.sim.camera_sim.SimulatedCamera`.

    ``cam_kwargs``: the camera's constructor arguments (picklable: trajectory object, fps, seed,
    ``T_cam_world``, optics); ``image_size`` (w, h) px; ``delay_s`` the modelled transport delay;
    ``nice`` the child's nice value (>= 0, ``pipeline_priority.normal_priority``).
    :meth:`start` waits until the child renders (``ready_timeout_s``) and raises
    :class:`MonoTrackerError` with one line when it cannot."""

    def __init__(self, cam_kwargs: dict, image_size: tuple, fps: float, delay_s: float, nice: int = 0):
        w, h = int(image_size[0]), int(image_size[1])
        self.shape = (h, w, 3)
        self.size = h * w * 3
        self.cam_kwargs, self.fps, self.delay_s, self.nice = cam_kwargs, float(fps), float(delay_s), int(nice)
        self.pid: int | None = None
        self.priority = ""
        self._shm = None
        self._proc = None
        self._conn = None
        self._last = 0
        self._lock = threading.Lock()

    def start(self, ready_timeout_s: float = 60.0) -> None:
        from multiprocessing import shared_memory

        ctx = mp.get_context("spawn")
        self._shm = shared_memory.SharedMemory(create=True, size=_total_size(self.size))
        np.ndarray((8,), np.int64, self._shm.buf, 0)[...] = 0
        parent, child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(target=_child, name="monotracker-simcam-render", daemon=True,
                                 args=(child, self._shm.name, self.shape, self.cam_kwargs, self.fps, self.delay_s,
                                       self.nice))
        try:
            self._proc.start()
            child.close()
            self._conn = parent
            if not parent.poll(ready_timeout_s):
                raise MonoTrackerError(f"simulated camera process did not start within {ready_timeout_s:.0f} s")
            _, self.pid, self.priority = parent.recv()
        except MonoTrackerError:
            self.close()
            raise
        except Exception as exc:  # noqa: BLE001 - EOF (the child died), a spawn refused, ...
            self.close()
            raise MonoTrackerError(f"simulated camera process failed to start ({type(exc).__name__})") from None
        os.set_blocking(parent.fileno(), False)

    def next_frame(self, timeout_s: float):
        """The newest rendered frame as ``(image, index, t_capture, truth, render_s)`` (image a
        private copy), or None when no new one came within ``timeout_s`` or the newest one was
        overwritten while being read (never a torn image). Older frames are skipped."""
        import pickle
        import select

        conn, shm = self._conn, self._shm
        if conn is None or shm is None:
            return None
        fd = conn.fileno()
        try:
            ready, _, _ = select.select([fd], [], [], timeout_s)
            if ready:
                while True:  # drain the wake-up bytes
                    try:
                        if not os.read(fd, 4096):
                            break
                    except BlockingIOError:
                        break
        except (OSError, ValueError):
            return None
        buf = shm.buf
        index = int(np.ndarray((8,), np.int64, buf, 0)[0])
        if index <= self._last:
            return None
        m, tpos, ipos, tail = _slot_layout(self.size, index % SLOTS)
        meta_i = np.ndarray((4,), np.int64, buf, m)
        meta_f = np.ndarray((4,), np.float64, buf, m)
        seq = int(meta_i[0])
        t_capture, render_s, n = float(meta_f[1]), float(meta_f[2]), int(meta_i[3])
        blob = bytes(buf[tpos:tpos + n])
        img = np.ndarray(self.shape, np.uint8, buf, ipos).copy()
        if not (seq == index == int(np.ndarray((1,), np.int64, buf, tail)[0]) == int(meta_i[0])) or n == 0:
            return None  # overtaken by the renderer while copying
        self._last = index
        return img, index, t_capture, pickle.loads(blob), render_s

    def set_camera_motion(self, kind: str | None) -> None:
        """Move the rendered camera from now on (``kind`` one of ``CAMERA_MOTION_FAULTS``), or put
        it back (None)."""
        from monotracker.sim.faults import CAMERA_MOTION_FAULTS

        shm = self._shm
        if shm is None:
            return
        ctrl = np.ndarray((8,), np.int64, shm.buf, 0)
        ctrl[3] = int(time.monotonic() * 1e6)
        ctrl[2] = 0 if kind is None else CAMERA_MOTION_FAULTS.index(kind) + 1

    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def close(self) -> None:
        with self._lock:
            conn, proc, shm = self._conn, self._proc, self._shm
            self._conn = self._proc = self._shm = None
        if shm is not None:
            np.ndarray((8,), np.int64, shm.buf, 0)[1] = 1  # stop
        if proc is not None and proc.pid is not None:  # never started (start() failed): nothing to join
            proc.join(2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(2.0)
        if conn is not None:
            conn.close()
        if shm is not None:
            shm.close()
            try:
                shm.unlink()
            except FileNotFoundError:
                pass

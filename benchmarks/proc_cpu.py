"""CPU use of this process's threads and of every child process (Linux ``/proc``), between two
snapshots: which part of a benchmark the cores went to (the server's threads, the browsers).

    a = snapshot(); ...; by_class, by_thread = cpu_use(a, snapshot(), wall_s)

Values are cores (CPU s per wall s: 1.0 = one core busy). Child processes are classed by their
command line (``chromium renderer`` / ``chromium gpu`` / ``chromium browser`` / ...); this
process's threads by their Python thread name. Elsewhere than Linux the snapshots are empty.
"""

from __future__ import annotations

import os
import threading

_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _stat(path: str) -> tuple[str, list[str]]:
    with open(path) as f:
        s = f.read()
    return s[s.index("(") + 1:s.rindex(")")], s[s.rindex(")") + 2:].split()


def _cpu_s(fields: list[str]) -> float:
    return (int(fields[11]) + int(fields[12])) / _TCK  # utime + stime


def _descendants(pid: int) -> list[int]:
    todo, out = [pid], []
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for tid in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{tid}/children") as f:
                    todo += [int(x) for x in f.read().split()]
        except OSError:
            pass
    return out[1:]


def _classify(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            raw = f.read()
        # a zygote-forked chromium child rewrites its argv as one space-joined string
        argv = [a.decode(errors="replace") for a in raw.replace(b"\0", b" ").split(b" ") if a]
    except OSError:
        return "gone"
    exe = os.path.basename(argv[0]) if argv else "?"
    if "chrom" in exe:
        kind = next((a.split("=", 1)[1] for a in argv if a.startswith("--type=")), "browser")
        return {"gpu-process": "chromium gpu"}.get(kind, f"chromium {kind}")
    return "playwright driver (node)" if exe.startswith("node") else exe


def snapshot() -> dict[tuple[str, object], float]:
    """CPU seconds so far: {("server python", thread name) | (process class, pid): s}."""
    out: dict[tuple[str, object], float] = {}
    if not os.path.isdir("/proc/self/task"):
        return out
    me = os.getpid()
    names = {t.native_id: t.name for t in threading.enumerate()}
    for tid in os.listdir(f"/proc/{me}/task"):
        try:
            comm, f = _stat(f"/proc/{me}/task/{tid}/stat")
        except OSError:
            continue
        key = ("server python", names.get(int(tid), comm))
        out[key] = out.get(key, 0.0) + _cpu_s(f)
    for pid in _descendants(me):
        try:
            out[(_classify(pid), pid)] = _cpu_s(_stat(f"/proc/{pid}/stat")[1])
        except OSError:
            continue
    return out


def cpu_use(before: dict, after: dict, wall_s: float) -> tuple[dict[str, float], dict[str, float]]:
    """(cores by process class, cores by server thread) between two :func:`snapshot` s."""
    by_class: dict[str, float] = {}
    by_thread: dict[str, float] = {}
    for k, v in after.items():
        d = (v - before.get(k, 0.0)) / max(wall_s, 1e-9)
        by_class[k[0]] = by_class.get(k[0], 0.0) + d
        if k[0] == "server python":
            by_thread[str(k[1])] = by_thread.get(str(k[1]), 0.0) + d
    return by_class, by_thread

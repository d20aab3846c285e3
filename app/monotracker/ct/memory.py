"""Whether a CT fits in the memory this process may still use, checked before its voxels are
read: otherwise ITK's "Failed to allocate memory" reads as a corrupt file, or Python dies with
a MemoryError traceback, minutes into a copy of a huge volume.

The limit is the smallest of: the memory the kernel says is available (``MemAvailable``), the
container's memory limit (cgroup v2 ``memory.max`` or v1 ``memory.limit_in_bytes``, less what
it uses) and the address-space limit (``ulimit -v``, less what this process has mapped).
"""

from __future__ import annotations

from pathlib import Path

from monotracker.errors import InputError

GIB = float(1 << 30)
#: What a loaded volume needs beyond its voxels, bytes (the ITK image and the NumPy copy are
#: counted by the callers; this is for the checks' temporary arrays and headroom).
HEADROOM_BYTES = 256 << 20


def _read_int(path: str) -> int | None:
    try:
        text = Path(path).read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _vm_size() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def available_bytes() -> tuple[float, str]:
    """(bytes this process can still allocate, what limits it); ``inf`` when nothing is known."""
    limits: list[tuple[float, str]] = []
    avail = _meminfo_available()
    if avail is not None:
        limits.append((float(avail), "the machine's free memory"))
    for lim_path, use_path in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                               ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        lim = _read_int(lim_path)
        if lim is not None and lim < (1 << 60):
            limits.append((float(max(0, lim - (_read_int(use_path) or 0))), "the container's memory limit"))
            break
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            limits.append((float(max(0, soft - _vm_size())), f"the address-space limit (ulimit -v, {soft / GIB:.1f} GiB)"))
    except (ImportError, ValueError, OSError):
        pass
    return min(limits) if limits else (float("inf"), "unknown")


def too_big(name: str, shape: tuple, dtype_name: str, bytes_per_voxel: float, need_bytes: float,
            available: tuple[float, str] | None = None) -> InputError:
    """The one-line refusal for a volume that does not fit (see :func:`check_fits`)."""
    have, what = available_bytes() if available is None else available
    n = 1
    for s in shape:
        n *= int(s)
    have_text = f"only {have / GIB:.1f} GiB is available ({what})" if have != float("inf") else "the memory ran out"
    return InputError(
        f"{name} is too large for this machine's memory: {' x '.join(str(int(s)) for s in shape)} voxels of {dtype_name} "
        f"({n * bytes_per_voxel / GIB:.1f} GiB); loading it needs about {need_bytes / GIB:.1f} GiB and {have_text}. "
        "Crop it to the head or resample it to a coarser grid (a 512 x 512 x 300 head CT is 0.15 GiB), or use a machine "
        "with more memory")


def check_fits(name: str, shape: tuple, dtype_name: str, bytes_per_voxel: float, copies: float) -> None:
    """Raise :func:`too_big`'s line when ``copies`` copies of a volume of ``shape`` voxels of
    ``bytes_per_voxel`` bytes, plus :data:`HEADROOM_BYTES`, exceed :func:`available_bytes`."""
    n = 1
    for s in shape:
        n *= int(s)
    need = copies * n * bytes_per_voxel + HEADROOM_BYTES
    avail = available_bytes()
    if need > avail[0]:
        raise too_big(name, shape, dtype_name, bytes_per_voxel, need, avail)


def is_allocation_failure(exc: BaseException) -> bool:
    """True for a MemoryError or ITK's failed allocation (a RuntimeError saying so)."""
    if isinstance(exc, MemoryError):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and ("Failed to allocate" in text or "bad_alloc" in text or "MemoryError" in text)


__all__ = ["available_bytes", "check_fits", "is_allocation_failure", "too_big"]

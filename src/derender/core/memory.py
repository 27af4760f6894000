"""Memory and threads shared by the engine and the writers: pre-populated buffers, thread counts, OpenCV's own threads.

:func:`populated_zeros` maps large buffers with ``MAP_POPULATE`` (on this project's
2-core VMs fresh memory costs 2-4 ms/MB in page faults, one populated mapping
0.3-0.5 ms/MB; ``benchmarks/README.md``). :func:`opencv_single_thread` switches OpenCV's
threads off while ours own the cores, so that the bytes of a result never depend on
the thread count.
"""

from __future__ import annotations

import mmap
import os
import threading
from contextlib import contextmanager
from typing import Any

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "CHANNELS",
    "N_CODES",
    "import_cv2",
    "opencv_single_thread",
    "thread_count",
    "POPULATE_BYTES",
    "populated_zeros",
    "available_memory",
    "check_memory",
]


#: Channel order of every image array.
CHANNELS = "RGB"


#: Code values of an 8-bit channel (the size of every per-code table).
N_CODES = 256


def available_memory() -> int | None:
    """Bytes the system can still give this process (``MemAvailable`` of ``/proc/meminfo``,
    lowered by a cgroup limit and by the address-space limit (``ulimit -v``) when they
    apply), or None where none can be read."""
    avail = _address_space_room()
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    mem = int(line.split()[1]) * 1024
                    break
            else:
                mem = None
    except OSError:
        return avail
    if mem is not None:
        avail = mem if avail is None else min(avail, mem)
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            with open(limit_file) as f:
                text = f.read().strip()
            if text == "max" or int(text) >= 1 << 60:
                continue
            with open(usage_file) as f:
                room = int(text) - int(f.read().strip())
            avail = room if avail is None else min(avail, room)
        except (OSError, ValueError):
            continue
    return avail


def _address_space_room() -> int | None:
    """``RLIMIT_AS`` minus this process's ``VmSize``, or None without a limit."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/status") as f:
            size = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
        return max(0, soft - size)
    except (ImportError, OSError, StopIteration, ValueError):
        return None


def check_memory(nbytes: int, what: str) -> None:
    """Raise :class:`~derender.core.errors.InputError` when ``nbytes`` (the memory ``what``
    needs) exceeds the memory available, saying how much is needed and available."""
    avail = available_memory()
    if avail is not None and nbytes > avail:
        raise InputError(f"{what} needs {nbytes / 2**30:.1f} GiB of memory, only {avail / 2**30:.1f} GiB "
                         "are available; use fewer or smaller images")


def import_cv2():
    """OpenCV, imported on first use (``import derender`` does not load it)."""
    import cv2

    return cv2


_CV2_THREADS_LOCK = threading.Lock()


_CV2_SINGLE_DEPTH = [0, 0]   # nesting depth, OpenCV's thread count outside


@contextmanager
def opencv_single_thread():
    """OpenCV's own threads off inside (process-wide setting; nested and concurrent uses
    from several of our threads are counted, the outermost restores the user's value)."""
    cv2 = import_cv2()
    with _CV2_THREADS_LOCK:
        if _CV2_SINGLE_DEPTH[0] == 0:
            _CV2_SINGLE_DEPTH[1] = cv2.getNumThreads()
            cv2.setNumThreads(1)
        _CV2_SINGLE_DEPTH[0] += 1
    try:
        yield
    finally:
        with _CV2_THREADS_LOCK:
            _CV2_SINGLE_DEPTH[0] -= 1
            if _CV2_SINGLE_DEPTH[0] == 0:
                cv2.setNumThreads(_CV2_SINGLE_DEPTH[1])


def thread_count(threads: int | None) -> int:
    """``threads`` (at least 1), or the CPUs this process may run on when None."""
    if threads is None:
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except AttributeError:  # pragma: no cover - non-Linux
            return max(1, os.cpu_count() or 1)
    return max(1, int(threads))


# --------------------------------------------------------------------------- tables
#: Arrays at least this large are mapped with their pages populated up front (:func:`populated_zeros`).
POPULATE_BYTES = 8 << 20


def populated_zeros(shape: tuple[int, ...] | int, dtype: Any = np.float32) -> np.ndarray:
    """``np.zeros(shape, dtype)`` whose memory is mapped with all pages present (anonymous
    ``mmap`` with ``MAP_POPULATE``; zero-filled by the kernel).

    Fresh memory normally costs a page fault at first touch of every page, ~2-4 ms per MB
    on this project's 2-core VMs (a 650 MB stack of frames: 1.3-2.9 s); populating the
    mapping in one call costs ~0.5 ms per MB (0.33-0.35 s). Small arrays, and systems
    without ``MAP_POPULATE``, get ``np.zeros``. The array owns the mapping (unmapped when
    the last view goes)."""
    dt = np.dtype(dtype)
    shape = (int(shape),) if np.isscalar(shape) else tuple(int(v) for v in shape)
    count = int(np.prod(shape, dtype=np.int64))
    nbytes = count * dt.itemsize
    flag = getattr(mmap, "MAP_POPULATE", None)
    if nbytes < POPULATE_BYTES or flag is None:
        return np.zeros(shape, dtype=dt)
    try:
        m = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | flag)
    except (OSError, ValueError):
        return np.zeros(shape, dtype=dt)
    return np.frombuffer(m, dtype=dt, count=count).reshape(shape)

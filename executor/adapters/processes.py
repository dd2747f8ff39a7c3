"""Child processes and loopback ports, as the executor's services, brokers and stand-ins use them.

- `free_port(host)`: a TCP port nobody listens on right now (the kernel's choice).
- `end_process(proc, timeout_s)`: SIGTERM, then SIGKILL after `timeout_s` s; the child reaped, its exit code
  returned (a child that already ended is only reaped).
- `keep_heap_mapped()`: this process keeps freed memory mapped (glibc `mallopt`), so that buffers of
  megabytes allocated again and again (a perception request's RGB-D frame) do not page-fault each time.

Public API: `free_port`, `end_process`, `keep_heap_mapped`.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import socket
import subprocess
from typing import Any


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on `host` that nobody listens on right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def end_process(proc: subprocess.Popen[Any], timeout_s: float) -> int | None:
    """End `proc`: SIGTERM, SIGKILL if it has not exited after `timeout_s` s, then reap it (waiting at most
    `timeout_s` s more). Returns its exit code (None only if even SIGKILL left it running)."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.terminate()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=timeout_s)
    return proc.returncode


_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024
"""glibc's upper limit for M_MMAP_THRESHOLD on 64-bit (bytes): blocks up to this size come from the heap."""
_TRIM_THRESHOLD = 1024 * 1024 * 1024
"""Free memory at the heap's top kept mapped (bytes) before any is given back to the kernel."""


def keep_heap_mapped() -> bool:
    """Keep freed memory of this process mapped: glibc serves blocks up to 32 MB from its heap and gives
    no memory back to the kernel until 1 GB at the heap's top is free (`mallopt` `M_MMAP_THRESHOLD`,
    `M_TRIM_THRESHOLD`, as real-time ROS 2 processes set them).

    Why: by default a block of a few MB is mapped fresh on every allocation and unmapped on its free,
    so a 2.4 MB RGB-D frame costs about 600 page faults (about 1 ms) each time it is encoded, received
    or decoded. Once the heap has grown to its working size, the same pages are reused. Process-wide;
    the price is that the process keeps its peak heap. Returns False where there is no glibc `mallopt`
    (nothing changes), True when both settings were applied.
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))

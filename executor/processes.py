"""Child processes and loopback ports, as the executor's services, brokers and stand-ins use them.

- `free_port(host)`: a TCP port nobody listens on right now (the kernel's choice).
- `end_process(proc, timeout_s)`: SIGTERM, then SIGKILL after `timeout_s` s; the child reaped, its exit code
  returned (a child that already ended is only reaped).

Public API: `free_port`, `end_process`.
"""

from __future__ import annotations

import contextlib
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

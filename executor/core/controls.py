"""Operator controls of a run: pause, resume, cancel, as flags the runner reads every tick.

Signals set them (`install_signal_handlers`, done first thing in `palletpilot.cli` so that a signal
during start-up is never fatal): SIGUSR1 pauses, SIGUSR2 resumes, SIGINT (Ctrl-C) and SIGTERM cancel.
A signal handler only sets a flag; the runner acts on it at its next tick (stops the vehicle, ends the
task with reason `cancelled`, writes the report). This module imports nothing heavy on purpose.

Public API: `Controls`, `CONTROLS` (the process's instance), `install_signal_handlers`.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType


class Controls:
    """Pause / resume / cancel requests; safe to set from a signal handler or another thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.paused = False
        self.cancelled = False
        self.cancel_signal: int | None = None
        self.cancel_reason = ""

    def pause(self) -> None:
        """Hold the vehicle still until `resume()`; the task's timeouts and progress checks freeze."""
        self.paused = True

    def resume(self) -> None:
        """Continue after `pause()`."""
        self.paused = False

    def cancel(self, reason: str = "cancelled by the operator", signum: int | None = None) -> None:
        """End the mission: the vehicle stops and the current task fails with reason `cancelled`."""
        with self._lock:
            if not self.cancelled:
                self.cancelled, self.cancel_reason, self.cancel_signal = True, reason, signum

    def reset(self) -> None:
        """Clear every request (a new run in the same process)."""
        self.paused = self.cancelled = False
        self.cancel_signal, self.cancel_reason = None, ""


CONTROLS = Controls()
"""The process's controls, set by the signal handlers."""


def install_signal_handlers(controls: Controls = CONTROLS, cancel: bool = True) -> None:
    """SIGUSR1 pause, SIGUSR2 resume and, with `cancel`, SIGINT and SIGTERM cancel (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        return

    def on_cancel(signum: int, _frame: FrameType | None) -> None:
        controls.cancel(f"cancelled by {signal.Signals(signum).name}", signum)

    if cancel:
        signal.signal(signal.SIGINT, on_cancel)
        signal.signal(signal.SIGTERM, on_cancel)
    if hasattr(signal, "SIGUSR1"):  # not on Windows
        signal.signal(signal.SIGUSR1, lambda _s, _f: controls.pause())
        signal.signal(signal.SIGUSR2, lambda _s, _f: controls.resume())

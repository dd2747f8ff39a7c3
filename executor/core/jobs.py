"""Work off the control loop: perception runs as a job the state polls each tick.

A behaviour submits a job (`Jobs.submit(fn, latency_s)`) and polls it from `update()`; meanwhile the
runner keeps ticking, so state timeouts fire and the vehicle keeps being commanded (standing still).

- On a wall clock the function runs on a worker thread; `poll()` never blocks. A job whose result
  is no longer wanted (its state ended, timed out or was cancelled) is abandoned: its result is
  dropped when it arrives, and a new job waits in the worker's queue behind it.
- On a simulated (deterministic) clock the function runs at once, in the loop, and its result is
  held back until the job's modelled duration has passed in simulated time: `latency_s` plus any
  `simulated_delay_s` the service reports (the simulator's injected delays). Seeded runs stay
  reproducible whatever the machine's load.

Public API: `Jobs`, `Job`.
"""

from __future__ import annotations

import concurrent.futures
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

T = TypeVar("T")


@dataclass
class Job(Generic[T]):
    """One piece of off-loop work: when it was asked for (s, the runner's clock) and its outcome."""

    name: str
    submitted_s: float
    ready_s: float  # deterministic clocks: the result is released at this time
    future: concurrent.futures.Future[T]
    info: dict[str, Any] = field(default_factory=dict)

    def poll(self, now_s: float) -> bool:
        """True once the result (or the exception) is available at `now_s`."""
        return self.future.done() and now_s >= self.ready_s

    def result(self) -> T:
        """The result; re-raises the function's exception. Call after `poll()` returned True."""
        return self.future.result(timeout=0)

    def cancel(self) -> None:
        """Not wanted any more: drop the result when it arrives (a running call cannot be interrupted)."""
        self.future.cancel()


class Jobs:
    """Runs jobs on a worker thread (wall clock) or in the loop with a modelled duration (simulated clock)."""

    def __init__(self, deterministic: bool, now: Callable[[], float]) -> None:
        self.deterministic = deterministic
        self._now = now
        self._queue: queue.Queue[tuple[Callable[[], Any], concurrent.futures.Future[Any]] | None] = queue.Queue()
        self._worker: threading.Thread | None = None

    def submit(self, name: str, fn: Callable[[], T], latency_s: float = 0.0, delay_of: Any = None) -> Job[T]:
        """Start `fn()` off the loop. `latency_s`: its modelled duration on a simulated clock (s);
        `delay_of`: an object whose `simulated_delay_s` after the call adds to it (injected delays)."""
        now = self._now()
        if self.deterministic:
            future: concurrent.futures.Future[T] = concurrent.futures.Future()
            try:
                future.set_result(fn())
            except Exception as exc:  # delivered to the state through `result()`
                future.set_exception(exc)
            extra = float(getattr(delay_of, "simulated_delay_s", 0.0) or 0.0)
            return Job(name, now, now + latency_s + extra, future)
        if self._worker is None:
            # A daemon thread: a perception call that hangs can never keep the process from exiting.
            self._worker = threading.Thread(target=self._work, name="perception", daemon=True)
            self._worker.start()
        future = concurrent.futures.Future()
        self._queue.put((fn, future))
        return Job(name, now, now, future)

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            fn, future = item
            if not future.set_running_or_notify_cancel():
                continue  # abandoned before it started
            try:
                future.set_result(fn())
            except BaseException as exc:  # delivered to the state through `result()`
                future.set_exception(exc)

    def close(self) -> None:
        """Stop the worker after the job it runs; queued jobs are dropped."""
        if self._worker is not None:
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is not None:
                    item[1].cancel()
            self._queue.put(None)
            self._worker = None

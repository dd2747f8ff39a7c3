"""The `Clock` port's implementations (the protocol is in `executor.ports`): the runner's time base and its 20 Hz tick.

- `SimClock`: simulated time. `tick()` advances the simulator by one control period and returns at
  once: deterministic, much faster than real time. `deterministic` is True, so work that runs off the
  loop (perception) is given a modelled duration in simulated time instead of its wall-clock one.
- `WallClock`: real time for the robot (or the simulator in real time). `tick()` sleeps to the next
  tick of a fixed schedule; a tick that starts late is an overrun (counted, and the schedule restarts
  from now instead of bursting to catch up). Jitter is how late each tick starts against its schedule.

`Clock.stats()` gives `ticks`, `overruns`, `overrun_streak` (consecutive overruns now),
`max_overrun_streak` and `jitter_ms` (`p50`, `p99`, `max`; None on a simulated clock).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from palletpilot.executor.ports import Clock

__all__ = ["CONTROL_DT", "Clock", "SimClock", "WallClock"]

CONTROL_DT = 0.05
"""The control period (s): 20 Hz."""


class SimClock:
    """Simulated time: each tick advances the simulator by `dt` seconds."""

    deterministic = True
    overrun_streak = 0

    def __init__(self, step: Callable[[float], None], dt: float = CONTROL_DT, start_s: float = 0.0) -> None:
        self._step = step
        self.dt = dt
        self.t = start_s
        self._ticks = 0

    def now(self) -> float:
        """Seconds since the start (simulated)."""
        return self.t

    def tick(self) -> None:
        """Advance one control period."""
        self._step(self.dt)
        self.t += self.dt
        self._ticks += 1

    def stats(self) -> dict[str, Any]:
        """Tick count; a simulated clock never overruns and has no jitter."""
        return {
            "clock": "simulated",
            "ticks": self._ticks,
            "overruns": 0,
            "overrun_streak": 0,
            "max_overrun_streak": 0,
            "jitter_ms": {"p50": None, "p99": None, "max": None},
        }


class WallClock:
    """Wall-clock time at a fixed tick rate; optionally steps a simulator by `dt` per tick (real-time sim)."""

    deterministic = False

    def __init__(
        self,
        dt: float = CONTROL_DT,
        step: Callable[[float], None] | None = None,
        overrun_s: float | None = None,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        start_s: float = 0.0,
    ) -> None:
        self.dt = dt
        self._step = step
        self._monotonic = monotonic
        self._sleep = sleep
        # A tick that starts this much behind its schedule is an overrun (default: half a period).
        self.overrun_s = 0.5 * dt if overrun_s is None else overrun_s
        self._t0 = monotonic() - start_s
        self._next = monotonic() + dt
        self._ticks = 0
        self._overruns = 0
        self.overrun_streak = 0
        self._max_streak = 0
        self._late_s: list[float] = []
        self._overrun_at: list[tuple[float, float]] = []  # (clock time s, late s) of the first overruns

    def now(self) -> float:
        """Seconds since the start (wall clock, monotonic)."""
        return self._monotonic() - self._t0

    def tick(self) -> None:
        """Sleep until the next tick is due; count it as an overrun when it is already late."""
        wait = self._next - self._monotonic()
        if wait > 0:
            self._sleep(wait)
        started = self._monotonic()
        late = max(0.0, started - self._next)
        self._late_s.append(late)
        self._ticks += 1
        if late > self.overrun_s:
            self._overruns += 1
            if len(self._overrun_at) < 20:
                self._overrun_at.append((started - self._t0, late))
            self.overrun_streak += 1
            self._max_streak = max(self._max_streak, self.overrun_streak)
            self._next = started + self.dt  # restart the schedule: no burst of catch-up ticks
        else:
            self.overrun_streak = 0
            self._next += self.dt
        if self._step is not None:
            self._step(self.dt)

    def stats(self) -> dict[str, Any]:
        """Ticks, overruns (with the first 20: when, how late) and the tick start jitter (ms) against the
        schedule."""
        late_ms = np.asarray(self._late_s) * 1e3
        jitter: dict[str, float | None] = {"p50": None, "p99": None, "max": None}
        if late_ms.size:
            jitter = {
                "p50": round(float(np.percentile(late_ms, 50)), 3),
                "p99": round(float(np.percentile(late_ms, 99)), 3),
                "max": round(float(late_ms.max()), 3),
            }
        return {
            "clock": "wall",
            "ticks": self._ticks,
            "overruns": self._overruns,
            "overrun_streak": self.overrun_streak,
            "max_overrun_streak": self._max_streak,
            "jitter_ms": jitter,
            "overruns_at": [{"t_s": round(t, 3), "late_ms": round(late * 1e3, 1)} for t, late in self._overrun_at],
        }

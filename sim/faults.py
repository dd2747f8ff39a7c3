"""Fault injection for the simulator: camera, perception, localization, control and vehicle faults, and kills.

A scenario's optional `faults:` list (`sim.scenario.Scenario.faults`) names what goes wrong and when:

```yaml
faults:
  - {kind: camera_drop, at_s: 30.0, duration_s: 2.0}                       # grab() raises "no frame (injected)"
  - {kind: camera_freeze, state: calibrate, after_s: 0.0, duration_s: 3.0}   # grab() repeats the last frame
  - {kind: perception_exception, state: estimate_pallet, count: 1}         # next calls raise RuntimeError
  - {kind: perception_slow, at_s: 12.0, delay_s: 2.0, count: 1}            # next calls take delay_s longer
  - {kind: localization_jump, at_s: 40.0, dx: 0.5, dy: 0.0, dyaw_deg: 0.0} # forklift frame; duration_s optional
  - {kind: solver_failure, at_s: 20.0, duration_s: 1.0}                    # the path follower's steps fail
  - {kind: vehicle_ignores_commands, at_s: 25.0, duration_s: 1.0}          # drive/stop/fork commands dropped
  - {kind: kill, state: lift, after_s: 0.5}                                # SIGKILL to this process
```

Trigger: exactly one of `at_s` (simulated seconds since the start) or `state` (a task state's name) with
`after_s` (s after that state starts, default 0) and optionally `task` (the task index; default: the first
time the state starts in any task). Every fault fires once. Times are simulated seconds (s), distances metres
(m), angles degrees where the name says `_deg`.

Public API:

- `FaultSpec`: the union of the fault models (discriminated by `kind`), validated like every scenario field:
  `CameraDrop`, `CameraFreeze`, `PerceptionException`, `PerceptionSlow`, `LocalizationJump`,
  `SolverFailure`, `VehicleIgnoresCommands`, `Kill`; `FAULT_KINDS` lists the kind names.
- `FaultInjector(faults, sim, realtime=False)`: applies them to a `sim.simulator.Simulator`:
  `observe(event, data, t)` (the runner's logged events; `state_start` arms `state` triggers),
  `poll(t)` (once per control tick: starts and ends faults, fires a due `kill`), `skip_until(t)` (resume at
  simulated time t: faults due before it do not fire again), `vehicle` (a `VehiclePort`
  over the simulator: `FaultyVehicle`), `grab()` (the camera source), `perception(inner)` (a wrapped
  `PerceptionService`: `FaultyPerception`, with `simulated_delay_s`), `step_failure(t)` (the path-follower
  fault hook), `injected` (start and end records for the report), `pending()` (faults that never fired).
- `CameraError`: what a dropped frame raises (`perception.errors.CameraError` where that exists, else
  `PerceptionError`).
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import Field, model_validator

from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import FileModel
from palletpilot.perception import errors as _perception_errors
from palletpilot.perception.errors import PerceptionError

if TYPE_CHECKING:
    from palletpilot.perception.frames import FrameBundle
    from palletpilot.sim.simulator import Simulator

CameraError: type[PerceptionError] = getattr(_perception_errors, "CameraError", PerceptionError)
"""Raised by `FaultInjector.grab` while a `camera_drop` is active."""

_EPS = 1e-9  # s: ticks at 0.05 s accumulate rounding error; a time within this of a deadline has reached it


class _Strict(FileModel):
    """A file schema (unknown keys, NaN and infinities are errors)."""


class _Fault(_Strict):
    """Trigger fields every fault has: exactly one of `at_s` or `state` (with `after_s`, `task`)."""

    at_s: float | None = Field(None, ge=0.0)
    """Simulated time (s since the start of the run) at which the fault fires."""
    state: str | None = Field(None, pattern=r"^[a-z][a-z0-9_]*$")
    """Name of the task state whose start arms the fault (e.g. `calibrate`, `lift`)."""
    after_s: float = Field(0.0, ge=0.0)
    """Delay (s) after `state` starts; only with `state`."""
    task: int | None = Field(None, ge=0)
    """Task index whose `state` counts; only with `state` (default: the first start in any task)."""

    @model_validator(mode="after")
    def _one_trigger(self) -> _Fault:
        if (self.at_s is None) == (self.state is None):
            got = "both given" if self.at_s is not None else "neither given"
            raise ValueError(f"give exactly one trigger, at_s or state ({got})")
        if self.state is None:
            # (their defaults are fine: a dumped scenario, e.g. in a journal, carries them)
            defaults = {"after_s": 0.0, "task": None}
            extra = [n for n in defaults if n in self.model_fields_set and getattr(self, n) != defaults[n]]
            if extra:
                raise ValueError(f"{' and '.join(extra)}: only with a state trigger, not with at_s")
        return self

    def trigger(self) -> dict[str, Any]:
        """The trigger fields as given (for the report)."""
        if self.at_s is not None:
            return {"at_s": self.at_s}
        out: dict[str, Any] = {"state": self.state, "after_s": self.after_s}
        if self.task is not None:
            out["task"] = self.task
        return out

    def params(self) -> dict[str, Any]:
        """The fault's own parameters (everything but the kind and the trigger)."""
        return self.model_dump(exclude={"kind", "at_s", "state", "after_s", "task"})

    @property
    def duration(self) -> float | None:
        """How long (s) the fault stays active once fired; None: until the end, or until used up."""
        return None


class _Timed(_Fault):
    duration_s: float = Field(gt=0.0)
    """How long (s, simulated) the fault stays active."""

    @property
    def duration(self) -> float | None:
        return self.duration_s


class CameraDrop(_Timed):
    """`grab()` raises `CameraError("no frame (injected)")` for `duration_s`."""

    kind: Literal["camera_drop"]


class CameraFreeze(_Timed):
    """`grab()` returns the last frame again, the same object unchanged, for `duration_s`."""

    kind: Literal["camera_freeze"]


class PerceptionException(_Fault):
    """The next `count` perception calls (calibrate, estimate_pallet) raise `RuntimeError` (a bug, not a
    `PerceptionError`)."""

    kind: Literal["perception_exception"]
    count: int = Field(1, ge=1)


class PerceptionSlow(_Fault):
    """The next `count` perception calls take `delay_s` (s) longer."""

    kind: Literal["perception_slow"]
    delay_s: float = Field(gt=0.0)
    count: int = Field(1, ge=1)


class LocalizationJump(_Fault):
    """Localization jumps by (dx, dy) m and dyaw_deg degrees in the forklift frame:
    reported `T_world_forklift` = true-with-noise `T_world_forklift @ SE2(dx, dy, radians(dyaw_deg))`,
    for `duration_s` (s; default: until the end of the run)."""

    kind: Literal["localization_jump"]
    dx: float = Field(0.0)
    dy: float = Field(0.0)
    dyaw_deg: float = Field(0.0)
    duration_s: float | None = Field(None, gt=0.0)

    @property
    def duration(self) -> float | None:
        return self.duration_s

    def offset(self) -> SE2:
        """The jump as `T_forklift_jumped` (forklift frame, m and rad)."""
        return SE2(self.dx, self.dy, math.radians(self.dyaw_deg))


class SolverFailure(_Timed):
    """`step_failure(t)` reports a failure, so the path follower's control steps fail, for `duration_s`."""

    kind: Literal["solver_failure"]


class VehicleIgnoresCommands(_Timed):
    """drive / stop / set_fork_height never reach the simulator for `duration_s`; it keeps its last commands."""

    kind: Literal["vehicle_ignores_commands"]


class Kill(_Fault):
    """The process kills itself with SIGKILL (no cleanup, as a power cut or the OOM killer would)."""

    kind: Literal["kill"]


FaultSpec = Annotated[
    CameraDrop
    | CameraFreeze
    | PerceptionException
    | PerceptionSlow
    | LocalizationJump
    | SolverFailure
    | VehicleIgnoresCommands
    | Kill,
    Field(discriminator="kind"),
]
"""One entry of a scenario's `faults:` list."""

FAULT_KINDS = (
    "camera_drop",
    "camera_freeze",
    "perception_exception",
    "perception_slow",
    "localization_jump",
    "solver_failure",
    "vehicle_ignores_commands",
    "kill",
)


class _Armed:
    """One fault's progress: waiting for its trigger, due, active, ended."""

    def __init__(self, index: int, spec: FaultSpec) -> None:
        self.index = index
        self.spec = spec
        self.kind: str = spec.kind
        self.due_t: float | None = spec.at_s  # simulated time it fires; set by `observe` for state triggers
        self.start_t: float | None = None
        self.ended = False
        self.remaining = int(getattr(spec, "count", 0))  # perception calls still to affect
        self.hits = 0  # how often the fault changed something (frames, calls, commands, steps)

    @property
    def active(self) -> bool:
        return self.start_t is not None and not self.ended


class FaultInjector:
    """Applies a scenario's faults to a simulator (see the module docstring).

    Time-triggered and state-triggered faults start in `poll` (and in `observe` for other kinds than
    `kill`, so a fault with `after_s: 0` already affects the state's first tick); faults with a duration end
    in `poll` once `duration_s` simulated seconds have passed; perception faults end when `count` calls
    are used up. The wrappers (`vehicle`, `grab`, `perception(...)`, `step_failure`) only read that state,
    so every effect is tied to simulated time, never to the wall clock.
    """

    def __init__(self, faults: Sequence[FaultSpec], sim: Simulator, realtime: bool = False) -> None:
        self.sim = sim
        self.realtime = realtime
        self.injected: list[dict[str, Any]] = []
        """Every fault as it fires and ends: {"kind", "t_s", "event": "start"|"end", "index", ...}."""
        self._armed = [_Armed(i, spec) for i, spec in enumerate(faults)]
        self._lock = threading.RLock()  # perception calls come from a worker thread
        self._now = 0.0
        self._last_frame: FrameBundle | None = None
        self.vehicle = FaultyVehicle(sim, self)
        """The simulator as a `VehiclePort`, with localization jumps and ignored commands applied."""

    # -- time and events ---------------------------------------------------------------------
    def observe(self, event: str, data: dict[str, Any], t: float) -> None:
        """One event the runner logs, at simulated time `t` (s); `state_start` (data: `state`, `task`) arms
        the faults triggered by that state. Faults due now start at once, except `kill` (it waits for `poll`)."""
        with self._lock:
            if event == "state_start":
                state, task = data.get("state"), data.get("task")
                for a in self._armed:
                    spec = a.spec
                    if a.due_t is None and spec.state == state and (spec.task is None or spec.task == task):
                        a.due_t = t + spec.after_s
            self._advance(t, kill=False)

    def poll(self, t: float) -> None:
        """Once per control tick, at simulated time `t` (s): start due faults, end expired ones, fire a due kill."""
        with self._lock:
            self._advance(t, kill=True)

    def skip_until(self, t: float) -> None:
        """Resume a run at simulated time `t` (s): time-triggered faults due before `t` fired in the earlier
        process and do not fire again. One whose window still covers `t` (a `duration_s` fault, or a
        `localization_jump` without one) stays active for the rest of its window, without a new start record;
        perception faults due before `t` count as used up. State-triggered faults stay armed."""
        with self._lock:
            self._now = max(self._now, t)
            for a in self._armed:
                if a.start_t is not None or a.spec.at_s is None or a.spec.at_s >= t - _EPS:
                    continue
                a.start_t = a.spec.at_s
                duration = a.spec.duration
                uses_calls = a.kind in ("perception_exception", "perception_slow")
                a.ended = uses_calls or a.kind == "kill" or (duration is not None and t >= a.start_t + duration - _EPS)

    def skip_states(self, started: Sequence[tuple[int, str]]) -> None:
        """Resume a run: state-triggered faults whose state (task index, state name) had already started in
        the earlier process fired there and do not fire again (a `kill` inside the state a resume re-enters
        would otherwise fire for ever)."""
        with self._lock:
            for a in self._armed:
                spec = a.spec
                if a.start_t is not None or spec.state is None:
                    continue
                if any(state == spec.state and (spec.task is None or spec.task == task) for task, state in started):
                    a.start_t, a.ended = self._now, True

    def _advance(self, t: float, kill: bool) -> None:
        self._now = max(self._now, t)
        for a in self._armed:
            if a.ended:
                continue
            if a.start_t is None:
                if a.due_t is None or t < a.due_t - _EPS or (a.kind == "kill" and not kill):
                    continue
                self._start(a, t)
                continue  # active for at least one tick
            duration = a.spec.duration
            if duration is not None and t >= a.start_t + duration - _EPS:
                self._end(a, t)

    def _start(self, a: _Armed, t: float) -> None:
        a.start_t = t
        self.injected.append(
            {"kind": a.kind, "t_s": round(t, 3), "event": "start", "index": a.index}
            | a.spec.trigger()
            | a.spec.params()
        )
        if a.kind == "kill":
            os.kill(os.getpid(), signal.SIGKILL)

    def _end(self, a: _Armed, t: float) -> None:
        a.ended = True
        self.injected.append({"kind": a.kind, "t_s": round(t, 3), "event": "end", "index": a.index, "hits": a.hits})

    def _active(self, kind: str) -> list[_Armed]:
        return [a for a in self._armed if a.kind == kind and a.active]

    def pending(self) -> list[FaultSpec]:
        """Faults that have not fired (yet): their trigger time or state was never reached."""
        with self._lock:
            return [a.spec for a in self._armed if a.start_t is None]

    # -- camera --------------------------------------------------------------------------------
    def grab(self) -> FrameBundle:
        """`sim.grab()` with faults: a `camera_drop` raises `CameraError("no frame (injected)")`; a
        `camera_freeze` returns the last frame again (the same object, so its stamp and truth too)."""
        with self._lock:
            drops = self._active("camera_drop")
            if drops:
                drops[0].hits += 1
                raise CameraError("no frame (injected)")
            freezes = self._active("camera_freeze")
            if freezes and self._last_frame is not None:
                freezes[0].hits += 1
                return self._last_frame
        frame = self.sim.grab()
        with self._lock:
            self._last_frame = frame
        return frame

    # -- perception ----------------------------------------------------------------------------
    def perception(self, inner: Any) -> FaultyPerception:
        """Wrap a `PerceptionService` so that perception faults apply to its calibrate / estimate_pallet."""
        return FaultyPerception(inner, self)

    def _perception_call(self) -> tuple[float, bool]:
        """Use up one call of the active perception faults: (extra delay in s, raise?)."""
        with self._lock:
            delay, crash = 0.0, False
            for kind in ("perception_slow", "perception_exception"):
                for a in self._active(kind):
                    if isinstance(a.spec, PerceptionSlow):
                        delay += a.spec.delay_s
                    else:
                        crash = True
                    a.hits += 1
                    a.remaining -= 1
                    if a.remaining <= 0:
                        self._end(a, self._now)
            return delay, crash

    # -- control ---------------------------------------------------------------------------------
    def step_failure(self, t: float) -> str | None:
        """The path follower's fault hook: a message while a `solver_failure` is active at simulated time `t`
        (s), else None."""
        with self._lock:
            for a in self._active("solver_failure"):
                duration = a.spec.duration
                assert a.start_t is not None and duration is not None
                if a.start_t - _EPS <= t < a.start_t + duration - _EPS:
                    a.hits += 1
                    return f"solver failure (injected at t={a.start_t:.2f} s)"
            return None

    # -- vehicle (used by FaultyVehicle) ------------------------------------------------------------
    def _jump(self) -> SE2 | None:
        with self._lock:
            jumps = self._active("localization_jump")
            if not jumps:
                return None
            offset = SE2.identity()
            for a in jumps:
                a.hits += 1
                assert isinstance(a.spec, LocalizationJump)
                offset = offset @ a.spec.offset()
            return offset

    def _ignore_command(self) -> bool:
        with self._lock:
            ignoring = self._active("vehicle_ignores_commands")
            for a in ignoring:
                a.hits += 1
            return bool(ignoring)


class FaultyVehicle:
    """The simulator as a `VehiclePort` with localization jumps and ignored commands applied.

    Everything not faulted (`localization_stamp`, `battery_level`, safety state, truth such as `true_pose`,
    ...) is delegated to the simulator unchanged, so new simulator methods keep working; a member the
    simulator lacks is missing here too. `emergency_stop` is never ignored: it is the safety PLC's input,
    not a drive command.
    """

    def __init__(self, sim: Simulator, injector: FaultInjector) -> None:
        self._sim = sim
        self._injector = injector

    def __getattr__(self, name: str) -> Any:
        if name in ("_sim", "_injector"):  # not set yet (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self._sim, name)

    def localization(self) -> SE2:
        """`T_world_forklift` (world frame, m and rad) as localization reports it, jumped by any active
        `localization_jump` (`@ SE2(dx, dy, dyaw)`, forklift frame)."""
        pose = self._sim.localization()
        offset = self._injector._jump()
        return pose if offset is None else pose @ offset

    def drive(self, speed: float, steering: float) -> None:
        """Drive command (m/s, rad); dropped while `vehicle_ignores_commands` is active."""
        if not self._injector._ignore_command():
            self._sim.drive(speed, steering)

    def stop(self) -> None:
        """Brake to a standstill; dropped while `vehicle_ignores_commands` is active."""
        if not self._injector._ignore_command():
            self._sim.stop()

    def set_fork_height(self, height: float) -> None:
        """Fork height target (m); dropped while `vehicle_ignores_commands` is active."""
        if not self._injector._ignore_command():
            self._sim.set_fork_height(height)

    @property
    def speed(self) -> float:
        """Measured speed (m/s)."""
        return self._sim.speed

    @property
    def steering(self) -> float:
        """Measured steering angle (rad)."""
        return self._sim.steering

    @property
    def fork_height(self) -> float:
        """Measured fork height (m)."""
        return self._sim.fork_height

    def proximity_ranges(self) -> tuple[float, float]:
        """Ranges (m) of the (left, right) fork-tip beams."""
        return self._sim.proximity_ranges()

    def load_detected(self) -> bool:
        """True when a pallet rides on the forks."""
        return self._sim.load_detected()

    def faults(self) -> list[str]:
        """The simulator's safety faults (injected faults are silent, as real ones would be)."""
        return self._sim.faults()


class FaultyPerception:
    """A `PerceptionService` with `perception_exception` and `perception_slow` applied to `calibrate` and
    `estimate_pallet`; everything else is delegated to the wrapped service.

    `simulated_delay_s` is the extra delay (s) of the last call (0.0 when none), so a simulated clock can
    account for it; with `realtime` the call also really sleeps that long.
    """

    def __init__(self, inner: Any, injector: FaultInjector) -> None:
        self._inner = inner
        self._injector = injector
        self.simulated_delay_s = 0.0

    def __getattr__(self, name: str) -> Any:
        if name in ("_inner", "_injector"):
            raise AttributeError(name)
        return getattr(self._inner, name)

    def _faulted(self) -> None:
        delay, crash = self._injector._perception_call()
        self.simulated_delay_s = delay
        if delay > 0.0 and self._injector.realtime:
            time.sleep(delay)
        if crash:
            raise RuntimeError("perception crashed (injected)")

    def calibrate(self, frames: Any) -> Any:
        """`inner.calibrate(frames)` with the active perception faults."""
        self._faulted()
        return self._inner.calibrate(frames)

    def estimate_pallet(
        self,
        frame: Any,
        calibration: Any,
        T_world_forklift: SE2,
        expected_T_world_pallet: SE2 | None = None,
        pallet: Any = None,
        support_height_m: float = 0.0,
    ) -> Any:
        """`inner.estimate_pallet(...)` with the active perception faults."""
        self._faulted()
        return self._inner.estimate_pallet(
            frame, calibration, T_world_forklift, expected_T_world_pallet, pallet, support_height_m=support_height_m
        )

    @property
    def last_good(self) -> Any:
        """The wrapped service's last successful calibration."""
        return self._inner.last_good

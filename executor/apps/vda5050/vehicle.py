"""What the AGV drives: the simulated warehouse on the wall clock, or a real truck (the ROS 2 adapter).

`Backend` bundles what a `Runner` needs (vehicle port, perception, camera, clock, vehicle parameters,
forks, path follower, event listeners) and the node the truck starts at. `sim_backend(loaded, scenario)`
builds it as `executor.app` does for `palletpilot run --clock wall`: the scenario's simulator with its
injected faults, perception in process (the shipped ONNX model on the RGB, or the simulator's labels),
the MPC follower with its wall-clock deadline, a `WallClock` at 20 Hz that steps the simulator.
`robot_backend(path)` needs `palletpilot.executor.adapters.ros` (another package's adapter) and says so clearly
when it is not installed.

`TickClock` wraps a clock and calls a hook after every tick: the AGV samples the truck there, in the one
thread that drives it.

Public API: `Backend`, `TickClock`, `sim_backend`, `robot_backend`, `BackendError`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from palletpilot.control.follower import Follower
from palletpilot.control.mpc import MpcConfig, MpcFollower
from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.adapters.local_perception import LocalPerception
from palletpilot.executor.apps.vda5050.config import Loaded
from palletpilot.executor.core.clock import CONTROL_DT, Clock, WallClock
from palletpilot.executor.ports import PerceptionService, VehiclePort
from palletpilot.geometry import PalletpilotError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.labels_mode import DEFAULT_LABELS_MODE, SIM_TRUTH, LabelsMode
from palletpilot.perception.specs import ForkGeometry


class BackendError(PalletpilotError):
    """The vehicle cannot be set up (a scenario on another map, no ROS 2 adapter, ...)."""


class TickClock:
    """A `Clock` that calls `hook()` after every tick of `inner`; `now` replaces the inner clock's time (a
    simulator's own time: paced by the wall clock, it never falls behind its vehicle's readings when a tick
    overruns)."""

    deterministic = False

    def __init__(
        self, inner: Clock, hook: Callable[[], None] = lambda: None, now: Callable[[], float] | None = None
    ) -> None:
        self.inner = inner
        self.hook = hook
        self._now = now or inner.now
        self.dt = inner.dt
        self.deterministic = inner.deterministic
        self.overrun_streak = 0

    def now(self) -> float:
        """The clock's time (s)."""
        return self._now()

    def tick(self) -> None:
        """Tick the inner clock, then run the hook."""
        self.inner.tick()
        self.overrun_streak = self.inner.overrun_streak
        self.hook()

    def stats(self) -> dict[str, Any]:
        """The inner clock's statistics."""
        return self.inner.stats()


@dataclass
class Backend:
    """Everything a `Runner` needs to drive one truck, and where the truck starts."""

    vehicle: VehiclePort
    perception: PerceptionService | None
    grab: Callable[[], FrameBundle]
    clock: TickClock
    params: VehicleParams
    forks: ForkGeometry
    follower: Follower
    start_node: str | None
    listeners: Sequence[Callable[[str, dict[str, Any], float], None]] = field(default_factory=tuple)
    battery: Callable[[], float | None] = lambda: None
    close: Callable[[], None] = lambda: None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def sim_backend(
    loaded: Loaded,
    scenario_path: str | Path,
    labels: str = "fused",
    seed: int | None = None,
    speed: float = 1.0,
) -> Backend:
    """The simulated warehouse of a scenario on the wall clock (its map must be the config's); `labels` as
    `run --labels` (`executor.app.Labels`). `speed`: simulated seconds per wall-clock second at most (each tick
    steps the simulator by the control period; away from 1 there is no wall-clock solve deadline for the MPC
    and no late tick: the simulation runs as fast as the machine allows up to `speed`)."""
    from palletpilot.executor.adapters.local_perception import LocalPerception
    from palletpilot.perception.segmentation import DEFAULT_MODEL, OnnxSegmenter
    from palletpilot.sim.faults import FaultInjector
    from palletpilot.sim.scenario import load_scenario
    from palletpilot.sim.simulator import Simulator

    scenario = load_scenario(scenario_path)
    scenario_map = scenario.path(scenario.map)
    try:
        same = _sha256(scenario_map) == _sha256(loaded.map_path)
    except OSError:
        same = True  # unreadable: the simulator names the file
    if not same:
        raise BackendError(
            f"{scenario_path}: map: {scenario_map} is not the AGV's map {loaded.map_path}: the simulated warehouse "
            "must be the one the AGV drives on"
        )
    sim = Simulator(scenario, seed=seed)
    injector = FaultInjector(scenario.faults, sim, realtime=True)

    def step(dt: float) -> None:
        sim.step(dt)
        injector.poll(sim.time)

    grab: Callable[[], FrameBundle] = injector.grab
    segmenter = None
    mode = LabelsMode.MODEL if labels == SIM_TRUTH else LabelsMode(labels)
    if labels != SIM_TRUTH:  # the truck's view: no labels from the simulator
        segmenter = None if mode == LabelsMode.GEOMETRY else OnnxSegmenter(DEFAULT_MODEL)
        inner = injector.grab

        def grab() -> FrameBundle:
            return dataclasses.replace(inner(), labels=None)

    perception = injector.perception(LocalPerception(sim.forks, sim.pallet_type, segmenter=segmenter, labels=mode))
    follower = MpcFollower(loaded.vehicle, MpcConfig())
    follower.step_fault = injector.step_failure
    wall = WallClock(step=step)
    if speed != 1.0:  # as fast as the machine allows up to `speed`: no wall-clock deadline, no late tick
        wall = WallClock(dt=CONTROL_DT / speed, step=lambda _: step(CONTROL_DT), overrun_s=math.inf)
        follower.mpc.solve_deadline_s = None
    clock = TickClock(wall, now=lambda: sim.time)
    clock.dt = CONTROL_DT  # what a tick means to the runner and the AGV: simulated seconds
    return Backend(
        vehicle=injector.vehicle,
        perception=perception,
        grab=grab,
        clock=clock,
        params=loaded.vehicle,
        forks=sim.forks,
        follower=follower,
        start_node=scenario.start,
        listeners=(injector.observe,),
        battery=lambda: sim.battery_level,
    )


def robot_backend(loaded: Loaded, robot_path: str | Path, labels: LabelsMode = DEFAULT_LABELS_MODE) -> Backend:
    """A real truck through the ROS 2 adapter (`executor.adapters.ros`, wired by `apps.vda5050.robot_backend`);
    `labels`: which source selects perception's pixels. Without the adapter's libraries: `BackendError`."""
    try:
        from palletpilot.executor.apps.vda5050.robot_backend import open_backend
    except ImportError as exc:
        raise BackendError(
            f"--robot {robot_path}: needs the ROS 2 adapter (executor.adapters.ros), which is not available "
            f"here ({exc}); run with --sim SCENARIO, or install the adapter"
        ) from None
    backend: Backend = open_backend(loaded, Path(robot_path), labels=labels)
    return backend


__all__ = ["Backend", "BackendError", "LocalPerception", "TickClock", "robot_backend", "sim_backend"]

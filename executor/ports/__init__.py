"""The executor's ports to the world: the vehicle, perception, the clock, and the typed vocabulary
(ARCHITECTURE.md).

`sim.simulator.Simulator` implements `VehiclePort` directly; `executor.ros.vehicle.RosVehicle` implements
it for the real forklift. `executor.local_perception.LocalPerception` is the in-process
`PerceptionService`, `executor.perception_remote` the client of the perception service.
`PassThroughVehicle` is the base of a `VehiclePort` that wraps another and changes or watches a few of
its calls (the watchdog's, the recorder's). `Clock` is the runner's time base (implemented in
`executor.clock`). `Reason` and `Outcome` are the typed vocabulary (`executor.vocabulary`).
Times (`localization_stamp`, frame stamps) are on the runner's clock, in seconds.

Light by contract: this module imports the standard library and the vocabulary only (the types of the
signatures under `TYPE_CHECKING`), so `import palletpilot.executor.ports` loads no perception, control,
numpy or scipy (import-linter, pyproject).

`RunObserver` is how the run's outputs (the MCAP recorder, the fault injector, the AGV's notes) follow a
run: the runner calls each observer with every event it logs; none reaches into the runner.

Public API: `VehiclePort`, `PassThroughVehicle`, `PerceptionService`, `Clock`, `RunObserver`, `Reason`,
`Outcome`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from palletpilot.executor.ports.vocabulary import Outcome, Reason

if TYPE_CHECKING:
    from palletpilot.control.safety import SafetyState
    from palletpilot.geometry import SE2
    from palletpilot.perception.calibration_io import Calibration
    from palletpilot.perception.clearance import Volume, VolumeCheck
    from palletpilot.perception.frames import FrameBundle
    from palletpilot.perception.pallet import PalletEstimate
    from palletpilot.perception.specs import PalletType

__all__ = ["Clock", "Outcome", "PassThroughVehicle", "PerceptionService", "Reason", "RunObserver", "VehiclePort"]


@runtime_checkable
class VehiclePort(Protocol):
    """What the executor needs from a forklift (SI units, world frame)."""

    def localization(self) -> SE2:
        """`T_world_forklift` from localization."""

    def localization_stamp(self) -> float:
        """When the last localization fix was taken (s, the runner's clock): the watchdog's input."""

    def drive(self, speed: float, steering: float) -> None:
        """Drive command: speed (m/s, negative in reverse), steering angle (rad)."""

    def stop(self) -> None:
        """Brake to a standstill (service brake, the drive controller's own deceleration)."""

    def emergency_stop(self) -> None:
        """The truck's safety stop: brake at the emergency deceleration whatever the drive commands,
        latched until the run ends (the safety PLC's stop input on a robot)."""

    @property
    def speed(self) -> float:
        """Measured speed (m/s)."""

    @property
    def steering(self) -> float:
        """Measured steering angle (rad)."""

    def set_fork_height(self, height: float) -> None:
        """Fork height target (m, fork bottoms above the floor)."""

    @property
    def fork_height(self) -> float:
        """Measured fork height (m)."""

    def proximity_ranges(self) -> tuple[float, float]:
        """Ranges (m) of the left and right fork-tip beams (`inf`: nothing within range)."""

    def load_detected(self) -> bool:
        """True when the forks carry a load (mast pressure sensor)."""

    def faults(self) -> list[str]:
        """Active safety faults (contact, bumper); empty when all is well."""

    def safety_state(self) -> SafetyState:
        """The safety scanners: field set, warning (speed cap), protective stop, what intrudes."""

    def set_safety_field_set(self, name: str, direction: str = "forward") -> None:
        """Select the scanners' field case before the truck drives: the field set (`control.safety.FIELD_SETS`:
        `normal`, or `narrow` to enter a pallet or a floor drop slot once the camera has seen the entry volume
        clear) and the direction of travel it is about to drive (`forward`, `reverse`). A standing truck is
        watched in that direction until it moves: a pallet just set down in front of the forks must not hold
        a truck that is about to back away from it."""


class PassThroughVehicle:
    """A `VehiclePort` that hands every call to `inner`; a subclass overrides the calls it changes or
    watches. The protocol's properties are delegated explicitly (`__getattr__` does not see them)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    @property
    def speed(self) -> float:
        """Measured speed (m/s)."""
        return float(self.inner.speed)

    @property
    def steering(self) -> float:
        """Measured steering angle (rad)."""
        return float(self.inner.steering)

    @property
    def fork_height(self) -> float:
        """Measured fork height (m)."""
        return float(self.inner.fork_height)


class PerceptionService(Protocol):
    """Calibration and pallet estimation, in process or behind a service boundary."""

    def calibrate(self, frames: Sequence[FrameBundle]) -> Calibration:
        """`T_forklift_camera` from frames of the forks and the floor (raises `CalibrationError`)."""

    def estimate_pallet(
        self,
        frame: FrameBundle,
        calibration: Calibration,
        T_world_forklift: SE2,
        expected_T_world_pallet: SE2 | None = None,
        pallet: PalletType | None = None,
        support_height_m: float = 0.0,
    ) -> PalletEstimate:
        """The pallet's pose (raises `PalletNotFound`); with `expected_T_world_pallet` (world frame) only
        the pallet instance standing there, within a gate, is taken (`perception.instances`). `pallet`:
        the type to look for (another type is `PalletNotFound`); None: the service's own default.
        `support_height_m`: the height of what the pallet stands on (m above the floor: 0, or a rack's
        beams), where the geometry looks for it (`perception.geometry_labels`)."""

    def check_volume(self, frame: FrameBundle, calibration: Calibration, volume: Volume) -> VolumeCheck:
        """Depth points inside an upright box ahead of the forks (forklift frame), and how much of it was seen."""

    @property
    def last_good(self) -> Calibration | None:
        """The last successful calibration."""


class Clock(Protocol):
    """The runner's time: `now()` in seconds since the start, `tick()` to the next control period
    (`executor.clock`: `SimClock`, `WallClock`)."""

    dt: float
    deterministic: bool
    overrun_streak: int

    def now(self) -> float:
        """Seconds since the start of the run."""
        ...

    def tick(self) -> None:
        """Advance to the next control tick (simulate one period, or sleep until it is due)."""
        ...

    def stats(self) -> dict[str, Any]:
        """Tick statistics for the report (`executor.clock`'s docstring)."""
        ...


class RunObserver(Protocol):
    """Follows a run: called with each event the runner logs (`event` name, its `data`, `t` on the runner's
    clock in s), in the control loop's thread; it must not block. Given to the runner when it is built
    (`Runner(..., listeners=[...])`), never swapped in afterwards."""

    def __call__(self, event: str, data: dict[str, Any], t: float, /) -> None:
        """One event of the run."""
        ...

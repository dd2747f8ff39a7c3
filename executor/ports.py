"""The executor's ports to the world: the vehicle and perception (ARCHITECTURE.md).

`sim.simulator.Simulator` implements `VehiclePort` and `CameraSource` directly; a robot adapter
implements them for the real forklift. `LocalPerception` is the in-process `PerceptionService`.
`PassThroughVehicle` is the base of a `VehiclePort` that wraps another and changes or watches a few of
its calls (the watchdog's, the recorder's).
The `Clock` port is in `executor.clock`. Times (`localization_stamp`, frame stamps) are on the
runner's clock, in seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

from palletpilot.control.safety import SafetyState
from palletpilot.geometry import SE2
from palletpilot.perception.calibration import Calibrator, Method
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.clearance import Volume, VolumeCheck, check_volume
from palletpilot.perception.depth_tare import DepthTare, correct_depth
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.geometry_labels import DEFAULT_ENVELOPE, DEFAULT_LABELS_MODE, Envelope, LabelsMode
from palletpilot.perception.pallet import PalletEstimate, estimate_pallet, estimator_config
from palletpilot.perception.segmentation import SegmentationService
from palletpilot.perception.specs import ForkGeometry, PalletType


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

    def set_safety_field_set(self, name: str) -> None:
        """Select the scanners' field set (`control.safety.FIELD_SETS`): `normal`, or `narrow` to enter a
        pallet or a floor drop slot once the camera has seen the entry volume clear."""


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


class LocalPerception:
    """`PerceptionService` in this process: labels from the frame or a segmenter, then the geometry.

    `depth_tare`: the camera's measured depth scale error (`perception.depth_tare`), removed from every
    frame before use; none for a camera without one (the simulator's, unless a scenario says otherwise).
    `labels`: which source selects the pallet's, the floor's and the forks' pixels
    (`perception.geometry_labels.LabelsMode`; `geometry` never runs the segmenter); `envelope`: how far
    the pallet may stand from where it is expected (the geometry's search region).
    """

    def __init__(
        self,
        forks: ForkGeometry,
        pallet: PalletType | None = None,
        method: Method = "model",
        segmenter: SegmentationService | None = None,
        depth_tare: DepthTare | None = None,
        labels: LabelsMode = DEFAULT_LABELS_MODE,
        envelope: Envelope = DEFAULT_ENVELOPE,
    ) -> None:
        self.forks = forks
        self.pallet = pallet or PalletType.eur()
        self.labels = labels
        self.envelope = envelope
        self.calibrator = Calibrator(forks, method, labels=labels)
        self.segmenter = segmenter
        self.depth_tare = depth_tare
        self.pallet_config = estimator_config(depth_tared=depth_tare is not None)  # the spread knows the tare

    def _labelled(self, frame: FrameBundle) -> FrameBundle:
        frame = correct_depth(frame, self.depth_tare)
        if frame.labels is not None or self.segmenter is None or self.labels == LabelsMode.GEOMETRY:
            return frame
        from palletpilot.perception.segmentation import ensure_labels

        return ensure_labels(frame, self.segmenter)

    def calibrate(self, frames: Sequence[FrameBundle]) -> Calibration:
        """Calibrate; on failure the last good calibration stays in `last_good`."""
        return self.calibrator.calibrate([self._labelled(f) for f in frames])

    def estimate_pallet(
        self,
        frame: FrameBundle,
        calibration: Calibration,
        T_world_forklift: SE2,
        expected_T_world_pallet: SE2 | None = None,
        pallet: PalletType | None = None,
        support_height_m: float = 0.0,
    ) -> PalletEstimate:
        """Estimate the pallet's pose in the forklift and world frames; with `expected_T_world_pallet`
        (world) only the pallet instance standing there is fitted; `pallet`: the type (default: this
        service's); `support_height_m`: what it stands on (m above the floor)."""
        expected = None if expected_T_world_pallet is None else T_world_forklift.inv() @ expected_T_world_pallet
        return estimate_pallet(
            self._labelled(frame),
            calibration,
            pallet or self.pallet,
            T_world_forklift=T_world_forklift,
            expected=expected,
            config=self.pallet_config,
            labels=self.labels,
            support_height_m=support_height_m,
            envelope=self.envelope,
        )

    def check_volume(self, frame: FrameBundle, calibration: Calibration, volume: Volume) -> VolumeCheck:
        """Depth points inside `volume` (forklift frame) and the share of it the camera saw."""
        return check_volume(correct_depth(frame, self.depth_tare), calibration, volume)

    @property
    def last_good(self) -> Calibration | None:
        """The last successful calibration."""
        return self.calibrator.last_good

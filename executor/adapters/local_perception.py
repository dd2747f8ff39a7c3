"""`LocalPerception`: the in-process `PerceptionService` (`executor.ports`), an adapter over the
perception package (calibration, pallet estimation, the entry-volume check, the segmenter).

Public API: `LocalPerception`.
"""

from __future__ import annotations

from collections.abc import Sequence

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
        self.pallet_config = estimator_config(  # the spread knows the tare and the camera's noise correlation
            depth_tare is not None, depth_tare.depth_correlation_px if depth_tare else 1.0
        )

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

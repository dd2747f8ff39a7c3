"""Run recordings: the channels (topics, schemas, cadences) and the pass-through wrappers that feed them.

Public API: `TOPICS`, `JSON_FIELDS`, `json_schema`, `RECORDING`, `RESUMED_RECORDING`, `FOXGLOVE_PORT`,
`SIM_EPOCH_NS`, `RecordingError`, `add_foxglove_argument`, `RecordingVehicle`, `RecordingSegmenter`,
`level`, `log_text`, `finite`, `LATCHED`, `Latch`, `quiet_handshakes`.

Channels (well-known Foxglove schemas, protobuf; `palletpilot.*`: JSON with a JSON schema), one a line:
topic, schema, when.

- `/tf`, foxglove.FrameTransforms, every tick: `map -> base_link` (localization as the executor read
  it), `base_link -> camera` (the last calibration, at the lift height; from the first calibration on);
  between the legs of an AGV session (no runner), `/tf` and `/vehicle/state` at 2 Hz
- `/vehicle/state`, palletpilot.VehicleState, every tick: pose, speed, steering, commanded speed, fork
  height, load, lateral and heading error, MPC solve time, state, task
- `/vehicle/beams`, palletpilot.Beams, 2 Hz and whenever the executor reads them: fork-tip ranges (m)
- `/scene/roadmap`, `/scene/temporary_nodes`, foxglove.SceneUpdate: at the start; when the roadmap changes
- `/scene/planned_paths`, `/scene/driven_path`, `/scene/mpc_horizon`, foxglove.SceneUpdate: per new
  plan; every 2 s; per MPC solve
- `/scene/truck`, `/scene/beams`, `/scene/safety_fields`, foxglove.SceneUpdate: on change (`base_link`)
- `/scene/pallet_estimates`, foxglove.SceneUpdate: per estimate: estimated pallet, node, tolerance box
- `/perception/calibration`, palletpilot.Calibration: per calibration (`Calibration.to_json`)
- `/camera/rgb`, `/camera/segmentation`, foxglove.CompressedImage (JPEG): per frame perception used;
  the overlay per frame segmented
- `/camera/depth`, foxglove.PointCloud: per frame perception used, in `camera`
- `/camera/calibration`, foxglove.CameraCalibration: per frame, the intrinsics
- `/log`, foxglove.Log: per event, with its level
- `/events`, palletpilot.Event: per event, the `events.jsonl` line
- `/roadmap/graph`, palletpilot.Roadmap: at the start, nodes and curves (for `palletpilot replay`)
- `/report/task`, palletpilot.TaskResult: per finished task; `/report/run`, palletpilot.RunResult: at the
  end, every `TaskResult` and the run's figures (for `replay`)
- `/sim/true_pose` (foxglove.PoseInFrame), `/scene/true_pallets`, `/scene/obstacles`: simulator only

Live: the channels of `LATCHED` are sent again when a viewer subscribes late (`Latch`), so it gets the
roadmap and the static scene; `quiet_handshakes` keeps refused viewers out of the run's output.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import threading
from collections.abc import Callable
from typing import Any

import foxglove
import numpy as np
from foxglove.messages import LogLevel
from foxglove.websocket import ServerListener

from palletpilot.executor.ports import PassThroughVehicle
from palletpilot.geometry import SE2, PalletpilotError
from palletpilot.geometry.fileio import dumps_json

RECORDING = "run.mcap"
"""The recording's name in the report folder."""
RESUMED_RECORDING = "run-resumed.mcap"
"""A resumed run's recording (the interrupted run's `run.mcap` stays as it was)."""
FOXGLOVE_PORT = 8765
"""The Foxglove WebSocket port of `--foxglove` without a number."""
SIM_EPOCH_NS = 1_704_067_200_000_000_000
"""Simulated time 0 as a timestamp: 2024-01-01T00:00:00Z (ns)."""

BEAMS_EVERY = 10  # ticks: 2 Hz
DRIVEN_EVERY = 40  # ticks: the driven path every 2 s
DRIVEN_STEP_M = 0.10  # a driven-path point every 10 cm
PALLETS_EVERY = 5  # ticks: a carried pallet's pose at 4 Hz
OBSTACLES_EVERY = 20  # ticks: walking people at 1 Hz
DEPTH_STRIDE = 3  # every 3rd depth pixel each way: 1/9 of the points
IDLE_EVERY = 10  # ticks: between a session's legs (`palletpilot agv`) the truck at 2 Hz

ERROR_EVENTS = frozenset(
    {
        "task_failed",
        "internal_error",
        "safety_stop",
        "vehicle_not_stopped",
        "stop_error",
        "stop_failed",
        "return_failed",
        "leg_failed",
    }
)
WARNING_EVENTS = frozenset(
    {
        "calibration_failed",
        "calibration_warning",
        "calibration_refused",
        "calibration_untrusted",
        "calibration_axis_kept",
        "camera_mount_warning",
        "perception_result_discarded",
        "path_blocked_hold",
        "entry_blocked",
        "approach_infeasible",
        "paused",
        "returning_on_failure",
        "recording_error",
        "order_rejected",
        "message_rejected",
    }
)
DEBUG_EVENTS = frozenset({"state_start", "state_end"})


def json_schema(name: str, properties: dict[str, str]) -> foxglove.Schema:
    """A JSON schema naming the message's fields (Foxglove's plot and raw-message panels use it)."""
    doc = {"type": "object", "properties": {k: {"type": v} for k, v in properties.items()}}
    return foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(doc).encode())


_NUM = "number"
TOPICS: dict[str, str] = {
    "/tf": "foxglove.FrameTransforms",
    "/vehicle/state": "palletpilot.VehicleState",
    "/vehicle/beams": "palletpilot.Beams",
    "/scene/roadmap": "foxglove.SceneUpdate",
    "/scene/temporary_nodes": "foxglove.SceneUpdate",
    "/scene/planned_paths": "foxglove.SceneUpdate",
    "/scene/driven_path": "foxglove.SceneUpdate",
    "/scene/mpc_horizon": "foxglove.SceneUpdate",
    "/scene/truck": "foxglove.SceneUpdate",
    "/scene/beams": "foxglove.SceneUpdate",
    "/scene/safety_fields": "foxglove.SceneUpdate",
    "/scene/pallet_estimates": "foxglove.SceneUpdate",
    "/scene/true_pallets": "foxglove.SceneUpdate",
    "/scene/obstacles": "foxglove.SceneUpdate",
    "/sim/true_pose": "foxglove.PoseInFrame",
    "/perception/calibration": "palletpilot.Calibration",
    "/camera/rgb": "foxglove.CompressedImage",
    "/camera/segmentation": "foxglove.CompressedImage",
    "/camera/depth": "foxglove.PointCloud",
    "/camera/calibration": "foxglove.CameraCalibration",
    "/log": "foxglove.Log",
    "/events": "palletpilot.Event",
    "/roadmap/graph": "palletpilot.Roadmap",
    "/report/task": "palletpilot.TaskResult",
    "/report/run": "palletpilot.RunResult",
}
"""Every channel a recording may hold, with its schema name."""

JSON_FIELDS: dict[str, dict[str, str]] = {
    "/vehicle/state": {
        "t_s": _NUM,
        "x_m": _NUM,
        "y_m": _NUM,
        "yaw_deg": _NUM,
        "speed_mps": _NUM,
        "steering_deg": _NUM,
        "commanded_speed_mps": _NUM,
        "fork_height_m": _NUM,
        "loaded": "boolean",
        "lateral_error_m": _NUM,
        "heading_error_deg": _NUM,
        "solve_ms": _NUM,
        "state": "string",
        "task": "integer",
    },
    "/vehicle/beams": {"left_m": _NUM, "right_m": _NUM, "read_by": "string"},
    "/perception/calibration": {"xyz_m": "array", "tilt_deg": _NUM, "pan_deg": _NUM, "quality": "object"},
    "/events": {"t": _NUM, "event": "string"},
    "/roadmap/graph": {"name": "string", "nodes": "array", "edges": "array"},
    "/report/task": {"index": "integer", "type": "string", "result": "string", "reason": "string"},
    "/report/run": {"mission": "string", "success": "boolean", "results": "array"},
}


class RecordingError(PalletpilotError):
    """The live view cannot start (its port is taken, its host unknown): an input problem."""


LATCHED = frozenset(
    {"/roadmap/graph", "/scene/roadmap", "/scene/temporary_nodes", "/scene/planned_paths", "/scene/true_pallets"}
    | {"/scene/obstacles", "/perception/calibration"}
)
"""Channels that hold a state sent seldom: a viewer that subscribes late gets their last message again."""


class Latch(ServerListener):
    """The last message of each `LATCHED` channel, and the ones a viewer has just subscribed to.

    A viewer that joins after the start still gets the roadmap and the static scene, as a latched ROS
    topic gives it: `on_subscribe` (the SDK's thread) marks the channel; the recorder's next tick sends
    its last message again (`due`), to every sink, so run.mcap holds it once more per late subscription.
    """

    def __init__(self) -> None:
        self._last: dict[str, Any] = {}
        self._due: set[str] = set()
        self._lock = threading.Lock()

    def keep(self, topic: str, message: Any) -> None:
        """Remember `message` as `topic`'s last (a no-op for channels that are not latched)."""
        if topic in LATCHED:
            with self._lock:
                self._last[topic] = message

    def on_subscribe(self, client: Any, channel: Any) -> None:
        """A viewer subscribed: its latched channel is due again."""
        if channel.topic in LATCHED:
            with self._lock:
                self._due.add(channel.topic)

    def due(self) -> list[tuple[str, Any]]:
        """The (topic, last message) pairs to send again now; each once per subscription."""
        with self._lock:
            out = [(t, self._last[t]) for t in sorted(self._due) if t in self._last]
            self._due.clear()
        return out


class _NoHandshakeNoise(logging.Filter):
    """Drops the SDK's `Dropping client ...: handshake failed` (a viewer asking for another subprotocol,
    a port scanner): a viewer's problem, printed into the run's progress line by Python's last-resort
    handler. Every other record of the SDK passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "handshake failed" not in record.getMessage()


SERVER_LOGGER = "foxglove.websocket.server"
"""The logger the foxglove SDK's WebSocket server writes to (through Python logging)."""


def quiet_handshakes() -> None:
    """Keep failed viewer handshakes out of the run's output (idempotent; before the server starts)."""
    logger = logging.getLogger(SERVER_LOGGER)
    if not any(isinstance(f, _NoHandshakeNoise) for f in logger.filters):
        logger.addFilter(_NoHandshakeNoise())


def add_foxglove_argument(parser: argparse.ArgumentParser) -> None:
    """`--foxglove [PORT]` and `--foxglove-host HOST`: serve the run's channels live over the Foxglove
    WebSocket protocol on HOST:PORT (default 127.0.0.1:8765); for `run` and any command that records a run."""
    parser.add_argument(
        "--foxglove",
        nargs="?",
        const=FOXGLOVE_PORT,
        type=_port,
        metavar="PORT",
        help=f"also show the run live in Foxglove (ws://127.0.0.1:PORT, default {FOXGLOVE_PORT}; 0: any free port; "
        "the viewer needs the foxglove.sdk.v1 subprotocol; with `run`, --clock wall plays it in real time)",
    )
    parser.add_argument(
        "--foxglove-host",
        default="127.0.0.1",
        metavar="HOST",
        help="the address --foxglove serves on (default 127.0.0.1, this machine only; 0.0.0.0: every interface)",
    )


def _port(text: str) -> int:
    """An argparse type: a TCP port 0..65535 (the adapter's own; it imports no CLI module)."""
    try:
        value = int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got '{text}'") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be an integer in 0..65535, got '{text}'")
    return value


class RecordingVehicle(PassThroughVehicle):
    """A `VehiclePort` that passes everything through and remembers what the executor read: the last
    localization fix (`T_world_forklift`, map frame) and the last beam ranges (m)."""

    def __init__(self, inner: Any, on_beams: Callable[[tuple[float, float]], None] | None = None) -> None:
        super().__init__(inner)
        self.last_pose: SE2 | None = None
        self.last_ranges: tuple[float, float] | None = None
        self._on_beams = on_beams

    def localization(self) -> SE2:
        """`T_world_forklift` from localization, remembered."""
        pose = self.inner.localization()
        self.last_pose = pose
        return pose

    def proximity_ranges(self) -> tuple[float, float]:
        """The fork-tip beams (m), remembered and recorded."""
        ranges = self.inner.proximity_ranges()
        self.last_ranges = ranges
        if self._on_beams is not None:
            self._on_beams(ranges)
        return ranges


class RecordingSegmenter:
    """A `SegmentationService` whose labels are also recorded as the overlay of the frame they belong to."""

    def __init__(self, inner: Any, recorder: Any) -> None:
        self.inner = inner
        self.recorder = recorder

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        labels = self.inner.segment(rgb)
        self.recorder.overlay_segmentation(rgb, labels)
        return labels

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def level(event: str) -> LogLevel:
    if event in ERROR_EVENTS:
        return LogLevel.Error
    if event in WARNING_EVENTS:
        return LogLevel.Warning
    if event in DEBUG_EVENTS:
        return LogLevel.Debug
    return LogLevel.Info


def log_text(event: str, data: dict[str, Any]) -> str:
    parts = [f"{k}={dumps_json(v) if not isinstance(v, str) else v}" for k, v in data.items()]
    text = f"{event}: {', '.join(parts)}" if parts else event
    return text if len(text) <= 2000 else text[:1997] + "..."


def finite(x: float | None, digits: int) -> float | None:
    return round(float(x), digits) if x is not None and math.isfinite(x) else None

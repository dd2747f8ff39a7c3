"""Run recordings: everything the truck saw and did, as MCAP (`run.mcap`) and live over Foxglove WebSocket.

A `Recorder` (foxglove-sdk: its MCAP writer and WebSocket server share one `foxglove.Context`, so both
carry the same channels) is fed by a run: `attach(runner)` (events through the runner's listeners,
the vehicle's readings through a pass-through wrapper), `tick()` once per control tick (the
simulator's step callback; a robot's loop), `wrap_grab` / `wrap_segmenter` (the camera frames
perception used and the labels it segmented), `finish(success)` and `close()`. A `SimFeed` adds the
simulator's truth.

A session (`palletpilot agv`: one `Runner` per leg, for as long as the process lives) records into one
file: `start_session(...)` once (the roadmap, the truck, the vehicle wrapper every runner then drives
through), `attach(runner)` at the start of each leg and `detach()` at its end, `tick()` every control
tick (between legs `/tf` and `/vehicle/state` at 2 Hz), `note(event, data)` for the session's own
events (orders, instant actions, legs: `/log` and `/events`, as a runner's), `finish_session(...)`
(`/report/run` with every leg's task results, so `palletpilot replay` reads a session as it reads a
run) and `close()`. `flush_s` finishes the current MCAP chunk that often (wall time), so a process
that dies loses at most that much: its file lacks the summary and ends in an open chunk, a streaming
reader (`mcap.stream_reader`) reads every flushed chunk, `palletpilot replay` refuses it in one line.

The recorder never changes what the run does: it only reads, it never draws from
the simulator's random generators, and any error in it is recorded once (`errors`) and ends the
recording, never the run.

Frames (REP 105, `executor.recording_scene`): `map` (world), `base_link` (forklift), `camera` (optical).
Time: the run's clock in nanoseconds: simulated seconds from `SIM_EPOCH_NS` (2024-01-01T00:00:00Z, so
a seeded run records the same stamps), or wall time; `log_time` never decreases.

Channels: `executor.recording_channels` lists them (topic, schema, when; `TOPICS`). The recorder's
event handlers live in `executor.recording_events` and its camera side in `executor.recording_camera`
(both bases of `Recorder`); scene messages are built by `executor.recording_scene`.

Cost: the recorder times itself; `cost()` gives the time spent in it per control tick (mean, p99,
max, ms), also written as the MCAP metadata record `recording_cost`.

Public API: `Recorder` (`attach`, `tick`, `finish`, `close`; sessions: `start_session`, `detach`,
`note`, `finish_session`), `SimFeed`, `RecordingVehicle`, `start_recording`, `add_foxglove_argument`,
`FOXGLOVE_PORT`, `SIM_EPOCH_NS`, `RECORDING`, `RESUMED_RECORDING`, `TOPICS`.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import foxglove
import numpy as np
from foxglove.channels import (
    CameraCalibrationChannel,
    CompressedImageChannel,
    FrameTransformsChannel,
    LogChannel,
    PointCloudChannel,
    PoseInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.messages import Point3

from palletpilot.control.follower import FollowerStatus
from palletpilot.control.safety import safety_fields
from palletpilot.executor.adapters.mcap import recording_scene as scene
from palletpilot.executor.adapters.mcap.recording_camera import RecorderCamera
from palletpilot.executor.adapters.mcap.recording_channels import (
    BEAMS_EVERY,
    DRIVEN_EVERY,
    DRIVEN_STEP_M,
    FOXGLOVE_PORT,
    IDLE_EVERY,
    JSON_FIELDS,
    RECORDING,
    RESUMED_RECORDING,
    SIM_EPOCH_NS,
    TOPICS,
    Latch,
    RecordingError,
    RecordingVehicle,
    add_foxglove_argument,
    finite,
    json_schema,
    quiet_handshakes,
)
from palletpilot.executor.adapters.mcap.recording_events import RecorderEvents
from palletpilot.executor.adapters.mcap.recording_sim import SimFeed
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import dumps_json
from palletpilot.perception.frames import FrameBundle

if TYPE_CHECKING:
    from palletpilot.control.follower import Follower
    from palletpilot.control.vehicle import VehicleParams
    from palletpilot.executor.core.results import TaskResult
    from palletpilot.executor.core.runner import Runner
    from palletpilot.executor.ports import VehiclePort
    from palletpilot.perception.specs import ForkGeometry
    from palletpilot.roadmap import Roadmap

COST_SAMPLES = 72_000
"""Tick costs kept for `cost()`'s p99: the last hour at 20 Hz (mean and max are over every tick)."""

__all__ = [
    "FOXGLOVE_PORT",
    "RECORDING",
    "RESUMED_RECORDING",
    "SIM_EPOCH_NS",
    "TOPICS",
    "Recorder",
    "RecordingError",
    "RecordingVehicle",
    "SimFeed",
    "add_foxglove_argument",
    "start_recording",
]


class Recorder(RecorderCamera, RecorderEvents):
    """Records one run (see the module docstring). `mcap`: the file to write (None: none); `port`: serve
    the channels live on host:port (None: no server, 0: any free port, see `port`); `wall`: stamps from
    wall time (else simulated time from `SIM_EPOCH_NS`). A server that cannot start raises
    `RecordingError` (an input problem: the port is taken); a file that cannot be opened is a line in
    `errors` and the run goes on without it. `flush_s`: finish the current chunk at least this often
    (wall seconds; None: only when it is full, 1 MiB)."""

    def __init__(
        self,
        mcap: Path | None,
        port: int | None = None,
        wall: bool = False,
        host: str = "127.0.0.1",
        flush_s: float | None = None,
    ) -> None:
        self.path = mcap
        self.wall = wall
        self.flush_s = flush_s
        self._last_flush = time.monotonic()
        self._session = False
        self.errors: list[str] = []
        self.ctx = foxglove.Context()
        self._lock = threading.Lock()
        self._writer: Any = None
        self._server: Any = None
        self._closed = False
        self._now: Callable[[], float] = lambda: 0.0
        self._epoch_ns = SIM_EPOCH_NS
        self._last_ns = 0
        self._tick_s: deque[float] = deque(maxlen=COST_SAMPLES)  # the last hour's ticks (a session is long)
        self._tick_stats = [0, 0.0, 0.0]  # every tick: count, total (s), max (s)
        self._pending_s = 0.0
        self._ticks = 0
        self.counts: dict[str, int] = {}
        self._latch = Latch()  # late viewers: the last message of the seldom-sent channels
        self.runner: Runner | None = None
        self.sim: SimFeed | None = None
        self.vehicle: RecordingVehicle | None = None
        self._params: VehicleParams | None = None
        self._forks: ForkGeometry | None = None
        self._roadmap: Roadmap | None = None
        self._follower: Follower | None = None
        self._init_state()
        if mcap is not None:
            try:
                options = foxglove.mcap.MCAPWriteOptions(compression_threads=0, chunk_size=1 << 20)
                self._writer = foxglove.open_mcap(mcap, allow_overwrite=True, context=self.ctx, writer_options=options)
            except Exception as exc:
                self.errors.append(f"{mcap}: cannot write the recording: {exc}")
        if port is not None:
            try:
                quiet_handshakes()
                self._server = foxglove.start_server(
                    name="palletpilot", host=host, port=port, context=self.ctx, server_listener=self._latch
                )
            except Exception as exc:
                self._shutdown()
                raise RecordingError(f"--foxglove: cannot serve on {host}:{port}: {exc}") from None
        self._make_channels()

    def _init_state(self) -> None:
        self._calibration: SE3 | None = None  # T_forklift_camera at lift height 0
        self._state, self._task_index = "", -1
        self._task: dict[str, Any] | None = None
        self._state_started: dict[str, float] = {}
        self._n_lateral = self._n_solve = 0
        self._plan: Any = None
        self._horizon_shown = False
        self._paths_seen = 0
        self._path_points: list[list[Point3]] = []
        self._roadmap_version = -1
        self._truck_key: tuple[float, bool] | None = None
        self._safety_key: Any = None
        self._driven: list[Point3] = []
        self._driven_last: tuple[float, float] | None = None
        self._driven_sent = 0
        self._estimates: list[Any] = []
        self._frame_stamps: dict[int, int] = {}
        self._last_frame: FrameBundle | None = None

    def _make_channels(self) -> None:
        c = self.ctx
        self.ch_tf = FrameTransformsChannel("/tf", context=c)
        self.ch_log = LogChannel("/log", context=c)
        self.ch_rgb = CompressedImageChannel("/camera/rgb", context=c)
        self.ch_seg = CompressedImageChannel("/camera/segmentation", context=c)
        self.ch_depth = PointCloudChannel("/camera/depth", context=c)
        self.ch_caminfo = CameraCalibrationChannel("/camera/calibration", context=c)
        self.ch_true_pose = PoseInFrameChannel("/sim/true_pose", context=c)
        self.scene = {t: SceneUpdateChannel(t, context=c) for t, s in TOPICS.items() if s == "foxglove.SceneUpdate"}
        self.json = {
            t: foxglove.Channel(
                t, schema=json_schema(TOPICS[t], JSON_FIELDS.get(t, {})), message_encoding="json", context=c
            )
            for t, s in TOPICS.items()
            if s.startswith("palletpilot.")
        }

    # -- plumbing -------------------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        """True while the recording takes messages (a sink is open and nothing failed)."""
        return not self._closed and (self._writer is not None or self._server is not None)

    @property
    def port(self) -> int | None:
        """The WebSocket server's port (None without a server)."""
        return None if self._server is None else int(self._server.port)

    def ns(self, t_s: float | None = None) -> int:
        """A log time (ns) for clock time `t_s` (s; default: now), never earlier than the last one."""
        t = self._now() if t_s is None else t_s
        ns = self._epoch_ns + round(t * 1e9)
        with self._lock:
            ns = max(ns, self._last_ns)
            self._last_ns = ns
        return ns

    def count_message(self, topic: str) -> None:
        """Count one message written on `topic` (the recording's per-channel figures)."""
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def log_scene(self, topic: str, update: Any, ns: int) -> None:
        """Log a SceneUpdate on a `/scene/...` topic."""
        self.scene[topic].log(update, log_time=ns)
        self.count_message(topic)
        self._latch.keep(topic, update)

    def log_json(self, topic: str, doc: Any, ns: int) -> None:
        """Log a JSON document (strict: non-finite numbers as null) on a JSON topic."""
        self.json[topic].log(dumps_json(doc).encode(), log_time=ns)
        self.count_message(topic)
        self._latch.keep(topic, doc)

    def _fail(self, where: str, exc: BaseException) -> None:
        """An error inside the recorder: one line, and the recording stops (the run goes on)."""
        self.errors.append(f"{self.path or 'recording'}: recording stopped ({where}): {type(exc).__name__}: {exc}")
        self._closed = True
        self._shutdown()

    def _guard(self, where: str, fn: Callable[[], None]) -> None:
        if not self.active:
            return
        t0 = time.perf_counter()
        try:
            fn()
        except Exception as exc:
            self._fail(where, exc)
        with self._lock:
            self._pending_s += time.perf_counter() - t0

    # -- wiring -----------------------------------------------------------------------------------------
    def wrap_vehicle(self, vehicle: VehiclePort) -> VehiclePort:
        """The vehicle a single run's runner must be built on: it passes everything through to `vehicle` and
        remembers what the executor read (localization, beams). Call before building the runner; the
        recorder never swaps a runner's vehicle afterwards."""
        self.vehicle = RecordingVehicle(vehicle, on_beams=self._beams_read)
        return cast("VehiclePort", self.vehicle)

    def attach(self, runner: Runner, sim: SimFeed | None = None) -> None:
        """Follow `runner`: its clock, its events (`on_event`, a `RunObserver` the runner was built with:
        `compose.build_runner`), the readings of the vehicle from `wrap_vehicle`; record the roadmap and
        the start. Call before the runner logs its first event. In a session: a new leg (the runner drives
        the session's vehicle wrapper; the roadmap was recorded at the session's start). A runner built
        without `on_event` is a `ValueError`: nothing is subscribed into a runner after it is built."""
        if self.on_event not in runner.listeners:
            raise ValueError("Recorder.attach: build the runner with Recorder.on_event among its observers")
        self.runner = runner
        ctx = runner.ctx
        self._params, self._forks, self._roadmap, self._follower = ctx.params, ctx.forks, ctx.roadmap, ctx.follower
        if self._session:
            self._guard("leg", self._leg_start)
            return
        self.sim = sim
        self._now = runner.clock.now
        if self.wall:
            self._epoch_ns = time.time_ns() - round(runner.clock.now() * 1e9)
        if self.vehicle is None:
            raise ValueError("Recorder.attach: build the runner on Recorder.wrap_vehicle(vehicle) first")
        self._guard("start", lambda: self._start(runner.mission.name))

    def start_session(
        self,
        vehicle: VehiclePort,
        now: Callable[[], float],
        params: VehicleParams,
        forks: ForkGeometry,
        roadmap: Roadmap,
        follower: Follower,
        name: str,
    ) -> VehiclePort:
        """Start recording a session of many runs (see the module docstring) on `vehicle` with the clock
        `now` (s); record the roadmap. Returns the vehicle every runner of the session must drive (it
        passes everything through to `vehicle` and remembers what was read)."""
        self._session = True
        self._now = now
        self._params, self._forks, self._roadmap, self._follower = params, forks, roadmap, follower
        if self.wall:
            self._epoch_ns = time.time_ns() - round(now() * 1e9)
        self.vehicle = RecordingVehicle(vehicle, on_beams=self._beams_read)
        self._guard("start", lambda: self._start(name))
        return cast("VehiclePort", self.vehicle)

    @property
    def in_session(self) -> bool:
        """True after `start_session`: every runner drives the session's vehicle wrapper (`attach` only
        follows it)."""
        return self._session

    def detach(self) -> None:
        """The end of a session's leg: ticks go on without a runner until the next `attach`."""
        self.runner = None

    def _leg_start(self) -> None:
        """A session's new leg: forget the last leg's task, plans and estimates (the calibration stays)."""
        self._state, self._task_index, self._task = "", -1, None
        self._state_started = {}
        self._paths_seen, self._path_points = 0, []
        self._estimates = []
        self._driven, self._driven_sent = [], 0  # each leg's own driven line: no message grows for ever

    def note(self, event: str, data: dict[str, Any]) -> None:
        """An event of the session itself (an order, an instant action, a leg), recorded as a runner's
        events are (`/log` with its level, `/events`); from any thread."""
        self._guard(f"event {event}", lambda: self._event(event, data, self._now()))

    def _start(self, name: str) -> None:
        assert self._roadmap is not None
        ns = self.ns()
        roadmap = self._roadmap
        if self._writer is not None:
            self._writer.write_metadata(
                "palletpilot",
                {
                    "mission": name,
                    "clock": "wall" if self.wall else "simulated",
                    "frames": "map base_link camera",
                    **({"session": "one runner per leg"} if self._session else {}),
                },
            )
        nodes = [scene.node_json(n) for n in roadmap.nodes() if not n.temporary]
        edges = [scene.edge_json(e) for e in roadmap.edges() if not e.temporary]
        self.log_json("/roadmap/graph", {"name": roadmap.name, "nodes": nodes, "edges": edges}, ns)
        self.log_scene("/scene/roadmap", scene.roadmap_update(roadmap, ns, temporary=False), ns)
        self.log_scene("/scene/temporary_nodes", scene.roadmap_update(roadmap, ns, temporary=True), ns)
        self._roadmap_version = roadmap.version
        if self.sim is not None:
            self.sim.start(self, ns)

    # -- what the run feeds ---------------------------------------------------------------------------
    def on_event(self, event: str, data: dict[str, Any], t: float) -> None:
        """A runner listener: the event as a Log (with its level) and as JSON; what it implies."""
        self._guard(f"event {event}", lambda: self._event(event, data, t))

    def tick(self) -> None:
        """One control tick (call once per tick, e.g. at the start of the simulator's step)."""
        if self.vehicle is None:
            return
        self._guard("tick", self._tick)
        with self._lock:
            spent = self._pending_s
            self._tick_s.append(spent)
            stats = self._tick_stats
            stats[0], stats[1], stats[2] = stats[0] + 1, stats[1] + spent, max(stats[2], spent)
            self._pending_s = 0.0

    def finish(self, success: bool, extra: dict[str, Any] | None = None) -> None:
        """The end of the run: `/report/run` (every TaskResult, and `extra`: the report's run figures), the
        final scene, the cost metadata."""
        self._guard("finish", lambda: self._finish(success, extra))

    def finish_session(
        self, name: str, success: bool, results: list[TaskResult], extra: dict[str, Any] | None = None
    ) -> None:
        """The end of a session: `/report/run` named `name` with every leg's `TaskResult` and `extra`, the
        final scene, the cost metadata (then `close()`)."""
        doc: dict[str, Any] = {"mission": name, "success": success, **(extra or {})}
        self._guard("finish", lambda: self._report(doc, results))

    def close(self) -> None:
        """Finish the file and stop the server (idempotent). Errors land in `errors`."""
        if self._closed:
            return
        self._closed = True
        self._shutdown()

    def _shutdown(self) -> None:
        writer, server = self._writer, self._server
        self._writer = self._server = None
        if writer is not None:
            try:
                writer.close()
            except Exception as exc:
                self.errors.append(f"{self.path}: cannot finish the recording: {exc}")
        if server is not None:
            try:
                server.stop()
            except Exception as exc:  # pragma: no cover - the server's own failure
                self.errors.append(f"foxglove: cannot stop the server: {exc}")

    def cost(self) -> dict[str, Any]:
        """Time spent in the recorder per control tick (ms): `ticks`, `mean_ms`, `p99_ms` (over the last
        `COST_SAMPLES` ticks), `max_ms`."""
        with self._lock:
            ms = np.asarray(self._tick_s, dtype=float) * 1e3
            count, total, most = self._tick_stats
        if not count:
            return {"ticks": 0, "mean_ms": None, "p99_ms": None, "max_ms": None}
        return {
            "ticks": int(count),
            "mean_ms": round(total / count * 1e3, 4),
            "p99_ms": round(float(np.percentile(ms, 99)), 4),
            "max_ms": round(most * 1e3, 3),
        }

    # -- ticks --------------------------------------------------------------------------------------------
    def _tick(self) -> None:
        runner, vehicle = self.runner, self.vehicle  # no runner: between a session's legs
        assert vehicle is not None and self._roadmap is not None
        self._ticks += 1
        for topic, message in self._latch.due():  # a viewer joined late (`Latch`)
            (self.log_scene if topic in self.scene else self.log_json)(topic, message, self.ns())
        if self.flush_s is not None and time.monotonic() - self._last_flush >= self.flush_s:
            self._last_flush = time.monotonic()
            writer = self._writer
            if writer is not None:
                writer.flush()  # a finished chunk on disk: a crash loses at most the last flush_s
        if runner is None and self._ticks % IDLE_EVERY:
            return  # between legs the truck stands: 2 Hz is enough
        ns = self.ns()
        height = vehicle.fork_height
        pose = vehicle.last_pose
        if pose is not None:
            self._drive_point(pose)
        mount = None if self._calibration is None else SE3.from_translation(0.0, 0.0, height) @ self._calibration
        tf = scene.tf_tree(ns, pose, mount)
        if tf is not None:
            self.ch_tf.log(tf, log_time=ns)
            self.count_message("/tf")
        loaded = bool(vehicle.load_detected())
        follower = self._follower
        assert follower is not None
        flog = follower.log
        lateral = heading = solve = None
        if len(flog.lateral) > self._n_lateral:
            self._n_lateral = len(flog.lateral)
            lateral, heading = flog.lateral[-1], math.degrees(flog.heading[-1])
        if len(flog.solve_s) > self._n_solve:
            self._n_solve = len(flog.solve_s)
            solve = flog.solve_s[-1] * 1e3
        commanded = None if runner is None else finite(getattr(runner.vehicle, "commanded_speed", None), 4)
        state = {
            "t_s": round(self._now(), 3),
            "x_m": None if pose is None else round(pose.x, 4),
            "y_m": None if pose is None else round(pose.y, 4),
            "yaw_deg": None if pose is None else round(math.degrees(pose.yaw), 3),
            "speed_mps": finite(vehicle.speed, 4),
            "steering_deg": finite(math.degrees(vehicle.steering), 3),
            "commanded_speed_mps": commanded,
            "fork_height_m": finite(height, 4),
            "loaded": loaded,
            "lateral_error_m": finite(lateral, 4),
            "heading_error_deg": finite(heading, 3),
            "solve_ms": finite(solve, 3),
            "state": self._state,
            "task": self._task_index,
        }
        self.json["/vehicle/state"].log(json.dumps(state).encode(), log_time=ns)
        self.count_message("/vehicle/state")
        self._horizon(follower, ns)
        planned = [] if runner is None else runner.ctx.memory.planned_paths
        if runner is not None and len(planned) != self._paths_seen:
            self._paths_seen = len(planned)
            self._path_points = [[Point3(x=x, y=y, z=0.0) for x, y in p[::2] + p[-1:]] for p in planned]
            self.log_scene("/scene/planned_paths", scene.paths_update(self._path_points, ns), ns)
        roadmap = self._roadmap
        if roadmap.version != self._roadmap_version:
            self._roadmap_version = roadmap.version
            self.log_scene("/scene/temporary_nodes", scene.roadmap_update(roadmap, ns, temporary=True), ns)
        key = (round(height, 3), loaded)
        if key != self._truck_key:
            self._truck_key = key
            assert self._params is not None and self._forks is not None
            self.log_scene("/scene/truck", scene.truck_update(self._params, self._forks, height, loaded, ns), ns)
        self._safety(ns)
        if self._ticks % BEAMS_EVERY == 0:
            self._beams(vehicle.inner.proximity_ranges(), "recorder", ns)
        if self._ticks % DRIVEN_EVERY == 0:
            self._send_driven(ns)
        if self.sim is not None:
            self.sim.tick(self, ns, self._ticks)

    def _drive_point(self, pose: SE2) -> None:
        last = self._driven_last
        if last is None or math.hypot(pose.x - last[0], pose.y - last[1]) >= DRIVEN_STEP_M:
            self._driven_last = (pose.x, pose.y)
            self._driven.append(Point3(x=pose.x, y=pose.y, z=0.0))

    def _send_driven(self, ns: int) -> None:
        if len(self._driven) != self._driven_sent:
            self._driven_sent = len(self._driven)
            update = scene.polyline_update("driven", self._driven, ns, (0.84, 0.15, 0.16, 1.0), 0.04)
            self.log_scene("/scene/driven_path", update, ns)

    def _horizon(self, follower: Any, ns: int) -> None:
        """The MPC's predicted states (map frame) after each accepted solve, if the follower exposes them."""
        plan = getattr(follower, "last_plan", None)
        running = follower.status is FollowerStatus.RUNNING
        base = follower.filter.pose
        if running and plan is not None and plan is not self._plan and base is not None:
            self._plan = plan
            xy = base.apply(np.asarray(plan)[:, :2])
            pts = [Point3(x=float(x), y=float(y), z=0.0) for x, y in xy]
            self.log_scene(
                "/scene/mpc_horizon", scene.polyline_update("mpc", pts, ns, (0.58, 0.0, 0.83, 1.0), 0.05), ns
            )
            self._horizon_shown = True
        elif not running and self._horizon_shown:
            self._horizon_shown = False
            self.log_scene("/scene/mpc_horizon", scene.polyline_update("mpc", [], ns, (0, 0, 0, 0), 0.0), ns)

    def _safety(self, ns: int) -> None:
        params, forks = self._params, self._forks
        assert params is not None and forks is not None and self.vehicle is not None
        if params.safety_scanner is None:
            return
        s = self.vehicle.inner.safety_state()
        speed = abs(self.vehicle.speed)
        key = (s.field_set, s.direction, s.warning, s.protective_stop, s.intrusions, round(speed, 1))
        if key == self._safety_key:
            return
        self._safety_key = key
        fields = safety_fields(params, speed, s.direction, s.field_set, forks.tip_x)
        z = params.safety_scanner.scan_height
        update = scene.safety_update(fields, s.warning, s.protective_stop, s.intrusions, z, ns)
        self.log_scene("/scene/safety_fields", update, ns)

    def _beams_read(self, ranges: tuple[float, float]) -> None:
        self._guard("beams", lambda: self._beams(ranges, "executor", self.ns()))

    def _beams(self, ranges: tuple[float, float], who: str, ns: int) -> None:
        assert self._forks is not None and self.vehicle is not None
        left, right = (float(r) for r in ranges)
        self.log_json("/vehicle/beams", {"left_m": finite(left, 4), "right_m": finite(right, 4), "read_by": who}, ns)
        update = scene.beams_update(self._forks, self.vehicle.fork_height, (left, right), ns)
        self.log_scene("/scene/beams", update, ns)

    # -- the end ------------------------------------------------------------------------------------------
    def _finish(self, success: bool, extra: dict[str, Any] | None) -> None:
        assert self.runner is not None
        runner = self.runner
        doc: dict[str, Any] = {
            "mission": runner.mission.name,
            "success": success,
            "adapt": runner.settings.adapt,
            "stops": runner.stops,
            "clock": runner.clock.stats(),
        }
        if self.sim is not None:
            doc.update(self.sim.finish(self, self.ns()))
        doc.update(extra or {})
        self._report(doc, runner.results)

    def _report(self, doc: dict[str, Any], results: list[TaskResult]) -> None:
        """`/report/run` (`doc` and every result), the driven path's last points, the cost metadata."""
        ns = self.ns()
        self._send_driven(ns)
        doc["results"] = [r.to_json() for r in results]
        self.log_json("/report/run", doc, ns)
        if self._writer is not None:
            cost = self.cost()
            self._writer.write_metadata("recording_cost", {k: str(v) for k, v in cost.items()})


def start_recording(
    folder: Path | None,
    port: int | None,
    wall: bool,
    resumed: bool = False,
    host: str = "127.0.0.1",
    flush_s: float | None = None,
) -> Recorder | None:
    """The recorder of a run: `run.mcap` (`run-resumed.mcap` for a resumed run) in the report folder
    and/or the live server on `host:port`; None when neither is asked for. A file that cannot be opened
    is a line in `Recorder.errors` (the run goes on without it); a port that cannot be served raises
    `RecordingError`. `flush_s`: see `Recorder`."""
    if folder is None and port is None:
        return None
    path = None if folder is None else folder / (RESUMED_RECORDING if resumed else RECORDING)
    return Recorder(path, port, wall=wall, host=host, flush_s=flush_s)

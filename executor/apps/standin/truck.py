"""The simulator as a stand-in truck on ROS 2 (`palletpilot sim serve SCENARIO --ros`).

`StandIn` runs a `sim.simulator.Simulator` on the wall clock at the robot file's control rate and plays
the truck exactly as the robot file wires it (`executor.ros.config`), so that `palletpilot robot` is
tested end to end without hardware:

- publishes every tick: localization (tf `map -> base_link` on the tf topic, or the pose topic),
  odometry (`odom` or `map` frame, `base_link` twist), joint states (steering rad, fork lift m), the two
  fork-tip beams (`sensor_msgs/Range`, +inf when nothing is within 4 m), the load sensor and the safety
  diagnostics (status `safety`: `estop`, `protective_field`, `warning_field`, `speed_limit`, `field_set`,
  `direction`, `intrusions`; ERROR on a collision or a latched emergency stop); the camera (colour
  `rgb8`, depth aligned to it `16UC1` in mm, `camera_info`) at `camera.rate_hz`, rendered and published
  by a child process (`executor.ros.standin_camera`: a frame takes about 40 ms of ray casting that, in
  this process, held the GIL and delayed the receipt of drive commands by up to a frame); each frame is
  what `sim.grab()` would give for the truck's state when it was requested, and the child's first frame
  comes a few seconds after the start (its own interpreter and world);
- subscribes the drive command (`AckermannDriveStamped`: speed m/s, steering angle rad), the fork
  height target, the field case (`SET/DIRECTION`) and the emergency stop;
- behaves like a truck controller with a command timeout: when no drive command came for
  `command_timeout_s` (0.2 s) it brakes at the vehicle's emergency deceleration to a standstill, and
  drives again on the next command. The check wakes exactly at the deadline, not at the next tick. An
  emergency stop (`true` on its topic) latches until the executor has stopped commanding and the truck
  stands (the run ended), as a reset on the safety PLC would.

Stops cleanly when `stop` is set (the CLI's SIGINT / SIGTERM), and ends the camera child with it (the
child also dies on its own when this process dies in any way: `CameraProcess`). `stats()` gives the ticks,
the command latency (header stamp to receipt, ms: p50 / p99 / max; over Cyclone DDS also split at the
sender's DDS write, from the sample's source timestamp), the timeout brakes and emergency stops, the
camera frames with their render time (ms, in the child) and the camera child's failure, if any.
While it runs, the interpreter's thread switch interval is `GIL_SWITCH_S` (1 ms), so that the transport's
receive thread waits at most that long for the loop's Python work. `run(stop, on_tick)` calls
`on_tick(stand_in)` once per control tick (the live view of
`executor.ros.standin_foxglove`); `last_ranges` and `command_speed` are there for it.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from palletpilot.control.safety import FIELD_SETS, TRAVEL_DIRECTIONS
from palletpilot.executor.adapters.ros import messages as msgs
from palletpilot.executor.adapters.ros.config import RobotConfig
from palletpilot.executor.adapters.ros.transport import Transport
from palletpilot.executor.apps.standin.camera import CameraProcess, camera_messages, camera_state
from palletpilot.geometry import SE2
from palletpilot.sim.simulator import BEAM_MAX_RANGE_M, Simulator

GIL_SWITCH_S = 0.001
"""The interpreter's thread switch interval while the stand-in runs (s; Python's default is 5 ms): a drive
command arriving while the loop steps and publishes (a few ms of Python per tick) waits at most this long
for the GIL on the transport's receive thread."""


@dataclass
class _Command:
    speed: float = 0.0
    steering: float = 0.0
    received_s: float = -math.inf  # time.monotonic()


@dataclass
class StandInStats:
    """What the stand-in measured (see `StandIn.stats`)."""

    ticks: int = 0
    commands: int = 0
    latency_ms: list[float] = field(default_factory=list)
    sender_ms: list[float] = field(default_factory=list)  # header stamp to the sender's DDS write (Cyclone DDS)
    transit_ms: list[float] = field(default_factory=list)  # the sender's DDS write to the receipt here
    timeout_brakes: list[float] = field(default_factory=list)  # time.time() of each brake start
    emergency_stops: int = 0
    frames: int = 0


def _pct(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p99": None, "max": None}
    a = np.asarray(values)
    return {
        "p50": round(float(np.percentile(a, 50)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "max": round(float(a.max()), 3),
    }


class StandIn:
    """A simulated truck on the robot file's topics (module docstring)."""

    def __init__(
        self,
        sim: Simulator,
        config: RobotConfig,
        transport: Transport,
        camera_hz: float | None = None,
        camera_publisher: Literal["child", "stand-in"] = "child",
    ) -> None:
        """Subscribe the commands, advertise the outputs and start the camera child (when the robot file's
        camera is `ros` and `camera_hz` (Hz; default the robot file's `camera.rate_hz`) is above 0).

        `camera_publisher`: `child` (the camera child publishes the frames on its own transport of the robot
        file's kind and domain) or `stand-in` (it hands them back and they go out on `transport`: for an
        in-process transport such as `MemoryTransport`).
        """
        self.sim = sim
        self.config = config
        self.transport = transport
        self.camera_hz = config.camera.rate_hz if camera_hz is None else camera_hz
        x, y, yaw_deg = config.frames.base_link_to_forklift
        self.T_base_link_forklift = SE2(x, y, math.radians(yaw_deg))
        self._lock = threading.Lock()
        self._cmd = _Command()
        self._fork_target: float | None = None
        self._field_set: str | None = None
        self._estop_request = False
        self.estop_latched = False
        self.timeout_brake = True  # no command yet: the truck holds
        self.stats_ = StandInStats()
        self.last_ranges: tuple[float, float] | None = None  # the fork-tip beams last published (m)
        t = config.topics
        transport.subscribe(t.drive.name, msgs.AckermannDriveStamped, t.drive.qos.spec(), self._on_drive)
        transport.subscribe(t.fork_height.name, msgs.Float64, t.fork_height.qos.spec(), self._on_fork)
        transport.subscribe(t.emergency_stop.name, msgs.Bool, t.emergency_stop.qos.spec(), self._on_estop)
        transport.subscribe(t.field_set.name, msgs.String, t.field_set.qos.spec(), self._on_field_set)
        self._outputs = self._advertise()
        self._range_type = msgs.range_type(config.ros_distro)
        self.camera: CameraProcess | None = None
        self._frame_stamp_s = 0.0  # wall-clock time (s) of the state of the frame in flight
        self._camera_error_told = False
        if self.camera_hz > 0 and "color" in self._outputs:
            self.camera = CameraProcess(sim.scenario, sim.seed, config, publish=camera_publisher == "child")

    # -- subscriptions (the transport's receive thread: store only) ---------------------------------------
    def _on_drive(self, msg: msgs.AckermannDriveStamped, received_s: float) -> None:
        now = time.time()
        stamp = msgs.seconds(msg.header.stamp)
        # Cyclone DDS samples carry the writer's source timestamp (ns since the epoch, taken in its write
        # call): it splits the latency into the sender's part and the transport's plus ours.
        info = getattr(msg, "sample_info", None)
        written = None if info is None else getattr(info, "source_timestamp", None)
        with self._lock:
            self._cmd = _Command(float(msg.drive.speed), float(msg.drive.steering_angle), received_s)
            s = self.stats_
            s.commands += 1
            if len(s.latency_ms) < 1_000_000:
                s.latency_ms.append((now - stamp) * 1e3)
                if isinstance(written, int) and written > 0:
                    s.sender_ms.append((written * 1e-9 - stamp) * 1e3)
                    s.transit_ms.append((now - written * 1e-9) * 1e3)

    def _on_fork(self, msg: msgs.Float64, _received_s: float) -> None:
        self._fork_target = float(msg.data)

    def _on_estop(self, msg: msgs.Bool, _received_s: float) -> None:
        if msg.data:
            self._estop_request = True

    def _on_field_set(self, msg: msgs.String, _received_s: float) -> None:
        self._field_set = msg.data

    def _advertise(self) -> dict[str, tuple[str, Any]]:
        c, t = self.config, self.config.topics
        loc = c.localization.tf if c.localization.source == "tf" else c.localization.pose
        outputs: dict[str, tuple[str, Any]] = {
            "localization": (loc.name, loc.qos.spec()),
            "odometry": (t.odometry.name, t.odometry.qos.spec()),
            "joint_states": (t.joint_states.name, t.joint_states.qos.spec()),
            "beam_left": (t.beam_left.name, t.beam_left.qos.spec()),
            "beam_right": (t.beam_right.name, t.beam_right.qos.spec()),
            "load": (t.load.name, t.load.qos.spec()),
            "diagnostics": (t.diagnostics.name, t.diagnostics.qos.spec()),
        }
        if c.camera.source == "ros":
            cam = c.camera
            outputs |= {
                "color": (cam.color.name, cam.color.qos.spec()),
                "depth": (cam.depth.name, cam.depth.qos.spec()),
                "info": (cam.info.name, cam.info.qos.spec()),
            }
        return outputs

    @property
    def command_speed(self) -> float:
        """The speed (m/s) of the last drive command received (0 before the first)."""
        with self._lock:
            return self._cmd.speed

    def topics(self) -> list[str]:
        """The topics it publishes."""
        return [name for name, _ in self._outputs.values()]

    def _publish(self, key: str, msg: Any) -> None:
        name, qos = self._outputs[key]
        self.transport.publish(name, msg, qos)

    # -- the loop -----------------------------------------------------------------------------------------
    def run(self, stop: threading.Event, on_tick: Callable[[StandIn], None] | None = None) -> StandInStats:
        """Step and publish at the control rate until `stop` is set, then end the camera child; returns the
        statistics. `on_tick(self)` runs once per control tick, after the state is published (the live
        view, `executor.ros.standin_foxglove`)."""
        interval = sys.getswitchinterval()
        sys.setswitchinterval(min(interval, GIL_SWITCH_S))  # the receive thread waits <= 1 ms for the loop
        try:
            return self._loop(stop, on_tick)
        finally:
            sys.setswitchinterval(interval)
            self.close()

    def close(self) -> None:
        """End the camera child (harmless when there is none or it ended already)."""
        if self.camera is not None:
            self.camera.close()
            self._take_frames()

    def _loop(self, stop: threading.Event, on_tick: Callable[[StandIn], None] | None) -> StandInStats:
        dt = self.config.control_dt
        last_step = time.monotonic()
        next_tick = last_step
        next_frame = last_step
        while not stop.is_set():
            now = time.monotonic()
            with self._lock:
                cmd = self._cmd
            deadline = cmd.received_s + self.config.command_timeout_s
            wake = next_tick if self.timeout_brake or deadline >= next_tick else max(deadline, now)
            if wake > now:
                stop.wait(wake - now)
                continue
            now = time.monotonic()
            self._apply_commands(now)
            self.sim.step(min(max(now - last_step, 0.0), 0.2))
            last_step = now
            self._publish_state()
            if now >= next_tick:
                self.stats_.ticks += 1
                if on_tick is not None:
                    on_tick(self)
                next_tick = max(next_tick + dt, now - dt)  # no burst of catch-up ticks after a stall
            self._take_frames()
            if self.camera is not None and self.camera.idle and now >= next_frame:
                self._request_frame()
                next_frame = max(next_frame + 1.0 / self.camera_hz, time.monotonic() - 0.5 / self.camera_hz)
        return self.stats_

    def _apply_commands(self, now: float) -> None:
        """The truck controller: command timeout, emergency stop latch, then the latest commands."""
        fl = self.sim.forklift
        with self._lock:
            cmd = self._cmd
        timed_out = now - cmd.received_s >= self.config.command_timeout_s
        if timed_out and not self.timeout_brake and abs(self.sim.speed) > 1e-3:
            self.stats_.timeout_brakes.append(time.time())
        self.timeout_brake = timed_out
        if self._estop_request:
            self._estop_request = False
            if not self.estop_latched:
                self.stats_.emergency_stops += 1
            self.estop_latched = True
        if self.estop_latched and timed_out and abs(self.sim.speed) < 1e-3:
            self.estop_latched = False  # the run ended and the truck stands: the PLC is reset
        fl.emergency = self.estop_latched or self.timeout_brake
        if not fl.emergency:
            self.sim.drive(cmd.speed, cmd.steering)
        else:
            fl.speed_cmd = 0.0
        if self._fork_target is not None:
            self.sim.set_fork_height(self._fork_target)
        field_case, self._field_set = self._field_set, None
        if field_case is not None:
            name, _, direction = field_case.partition("/")  # `SET/DIRECTION`, or a bare `SET` (forward)
            if name in FIELD_SETS and direction in ("", *TRAVEL_DIRECTIONS):
                self.sim.set_safety_field_set(name, direction or "forward")

    def _header(self, frame: str, t: float) -> msgs.Header:
        return msgs.Header(stamp=msgs.stamp(t), frame_id=frame)

    def _publish_state(self) -> None:
        sim, c = self.sim, self.config
        f, j = c.frames, c.joints
        t = time.time()
        T_map_base = sim.localization() @ self.T_base_link_forklift.inv()
        q = msgs.quaternion_from_yaw(T_map_base.yaw)
        if c.localization.source == "tf":
            tf = msgs.TransformStamped(
                self._header(f.map, t), f.base_link, msgs.Transform(msgs.Vector3(T_map_base.x, T_map_base.y, 0.0), q)
            )
            self._publish("localization", msgs.TFMessage([tf]))
        else:
            pose = msgs.PoseWithCovariance(msgs.Pose(msgs.Point(T_map_base.x, T_map_base.y, 0.0), q))
            self._publish("localization", msgs.PoseWithCovarianceStamped(self._header(f.map, t), pose))
        v = sim.speed
        omega = v * math.tan(sim.steering) / sim.vehicle.wheelbase
        off = self.T_base_link_forklift
        vx = math.cos(off.yaw) * v + omega * off.y  # base_link origin's velocity, base_link axes
        vy = math.sin(off.yaw) * v - omega * off.x
        odom = msgs.Odometry(
            self._header(f.odom or f.map, t),
            f.base_link,
            msgs.PoseWithCovariance(msgs.Pose(msgs.Point(T_map_base.x, T_map_base.y, 0.0), q)),
            msgs.TwistWithCovariance(msgs.Twist(msgs.Vector3(vx, vy, 0.0), msgs.Vector3(0.0, 0.0, omega))),
        )
        self._publish("odometry", odom)
        self._publish(
            "joint_states",
            msgs.JointState(
                self._header(f.base_link, t),
                [j.steering, j.fork],
                [j.steering_sign * sim.steering, sim.fork_height - j.fork_offset_m],
                [],
                [],
            ),
        )
        left, right = sim.proximity_ranges()
        self.last_ranges = (left, right)
        for key, value in (("beam_left", left), ("beam_right", right)):
            beam = self._range_type(
                header=self._header(f.base_link, t),
                radiation_type=msgs.Range.INFRARED,
                field_of_view=0.02,
                min_range=0.0,
                max_range=BEAM_MAX_RANGE_M,
                range=value,
            )
            self._publish(key, beam)
        self._publish("load", msgs.Bool(sim.load_detected()))
        self._publish("diagnostics", msgs.DiagnosticArray(self._header("", t), [self._safety_status()]))

    def _safety_status(self) -> msgs.DiagnosticStatus:
        sim = self.sim
        s = sim.safety_state()
        faults = sim.faults()
        values = {
            "estop": str(self.estop_latched).lower(),
            "protective_field": str(s.protective_stop).lower(),
            "warning_field": str(s.warning).lower(),
            "field_set": s.field_set,
            "direction": s.direction,
            "intrusions": ",".join(s.intrusions),
            "command_timeout": str(self.timeout_brake).lower(),
        }
        if s.speed_limit is not None:
            values["speed_limit"] = f"{s.speed_limit:.3f}"
        if faults or self.estop_latched:
            level = msgs.DiagnosticStatus.ERROR
            message = "; ".join(faults) or "emergency stop latched"
        elif s.protective_stop or s.warning:
            level, message = msgs.DiagnosticStatus.WARN, "protective stop" if s.protective_stop else "warning field"
        else:
            level, message = msgs.DiagnosticStatus.OK, "ok"
        return msgs.DiagnosticStatus(
            level=level,
            name=self.config.safety.status,
            message=message,
            hardware_id="palletpilot-sim",
            values=[msgs.KeyValue(k, v) for k, v in values.items()],
        )

    def _request_frame(self) -> None:
        """Hand the truck's state now to the camera child (a few hundred bytes; it renders and publishes)."""
        assert self.camera is not None
        state = camera_state(self.sim)
        self._frame_stamp_s = state.stamp_s
        self.camera.request(state)

    def _take_frames(self) -> None:
        """Collect the camera child's replies: count frames, publish those handed back, tell a failure once."""
        if self.camera is None:
            return
        for frame in self.camera.poll():
            for topic, msg, qos in camera_messages(frame, self.config, self._frame_stamp_s):
                self.transport.publish(topic, msg, qos)
        self.stats_.frames = self.camera.frames
        if self.camera.error is not None and not self._camera_error_told:
            self._camera_error_told = True
            print(f"sim serve: no more camera frames: {self.camera.error}", file=sys.stderr, flush=True)

    def stats(self) -> dict[str, Any]:
        """Ticks, commands, command latency (ms) and its split (Cyclone DDS only: the drive command's header
        stamp to the sender's DDS write, the sender's process; that write to the receipt here, the transport
        and this process), timeout brakes and emergency stops, camera frames and their render time in the
        child (ms), the camera child's failure (one line) or None."""
        s = self.stats_
        with self._lock:
            latency, sender, transit = list(s.latency_ms), list(s.sender_ms), list(s.transit_ms)
        return {
            "ticks": s.ticks,
            "commands": s.commands,
            "command_latency_ms": _pct(latency),
            "command_latency_split_ms": {"stamp_to_dds_write": _pct(sender), "dds_write_to_receipt": _pct(transit)},
            "timeout_brakes": len(s.timeout_brakes),
            "emergency_stops": s.emergency_stops,
            "frames": s.frames,
            "frame_render_ms": _pct(list(self.camera.render_ms) if self.camera is not None else []),
            "camera_error": self.camera.error if self.camera is not None else None,
        }

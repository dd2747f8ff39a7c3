"""`RosVehicle`: the executor's `VehiclePort` for a real truck, on ROS 2 topics through a `Transport`.

Inputs (the robot file names every topic; `executor.ros.config`): localization from tf (`map ->
base_link`, or `map -> odom -> base_link`) or a `PoseWithCovarianceStamped`; speed from
`nav_msgs/Odometry` (`twist.twist.linear.x` of `base_link`, m/s); steering angle and fork height from
`sensor_msgs/JointState`; the fork-tip beams from two `sensor_msgs/Range`; the load sensor from a
`std_msgs/Bool`; the safety state and faults from `diagnostic_msgs/DiagnosticArray` (the key / value
convention is in `executor.ros.config`). The adapter keeps the latest reading of every topic with its
receive time; `localization_stamp()` is that time on the runner's clock (`now`, bound once the clock
exists), which the runner's localization watchdog checks.

Outputs: `ackermann_msgs/AckermannDriveStamped` on the drive topic at the control rate (`tick()` runs
after each clock tick and re-sends the current command; `drive` and `stop` also send at once):
`drive.speed` (m/s, negative in reverse), `drive.steering_angle` (rad: the executor's steering, whose
tangent over the wheelbase is the curvature, positive left), `acceleration` the vehicle file's limit
(m/s^2, `max_accel` driving, `max_decel` for `stop`; 0 for `emergency_stop`: "as fast as possible" in
ackermann_msgs), `steering_angle_velocity` its steering rate. The fork height target (m) on a
`std_msgs/Float64`; the scanners' field set on a `std_msgs/String`; `emergency_stop()` latches and
sends `std_msgs/Bool` true on the emergency stop topic every tick (never false: the safety PLC resets).
A process that dies sends nothing more: the truck controller's command timeout brakes the truck.

Stale inputs: `faults()` (called every tick by the runner) raises `TaskFailed(sensor_timeout)` naming
the topic when one is older than its `timeout_s`; readings themselves never raise, so the runner's
fail-safe stop always works. `problems()` lists what keeps a run from starting (silent topics, no tf,
an active fault); `wait_ready(timeout_s)` waits for them to clear.

Frames: `localization()` is `T_world_forklift = T_map_base_link @ T_base_link_forklift` (world = the
robot file's `map` frame; `frames.base_link_to_forklift`).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

from palletpilot.control.safety import FIELD_SETS, TRAVEL_DIRECTIONS, SafetyState
from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.adapters.ros import messages as msgs
from palletpilot.executor.adapters.ros.config import RobotConfig, TopicSpec
from palletpilot.executor.adapters.ros.transport import Subscription, Transport
from palletpilot.executor.core.errors import SENSOR_TIMEOUT, TaskFailed
from palletpilot.geometry import SE2

_TRUE = {"true", "1", "yes", "on"}


def _flag(value: str | None) -> bool:
    return value is not None and value.strip().lower() in _TRUE


def _se2(translation: msgs.Vector3 | msgs.Point, rotation: msgs.Quaternion) -> SE2:
    return SE2(translation.x, translation.y, msgs.yaw_from_quaternion(rotation))


def _frame(name: str) -> str:
    return name.lstrip("/")


class RosVehicle:
    """`VehiclePort` on ROS 2 topics (module docstring)."""

    def __init__(
        self,
        transport: Transport,
        config: RobotConfig,
        params: VehicleParams,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        self.transport = transport
        self.config = config
        self.params = params
        self.now = now  # the runner's clock (s); `time.monotonic` until the clock exists
        t = config.topics
        x, y, yaw_deg = config.frames.base_link_to_forklift
        self.T_base_link_forklift = SE2(x, y, math.radians(yaw_deg))
        self._tf: dict[tuple[str, str], tuple[SE2, float]] = {}
        self._joints: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()
        loc = config.localization
        self._pose: Subscription[msgs.PoseWithCovarianceStamped] | None = None
        self._tf_sub: Subscription[msgs.TFMessage] | None = None
        if loc.source == "tf":
            self._tf_sub = transport.subscribe(loc.tf.name, msgs.TFMessage, loc.tf.qos.spec(), self._on_tf)
        else:
            self._pose = transport.subscribe(loc.pose.name, msgs.PoseWithCovarianceStamped, loc.pose.qos.spec())
        self._odom = transport.subscribe(t.odometry.name, msgs.Odometry, t.odometry.qos.spec())
        self._joint_sub = transport.subscribe(
            t.joint_states.name, msgs.JointState, t.joint_states.qos.spec(), self._on_joints
        )
        range_type = msgs.range_type(config.ros_distro)
        self._beams = (
            transport.subscribe(t.beam_left.name, range_type, t.beam_left.qos.spec()),
            transport.subscribe(t.beam_right.name, range_type, t.beam_right.qos.spec()),
        )
        self._load = transport.subscribe(t.load.name, msgs.Bool, t.load.qos.spec())
        self._diag: dict[str, tuple[msgs.DiagnosticStatus, float]] = {}
        self._diag_sub = transport.subscribe(
            t.diagnostics.name, msgs.DiagnosticArray, t.diagnostics.qos.spec(), self._on_diagnostics
        )
        for spec, kind in (
            (t.drive, msgs.AckermannDriveStamped),
            (t.fork_height, msgs.Float64),
            (t.emergency_stop, msgs.Bool),
            (t.field_set, msgs.String),
        ):
            transport.advertise(spec.name, kind, spec.qos.spec())
        self._speed_cmd = 0.0
        self._steering_cmd = 0.0
        self._accel_cmd = 0.0
        self._fork_target: float | None = None
        self._field_set = "normal"
        self.emergency = False
        self._sent_this_tick = False
        self.commands_sent = 0
        self.localization_age_s: list[float] = []

    # -- receiving --------------------------------------------------------------------------------
    def _on_tf(self, msg: msgs.TFMessage, received_s: float) -> None:
        f = self.config.frames
        wanted = {(f.map, f.base_link), (f.map, f.odom), (f.odom, f.base_link)}
        with self._lock:
            for tf in msg.transforms:
                key = (_frame(tf.header.frame_id), _frame(tf.child_frame_id))
                if key in wanted:
                    self._tf[key] = (_se2(tf.transform.translation, tf.transform.rotation), received_s)

    def _on_joints(self, msg: msgs.JointState, received_s: float) -> None:
        with self._lock:
            for name, position in zip(msg.name, msg.position, strict=False):
                self._joints[name] = (float(position), received_s)

    def _on_diagnostics(self, msg: msgs.DiagnosticArray, received_s: float) -> None:
        with self._lock:
            for status in msg.status:
                self._diag[status.name] = (status, received_s)

    def _runner_time(self, received_s: float) -> float:
        """A receive time (`time.monotonic()`) on the runner's clock."""
        return self.now() - (time.monotonic() - received_s)

    def _fix(self) -> tuple[SE2, float] | None:
        """`T_map_base_link` and when it arrived (monotonic s), or None."""
        if self._pose is not None:
            got = self._pose.latest()
            if got is None:
                return None
            p = got.msg.pose.pose
            return _se2(p.position, p.orientation), got.received_s
        f = self.config.frames
        with self._lock:
            direct = self._tf.get((f.map, f.base_link))
            if direct is not None:
                return direct
            if f.odom is None:
                return None
            a, b = self._tf.get((f.map, f.odom)), self._tf.get((f.odom, f.base_link))
        if a is None or b is None:
            return None
        return a[0] @ b[0], min(a[1], b[1])

    # -- VehiclePort: readings ----------------------------------------------------------------------
    def localization(self) -> SE2:
        """`T_world_forklift` (world = the `map` frame): the last fix; the origin before the first.
        The fix's age at this read goes to `localization_age_s` (the report's `localization_age_ms`)."""
        fix = self._fix()
        if fix is not None and len(self.localization_age_s) < 1_000_000:
            self.localization_age_s.append(time.monotonic() - fix[1])
        return (fix[0] if fix is not None else SE2()) @ self.T_base_link_forklift

    def localization_stamp(self) -> float:
        """When the last fix arrived, on the runner's clock (s); `-inf` before the first."""
        fix = self._fix()
        return -math.inf if fix is None else self._runner_time(fix[1])

    @property
    def speed(self) -> float:
        """Measured speed of the forklift origin along its x axis (m/s) from odometry; 0 before the first."""
        got = self._odom.latest()
        if got is None:
            return 0.0
        tw = got.msg.twist.twist
        off = self.T_base_link_forklift
        vx = tw.linear.x - tw.angular.z * off.y  # velocity of the forklift origin, base_link axes
        vy = tw.linear.y + tw.angular.z * off.x
        return math.cos(off.yaw) * vx + math.sin(off.yaw) * vy

    def _joint(self, name: str) -> float | None:
        with self._lock:
            got = self._joints.get(name)
        return None if got is None else got[0]

    @property
    def steering(self) -> float:
        """Measured steering angle (rad, the executor's convention) from the steering joint."""
        j = self.config.joints
        value = self._joint(j.steering)
        return 0.0 if value is None else j.steering_sign * value

    @property
    def fork_height(self) -> float:
        """Measured fork height (m, fork bottoms above the floor) from the lift joint."""
        j = self.config.joints
        value = self._joint(j.fork)
        return 0.0 if value is None else value + j.fork_offset_m

    def proximity_ranges(self) -> tuple[float, float]:
        """(left, right) fork-tip beam ranges (m): +inf nothing within range; NaN, -inf or no reading 0 (fail safe)."""
        out = []
        for sub in self._beams:
            got = sub.latest()
            if got is None:
                out.append(0.0)
                continue
            r = got.msg
            value = float(r.range)
            if math.isnan(value) or value == -math.inf:
                out.append(0.0)
            elif value == math.inf or (r.max_range > 0 and value > r.max_range):
                out.append(math.inf)
            else:
                out.append(max(value, 0.0))
        return out[0], out[1]

    def load_detected(self) -> bool:
        """The load sensor (False before the first message)."""
        got = self._load.latest()
        return bool(got is not None and got.msg.data)

    def _safety(self) -> tuple[msgs.DiagnosticStatus | None, dict[str, str]]:
        with self._lock:
            got = self._diag.get(self.config.safety.status)
        if got is None:
            return None, {}
        return got[0], {kv.key: kv.value for kv in got[0].values}

    def safety_state(self) -> SafetyState:
        """The safety PLC's state from the diagnostics (`executor.ros.config` has the keys)."""
        _status, kv = self._safety()
        warning = _flag(kv.get("warning_field"))
        limit: float | None = None
        if warning:
            scanner = self.params.safety_scanner
            limit = scanner.warning_speed if scanner is not None else 0.3
            try:
                limit = float(kv["speed_limit"]) if "speed_limit" in kv else limit
            except ValueError:
                pass  # an unreadable cap: the vehicle's own
        field_set = kv.get("field_set", self._field_set)
        direction = kv.get("direction", "reverse" if self.speed < 0 else "forward")
        intrusions = tuple(s.strip() for s in kv.get("intrusions", "").split(",") if s.strip())
        return SafetyState(
            field_set="narrow" if field_set == "narrow" else "normal",
            direction="reverse" if direction == "reverse" else "forward",
            warning=warning,
            protective_stop=_flag(kv.get("protective_field")),
            speed_limit=limit,
            intrusions=intrusions,
        )

    def active_faults(self) -> list[str]:
        """Faults from the diagnostics: the e-stop, ERROR / STALE on the safety status, ERROR on a fault status."""
        out = []
        status, kv = self._safety()
        if status is not None:
            if _flag(kv.get("estop")):
                out.append(f"emergency stop: {status.message or 'pressed'}")
            elif status.level in (msgs.DiagnosticStatus.ERROR, msgs.DiagnosticStatus.STALE):
                out.append(f"{status.name}: {status.message or 'error'}")
        with self._lock:
            statuses = [self._diag[n][0] for n in self.config.safety.fault_statuses if n in self._diag]
        out += [f"{s.name}: {s.message or 'error'}" for s in statuses if s.level == msgs.DiagnosticStatus.ERROR]
        return out

    def silent_inputs(self) -> list[str]:
        """Input topics older than their timeout (`topics.X: /name: ...`), or never heard."""
        t, out = self.config.topics, []
        now = time.monotonic()
        subs: dict[str, tuple[TopicSpec, Subscription[Any] | None]] = {
            "odometry": (t.odometry, self._odom),
            "joint_states": (t.joint_states, self._joint_sub),
            "beam_left": (t.beam_left, self._beams[0]),
            "beam_right": (t.beam_right, self._beams[1]),
            "load": (t.load, self._load),
            "diagnostics": (t.diagnostics, self._diag_sub),
        }
        for field, (spec, sub) in subs.items():
            if sub is None or spec.timeout_s is None:
                continue
            age = sub.age(now)
            if age > spec.timeout_s:
                heard = "never heard" if math.isinf(age) else f"last message {age:.2f} s ago"
                out.append(f"topics.{field}: {spec.name}: {heard} (limit {spec.timeout_s:g} s)")
        j = self.config.joints
        for name in (j.steering, j.fork):
            with self._lock:
                got = self._joints.get(name)
            limit = t.joint_states.timeout_s
            if got is None and self._joint_sub.count > 0:
                out.append(f"joints: '{name}' is not in {t.joint_states.name} (names: {self._joint_names()})")
            elif got is not None and limit is not None and now - got[1] > limit:
                out.append(f"joints: '{name}' on {t.joint_states.name}: last position {now - got[1]:.2f} s ago")
        return out

    def _joint_names(self) -> str:
        with self._lock:
            return ", ".join(sorted(self._joints)) or "none"

    def localization_problem(self) -> str | None:
        """Why there is no usable fix (no tf, a stale one), or None."""
        loc, f = self.config.localization, self.config.frames
        fix = self._fix()
        if fix is None:
            if loc.source == "pose":
                return f"localization.pose: {loc.pose.name}: never heard"
            with self._lock:
                have = ", ".join(f"{a} -> {b}" for a, b in sorted(self._tf)) or "none"
            via = f" or {f.map} -> {f.odom} -> {f.base_link}" if f.odom else ""
            return f"localization.tf: {loc.tf.name}: no transform {f.map} -> {f.base_link}{via} (have: {have})"
        age = time.monotonic() - fix[1]
        if age > loc.timeout_s:
            return f"localization: the last fix is {age:.2f} s old (limit {loc.timeout_s:g} s)"
        return None

    def problems(self) -> list[str]:
        """What keeps a run from starting: no usable localization, silent inputs, active faults."""
        out = [p for p in [self.localization_problem()] if p is not None]
        out += self.silent_inputs()
        out += [f"safety: {fault}" for fault in self.active_faults()]
        return out

    def wait_ready(self, timeout_s: float, poll_s: float = 0.05) -> list[str]:
        """Wait up to `timeout_s` for `problems()` to clear; returns what is left ([] when ready)."""
        t_end = time.monotonic() + timeout_s
        while True:
            problems = self.problems()
            if not problems or time.monotonic() >= t_end:
                return problems
            time.sleep(poll_s)

    def faults(self) -> list[str]:
        """Active faults (`active_faults`); raises `TaskFailed(sensor_timeout)` when an input went silent."""
        silent = self.silent_inputs()
        if silent:
            raise TaskFailed(SENSOR_TIMEOUT, "input silent: " + "; ".join(silent))
        return self.active_faults()

    # -- VehiclePort: commands ----------------------------------------------------------------------
    def _send_drive(self) -> None:
        p = self.params
        cmd = msgs.AckermannDriveStamped(
            header=msgs.Header(stamp=msgs.stamp(time.time()), frame_id=self.config.frames.base_link),
            drive=msgs.AckermannDrive(
                steering_angle=self._steering_cmd,
                steering_angle_velocity=math.radians(p.max_steering_rate_deg_s),
                speed=self._speed_cmd,
                acceleration=self._accel_cmd,
            ),
        )
        spec = self.config.topics.drive
        self.transport.publish(spec.name, cmd, spec.qos.spec())
        self._sent_this_tick = True
        self.commands_sent += 1

    def drive(self, speed: float, steering: float) -> None:
        """Drive command: speed (m/s, negative in reverse), steering angle (rad); ignored after `emergency_stop`."""
        if self.emergency:
            return
        self._speed_cmd, self._steering_cmd, self._accel_cmd = float(speed), float(steering), self.params.max_accel
        self._send_drive()

    def stop(self) -> None:
        """Zero speed at the service deceleration (`max_decel`); the steering is held."""
        self._speed_cmd = 0.0
        if not self.emergency:
            self._accel_cmd = self.params.max_decel
        self._send_drive()

    def emergency_stop(self) -> None:
        """Latch the safety stop: zero speed "as fast as possible", and the emergency stop topic true."""
        self.emergency = True
        self._speed_cmd, self._accel_cmd = 0.0, 0.0
        self._send_drive()
        self._send_estop()

    def _send_estop(self) -> None:
        spec = self.config.topics.emergency_stop
        self.transport.publish(spec.name, msgs.Bool(data=True), spec.qos.spec())

    def set_fork_height(self, height: float) -> None:
        """Fork height target (m, fork bottoms above the floor), sent at once and every tick."""
        self._fork_target = float(height)
        self._send_fork()

    def _send_fork(self) -> None:
        if self._fork_target is None:
            return
        spec = self.config.topics.fork_height
        self.transport.publish(spec.name, msgs.Float64(data=self._fork_target), spec.qos.spec())

    def set_safety_field_set(self, name: str, direction: str = "forward") -> None:
        """Select the scanners' field case, sent on the field set topic as `SET/DIRECTION` (one message, so
        the truck never switches to the set with the other direction): `normal` or `narrow`, and the
        direction of travel it is about to drive, `forward` or `reverse`."""
        if name not in FIELD_SETS:
            raise ValueError(f"unknown safety field set '{name}' (one of {', '.join(FIELD_SETS)})")
        if direction not in TRAVEL_DIRECTIONS:
            raise ValueError(f"unknown direction of travel '{direction}' (one of {', '.join(TRAVEL_DIRECTIONS)})")
        self._field_set = name
        spec = self.config.topics.field_set
        self.transport.publish(spec.name, msgs.String(data=f"{name}/{direction}"), spec.qos.spec())

    def tick(self, dt: float = 0.0) -> None:
        """After each clock tick: re-send the drive command (unless sent this tick), the fork target, the e-stop."""
        if not self._sent_this_tick:
            self._send_drive()
        self._sent_this_tick = False
        self._send_fork()
        if self.emergency:
            self._send_estop()

    def close(self) -> None:
        """Stop sending (the truck's command timeout brakes it if it still moves)."""
        self.emergency = True

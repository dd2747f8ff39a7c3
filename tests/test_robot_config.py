"""The robot file, the ROS 2 vehicle adapter and the camera source, on an in-process transport (no DDS):
what each topic means to the executor, what a silent topic or a fault does, what goes out on the drive
topic, and the refusals of `palletpilot robot` before anything moves."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

from palletpilot.control.vehicle import load_vehicle
from palletpilot.executor.adapters.ros import messages as m
from palletpilot.executor.adapters.ros.camera import (
    RosCamera,
    camera_info,
    depth_image,
    image_to_depth,
    image_to_rgb,
    rgb_image,
)
from palletpilot.executor.adapters.ros.config import RobotConfig, RobotConfigError, load_robot
from palletpilot.executor.adapters.ros.transport import MemoryTransport
from palletpilot.executor.adapters.ros.vehicle import RosVehicle
from palletpilot.executor.apps.cli import main
from palletpilot.executor.apps.cli_robot import static_tf_text
from palletpilot.executor.apps.robot import RobotError, calibration_problem, load_inputs, start_node
from palletpilot.executor.core.errors import SENSOR_TIMEOUT, TaskFailed
from palletpilot.executor.ports import VehiclePort
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration_io import Calibration, save_calibration
from palletpilot.perception.errors import PerceptionError
from palletpilot.roadmap import load_map

EXAMPLE = bundled_path("missions", "robot.yaml")
VEHICLE = load_vehicle(bundled_path("missions", "forklift.yaml"))


def _config(**overrides: object) -> RobotConfig:
    doc = {"name": "test", **overrides}
    return RobotConfig.model_validate(doc)


def _header(frame: str = "") -> m.Header:
    return m.Header(stamp=m.stamp(time.time()), frame_id=frame)


def _tf(parent: str, child: str, x: float, y: float, yaw: float) -> m.TransformStamped:
    return m.TransformStamped(_header(parent), child, m.Transform(m.Vector3(x, y, 0.0), m.quaternion_from_yaw(yaw)))


def _safety(level: int = 0, message: str = "ok", **values: str) -> m.DiagnosticArray:
    kv = [m.KeyValue(k, v) for k, v in values.items()]
    return m.DiagnosticArray(_header(), [m.DiagnosticStatus(level=level, name="safety", message=message, values=kv)])


def _feed(bus: MemoryTransport, config: RobotConfig, speed: float = 0.0, with_tf: bool = True) -> None:
    """One round of every input the adapter needs, as a healthy truck sends it."""
    t = config.topics
    if with_tf:
        bus.publish("/tf", m.TFMessage([_tf("map", "odom", 1.0, 2.0, 0.0), _tf("odom", "base_link", 3.0, 0.0, 0.5)]))
    odom = m.Odometry(_header("odom"), "base_link")
    odom.twist.twist.linear.x = speed
    bus.publish(t.odometry.name, odom)
    bus.publish(t.joint_states.name, m.JointState(_header(), ["steering_joint", "fork_lift_joint"], [0.2, 0.4]))
    for name, r in ((t.beam_left.name, 1.5), (t.beam_right.name, math.inf)):
        bus.publish(name, m.Range(_header(), max_range=4.0, range=r))
    bus.publish(t.load.name, m.Bool(True))
    bus.publish(t.diagnostics.name, _safety())


@pytest.fixture()
def truck() -> tuple[MemoryTransport, RosVehicle, RobotConfig]:
    config = _config()
    bus = MemoryTransport()
    return bus, RosVehicle(bus, config, VEHICLE), config


# -- the robot file ----------------------------------------------------------------------------------------
def test_example_robot_file_is_the_defaults() -> None:
    config = load_robot(EXAMPLE)
    defaults = RobotConfig()
    assert config.model_dump(exclude={"name"}) == defaults.model_dump(exclude={"name"})
    assert config.frames.camera == "camera_color_optical_frame" and config.rates.control_hz == 20
    assert config.path(config.forks).is_file()
    assert config.command_timeout_s == 0.2


def test_bad_robot_file_one_line_per_problem(tmp_path: Path) -> None:
    bad = tmp_path / "robot.yaml"
    bad.write_text(
        "rates: {control_hz: 1}\n"
        "localization: {source: gps}\n"
        "topics:\n  odometry: '/od om'\n  load: {name: /x, qos: {depth: 0}}\n  drive: /x\n  speed: /y\n"
        "camera: {source: kinect}\n"
    )
    with pytest.raises(RobotConfigError) as err:
        load_robot(bad)
    lines = err.value.problems
    assert all(line.startswith(f"{bad}: ") for line in lines)
    text = "\n".join(lines)
    for field in ("rates.control_hz", "localization.source", "topics.odometry.name", "topics.load.qos.depth"):
        assert field in text
    assert "topics.speed: Extra inputs are not permitted" in text
    assert "camera.source" in text
    assert len(lines) == 6  # (the /x twice is checked once the fields are valid)


def test_a_topic_carries_one_thing(tmp_path: Path) -> None:
    bad = tmp_path / "robot.yaml"
    bad.write_text("topics: {load: /forks/load, drive: /forks/load}\n")
    with pytest.raises(RobotConfigError, match=r"topics\.drive and topics\.load are both '/forks/load'"):
        load_robot(bad)


def test_robot_command_refuses_a_bad_robot_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "robot.yaml"
    bad.write_text("rates: {control_hz: 1000}\nforks: missing.yaml\n")
    mission = bundled_path("missions", "pickup_delivery.yaml")
    assert main(["robot", str(mission), "--robot", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert any("rates.control_hz" in line for line in err)
    assert all("Traceback" not in line for line in err)


def test_stale_calibration_is_refused(tmp_path: Path) -> None:
    cal = tmp_path / "cal.json"
    save_calibration(cal, Calibration(SE3.from_xyz_rpy((-0.1, 0.0, 0.45), np.radians([-112.0, 0.0, -90.0])), "model"))
    assert calibration_problem(cal, 30.0) is None
    old = time.time() - 40 * 86400
    os.utime(cal, (old, old))
    line = calibration_problem(cal, 30.0)
    assert line is not None and "stale: 40.0 days old (limit 30 days" in line
    robot = tmp_path / "robot.yaml"
    robot.write_text(f"forks: {bundled_path('missions', 'forks.yaml')}\n")
    with pytest.raises(RobotError, match="stale"):
        load_inputs(bundled_path("missions", "pickup_delivery.yaml"), robot, cal)


def test_start_node_within_tolerance() -> None:
    roadmap = load_map(bundled_path("missions", "warehouse.yaml"))
    charger = roadmap.node("charger").pose
    assert start_node(roadmap, SE2(charger.x + 0.1, charger.y, charger.yaw + 0.05)) == "charger"
    with pytest.raises(RobotError, match="from node 'charger'"):
        start_node(roadmap, SE2(charger.x + 0.5, charger.y, charger.yaw))
    with pytest.raises(RobotError, match="unknown node"):
        start_node(roadmap, charger, "nowhere")


# -- readings ------------------------------------------------------------------------------------------------
def test_vehicle_is_a_vehicle_port(truck: tuple[MemoryTransport, RosVehicle, RobotConfig]) -> None:
    _bus, vehicle, _config = truck
    assert isinstance(vehicle, VehiclePort)


def test_readings_from_the_topics(truck: tuple[MemoryTransport, RosVehicle, RobotConfig]) -> None:
    bus, vehicle, config = truck
    assert vehicle.problems()  # nothing heard yet
    _feed(bus, config, speed=0.8)
    assert vehicle.problems() == []
    pose = vehicle.localization()  # map -> odom (1, 2, 0) then odom -> base_link (3, 0, 0.5)
    assert (pose.x, pose.y, pose.yaw) == pytest.approx((4.0, 2.0, 0.5))
    assert vehicle.localization_stamp() == pytest.approx(time.monotonic(), abs=0.05)
    assert vehicle.speed == pytest.approx(0.8)
    assert vehicle.steering == pytest.approx(0.2) and vehicle.fork_height == pytest.approx(0.4)
    assert vehicle.proximity_ranges() == (1.5, math.inf)
    assert vehicle.load_detected() is True
    assert vehicle.faults() == [] and not vehicle.safety_state().protective_stop


def test_frames_signs_and_offsets() -> None:
    config = _config(
        frames={"odom": None, "base_link_to_forklift": (1.0, 0.0, 180.0)},
        joints={"steering_sign": -1, "fork_offset_m": 0.05},
        localization={"source": "pose", "pose": "/pose"},
    )
    bus = MemoryTransport()
    vehicle = RosVehicle(bus, config, VEHICLE)
    assert "localization.pose: /pose: never heard" in vehicle.problems()
    pose = m.PoseWithCovariance(m.Pose(m.Point(2.0, 0.0, 0.0), m.quaternion_from_yaw(0.0)))
    bus.publish("/pose", m.PoseWithCovarianceStamped(_header("map"), pose))
    _feed(bus, config, speed=0.5, with_tf=False)
    fix = vehicle.localization()  # the forklift frame 1 m ahead of base_link, turned around
    assert (fix.x, fix.y, abs(fix.yaw)) == pytest.approx((3.0, 0.0, math.pi))
    assert vehicle.speed == pytest.approx(-0.5)  # base_link forward is the forklift's reverse
    assert vehicle.steering == pytest.approx(-0.2)
    assert vehicle.fork_height == pytest.approx(0.45)


def test_beam_readings_fail_safe(truck: tuple[MemoryTransport, RosVehicle, RobotConfig]) -> None:
    bus, vehicle, config = truck
    for r, expected in ((math.nan, 0.0), (-math.inf, 0.0), (5.0, math.inf), (0.3, 0.3)):
        bus.publish(config.topics.beam_left.name, m.Range(_header(), max_range=4.0, range=r))
        assert vehicle.proximity_ranges()[0] == expected


def test_tf_missing_is_named(truck: tuple[MemoryTransport, RosVehicle, RobotConfig]) -> None:
    bus, vehicle, config = truck
    _feed(bus, config, with_tf=False)
    bus.publish("/tf", m.TFMessage([_tf("odom", "base_link", 0, 0, 0)]))
    (line,) = vehicle.problems()
    assert "localization.tf: /tf: no transform map -> base_link or map -> odom -> base_link" in line
    assert "(have: odom -> base_link)" in line


def test_safety_state_and_faults(truck: tuple[MemoryTransport, RosVehicle, RobotConfig]) -> None:
    bus, vehicle, config = truck
    _feed(bus, config)
    diag = config.topics.diagnostics.name
    bus.publish(
        diag,
        _safety(
            1,
            "warning",
            warning_field="true",
            protective_field="false",
            field_set="narrow",
            intrusions="person, box",
        ),
    )
    s = vehicle.safety_state()
    assert s.warning and s.speed_limit == pytest.approx(0.3) and s.field_set == "narrow"
    assert s.intrusions == ("person", "box") and vehicle.faults() == []
    bus.publish(diag, _safety(1, "stop", protective_field="true", speed_limit="0.1", warning_field="true"))
    assert vehicle.safety_state().protective_stop and vehicle.safety_state().speed_limit == pytest.approx(0.1)
    bus.publish(diag, _safety(2, "contact on the bumper"))
    assert vehicle.faults() == ["safety: contact on the bumper"]
    bus.publish(diag, _safety(2, "pressed", estop="true"))
    assert vehicle.faults() == ["emergency stop: pressed"]
    assert vehicle.problems() == ["safety: emergency stop: pressed"]


def test_silent_input_stops_with_sensor_timeout(truck: tuple[MemoryTransport, RosVehicle, RobotConfig]) -> None:
    bus, vehicle, config = truck
    _feed(bus, config)
    got = vehicle._odom.latest()
    assert got is not None
    vehicle._odom._latest = type(got)(got.msg, got.received_s - 1.0)  # odometry 1 s old (limit 0.3 s)
    with pytest.raises(TaskFailed) as err:
        vehicle.faults()
    assert err.value.reason == SENSOR_TIMEOUT
    assert "topics.odometry: /odom: last message 1.0" in str(err.value)
    assert vehicle.speed == 0.0  # readings never raise: the fail-safe stop always works


# -- commands ----------------------------------------------------------------------------------------------
def test_drive_commands_at_the_control_rate(truck: tuple[MemoryTransport, RosVehicle, RobotConfig]) -> None:
    bus, vehicle, config = truck
    drive = config.topics.drive.name
    vehicle.drive(0.7, -0.1)
    (cmd,) = bus.sent(drive)
    assert isinstance(cmd, m.AckermannDriveStamped) and cmd.header.frame_id == "base_link"
    assert (cmd.drive.speed, cmd.drive.steering_angle) == pytest.approx((0.7, -0.1))
    assert cmd.drive.acceleration == pytest.approx(VEHICLE.max_accel)
    vehicle.tick()  # sent this tick already: no second message
    assert len(bus.sent(drive)) == 1
    vehicle.tick()  # a tick without a command: the last one again, so the truck's timeout never fires
    assert len(bus.sent(drive)) == 2 and bus.sent(drive)[-1].drive.speed == pytest.approx(0.7)
    vehicle.stop()
    assert bus.sent(drive)[-1].drive.speed == 0.0
    assert bus.sent(drive)[-1].drive.acceleration == pytest.approx(VEHICLE.max_decel)
    vehicle.set_fork_height(1.1)
    assert bus.sent(config.topics.fork_height.name)[-1].data == pytest.approx(1.1)
    vehicle.set_safety_field_set("narrow")
    assert bus.sent(config.topics.field_set.name)[-1].data == "narrow/forward"
    vehicle.set_safety_field_set("normal", "reverse")  # one message: the set and the direction together
    assert bus.sent(config.topics.field_set.name)[-1].data == "normal/reverse"
    with pytest.raises(ValueError):
        vehicle.set_safety_field_set("wide")
    with pytest.raises(ValueError):
        vehicle.set_safety_field_set("normal", "sideways")


def test_emergency_stop_latches(truck: tuple[MemoryTransport, RosVehicle, RobotConfig]) -> None:
    bus, vehicle, config = truck
    vehicle.drive(1.0, 0.0)
    vehicle.emergency_stop()
    last = bus.sent(config.topics.drive.name)[-1].drive
    assert (last.speed, last.acceleration) == (0.0, 0.0)  # ackermann_msgs: 0 = as fast as possible
    assert [b.data for b in bus.sent(config.topics.emergency_stop.name)] == [True]
    vehicle.drive(1.0, 0.0)  # ignored
    vehicle.tick()
    assert bus.sent(config.topics.drive.name)[-1].drive.speed == 0.0
    assert len(bus.sent(config.topics.emergency_stop.name)) == 2  # repeated every tick while latched


# -- camera --------------------------------------------------------------------------------------------------
def test_image_conversions() -> None:
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    img = rgb_image(rgb, _header())
    assert np.array_equal(image_to_rgb(img), rgb)
    padded = b"".join(rgb[i, :, ::-1].tobytes() + b"\0" for i in range(2))  # rows of 10 bytes, 9 used
    bgr = m.Image(_header(), 2, 3, "bgr8", 0, 10, padded)
    assert np.array_equal(image_to_rgb(bgr), rgb)
    depth = np.array([[0.5, np.nan], [1.234, 0.0]], dtype=np.float32)
    back = image_to_depth(depth_image(depth, _header()))
    assert back.dtype == np.float32 and np.allclose(back, [[0.5, 0.0], [1.234, 0.0]])
    f32 = m.Image(_header(), 2, 2, "32FC1", 0, 8, depth.tobytes())
    assert np.allclose(image_to_depth(f32), [[0.5, 0.0], [1.234, 0.0]])
    with pytest.raises(PerceptionError, match="encoding 'mono8'"):
        image_to_rgb(m.Image(_header(), 1, 1, "mono8", 0, 1, b"\0"))


def test_ros_camera_pairs_colour_and_depth() -> None:
    config = _config()
    bus = MemoryTransport()
    camera = RosCamera(bus, config, fork_height=lambda: 0.25)
    with pytest.raises(PerceptionError, match="never heard"):
        camera.grab()
    h, w = 48, 64
    K = np.array([[60.0, 0, 32.0], [0, 60.0, 24.0], [0, 0, 1]])
    cam = config.camera
    stamp = _header("camera_color_optical_frame")
    bus.publish(cam.info.name, camera_info(K, w, h, stamp))
    bus.publish(cam.color.name, rgb_image(np.full((h, w, 3), 7, np.uint8), stamp))
    late = m.Header(stamp=m.stamp(m.seconds(stamp.stamp) + 0.5), frame_id=stamp.frame_id)
    bus.publish(cam.depth.name, depth_image(np.full((h, w), 2.0), late))
    assert "no colour and depth image within 0.02 s" in camera.problems()[0]
    bus.publish(cam.depth.name, depth_image(np.full((h, w), 1.5), stamp))
    frame = camera.grab()
    assert frame.depth[0, 0] == pytest.approx(1.5) and frame.rgb is not None and frame.rgb[0, 0, 0] == 7
    assert np.allclose(frame.K, K) and frame.fork_height == pytest.approx(0.25)
    assert frame.stamp_s == pytest.approx(time.monotonic(), abs=0.1)
    assert camera.grab() is frame  # the same pair: converted once


# -- calibrate --ros-static-tf ---------------------------------------------------------------------------
def test_static_tf_text() -> None:
    T = SE3.from_xyz_rpy((-0.1, 0.02, 0.45), np.radians([-112.0, 0.0, -90.0]))
    text = static_tf_text(Calibration(T, "model"))
    line = next(x for x in text.splitlines() if "static_transform_publisher" in x)
    args = line.split()
    values = {args[i][2:]: args[i + 1] for i in range(len(args)) if args[i].startswith("--")}
    assert values["frame-id"] == "base_link" and values["child-frame-id"] == "camera_color_optical_frame"
    assert [float(values[k]) for k in ("x", "y", "z")] == pytest.approx([-0.1, 0.02, 0.45])
    q = [float(values[k]) for k in ("qx", "qy", "qz", "qw")]
    assert np.allclose(np.abs(np.dot(q, T.rotation.as_quat())), 1.0)
    import yaml

    doc = yaml.safe_load(text)
    assert doc["child_frame_id"] == "camera_color_optical_frame" and doc["header"]["frame_id"] == "base_link"
    assert doc["transform"]["translation"]["z"] == pytest.approx(0.45)


def test_calibrate_takes_ros_static_tf() -> None:
    from palletpilot.executor.apps.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["calibrate", "f.npz", "--forks", "forks.yaml", "--ros-static-tf"])
    assert args.ros_static_tf == "-"
    args = parser.parse_args(["calibrate", "f.npz", "--forks", "forks.yaml", "--ros-static-tf", "cam_tf.yaml"])
    assert args.ros_static_tf == "cam_tf.yaml"


def test_realsense_camera_grabs_off_the_loop() -> None:
    from palletpilot.executor.adapters.ros.camera import RealSenseCamera
    from palletpilot.perception.frames import FrameBundle

    class FakeSource:
        closed = False

        def grab(self) -> FrameBundle:
            time.sleep(0.01)
            K = np.array([[60.0, 0, 32.0], [0, 60.0, 24.0], [0, 0, 1]])
            return FrameBundle(depth=np.ones((48, 64), np.float32), K=K, rgb=np.zeros((48, 64, 3), np.uint8))

        def close(self) -> None:
            self.closed = True

    source = FakeSource()
    camera = RealSenseCamera(fork_height=lambda: 0.3, source=source)
    t_end = time.monotonic() + 5.0
    while camera.problems() and time.monotonic() < t_end:
        time.sleep(0.01)
    frame = camera.grab()
    assert frame.fork_height == pytest.approx(0.3) and frame.stamp_s is not None
    assert time.monotonic() - frame.stamp_s < 0.5
    camera.close()
    assert source.closed


def test_calibrate_ros_static_tf_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`calibrate --ros-static-tf FILE` writes the calibration's transform; bare, it prints after the JSON."""
    import json

    import yaml

    frame, cal, tf_file = tmp_path / "frame.npz", tmp_path / "cal.json", tmp_path / "cam_tf.yaml"
    scenario = bundled_path("missions", "scenario_demo.yaml")
    assert main(["sim", "render", str(scenario), "--out", str(frame), "--seed", "1"]) == 0
    forks = str(bundled_path("missions", "forks.yaml"))
    argv = ["calibrate", str(frame), "--forks", forks, "--out", str(cal)]
    assert main([*argv, "--ros-static-tf", str(tf_file)]) == 0
    xyz = json.loads(cal.read_text())["xyz_m"]
    doc = yaml.safe_load(tf_file.read_text())
    t = doc["transform"]["translation"]
    assert [t["x"], t["y"], t["z"]] == pytest.approx(xyz, abs=1e-6)
    capsys.readouterr()
    assert main([*argv, "--json", "--ros-static-tf"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["xyz_m"] == pytest.approx(xyz)  # stdout stays JSON; the transform goes to stderr
    assert "static_transform_publisher" in err and "--child-frame-id camera_color_optical_frame" in err

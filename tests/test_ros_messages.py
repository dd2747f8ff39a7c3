"""The ROS 2 messages of the adapter: Cyclone DDS's CDR bytes equal an independent serialiser's (`rosbags`, the
ROS 2 Humble type store), field names and order match the `.msg` definitions, and the transports' small parts
(topic names, the rclpy import guard, a loopback round trip on Cyclone DDS) behave."""

from __future__ import annotations

import math
import os
import random
import time
from typing import Any

import numpy as np
import pytest

from palletpilot.executor.adapters.ros import messages as m
from palletpilot.executor.adapters.ros.transport import (
    QosSpec,
    TransportError,
    check_topic_name,
    dds_topic_name,
    rclpy_available,
)

rosbags = pytest.importorskip("rosbags.typesys")
from rosbags.interfaces import Nodetype  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

# ros-drivers/ackermann_msgs, branch ros2 (not in the Humble type store).
ACKERMANN_DRIVE = """
float32 steering_angle
float32 steering_angle_velocity
float32 speed
float32 acceleration
float32 jerk
"""
ACKERMANN_DRIVE_STAMPED = """
std_msgs/Header header
AckermannDrive  drive
"""


@pytest.fixture(scope="module")
def stores() -> dict[str, Any]:
    """The ROS 2 Humble and Jazzy type stores of rosbags, with ackermann_msgs registered."""
    out = {}
    for name, which in (("humble", Stores.ROS2_HUMBLE), ("jazzy", Stores.ROS2_JAZZY)):
        ts = get_typestore(which)
        types = get_types_from_msg(ACKERMANN_DRIVE, "ackermann_msgs/msg/AckermannDrive")
        types.update(get_types_from_msg(ACKERMANN_DRIVE_STAMPED, "ackermann_msgs/msg/AckermannDriveStamped"))
        ts.register(types)
        out[name] = ts
    return out


def _store(stores: dict[str, Any], cls: type) -> Any:
    """Jazzy's store for Jazzy's Range, Humble's for everything else (the rest is the same in both)."""
    return stores["jazzy" if cls is m.RangeWithVariance else "humble"]


_DTYPES = {
    "float64": np.float64,
    "float32": np.float32,
    "uint8": np.uint8,
    "byte": np.uint8,
    "int32": np.int32,
    "uint32": np.uint32,
}


def _to_rosbags(ts: Any, msg: Any) -> Any:
    """The same message built as a rosbags object, field by field from the type store's definitions."""
    name = m.ros_type_name(type(msg))
    _consts, fields = ts.fielddefs[name]
    kwargs = {}
    for fname, (ntype, detail) in fields:
        value = getattr(msg, fname)
        if ntype == Nodetype.NAME:
            kwargs[fname] = _to_rosbags(ts, value)
        elif ntype == Nodetype.BASE:
            kwargs[fname] = value
        else:  # array or sequence
            (sub_type, sub_detail), _n = detail
            if sub_type == Nodetype.NAME:
                kwargs[fname] = [_to_rosbags(ts, v) for v in value]
            elif sub_detail[0] == "string":
                kwargs[fname] = list(value)
            else:
                kwargs[fname] = np.array(list(value), dtype=_DTYPES[sub_detail[0]])
    return ts.types[name](**kwargs)


def _header(frame: str = "base_link") -> m.Header:
    return m.Header(stamp=m.stamp(1_700_000_123.456789), frame_id=frame)


def _covariance(seed: int) -> list[float]:
    rng = random.Random(seed)
    return [rng.uniform(-1, 1) for _ in range(36)]


def samples() -> list[Any]:
    """One sample of every message, with values that exercise alignment (odd string lengths, float32s)."""
    tf = m.TransformStamped(
        header=_header("map"),
        child_frame_id="base_link",
        transform=m.Transform(m.Vector3(1.5, -2.25, 0.0), m.quaternion_from_yaw(0.3)),
    )
    pose = m.PoseWithCovariance(m.Pose(m.Point(3.0, 4.0, 0.0), m.quaternion_from_yaw(-1.2)), _covariance(1))
    status = m.DiagnosticStatus(
        level=m.DiagnosticStatus.ERROR,
        name="safety",
        message="protective stop",
        hardware_id="plc-1",
        values=[
            m.KeyValue("estop", "false"),
            m.KeyValue("protective_field", "true"),
            m.KeyValue("field_set", "narrow"),
        ],
    )
    image = m.Image(
        header=_header("camera_color_optical_frame"),
        height=2,
        width=3,
        encoding="rgb8",
        step=9,
        data=bytes(range(18)),
    )
    info = m.CameraInfo(
        header=_header("camera_color_optical_frame"),
        height=480,
        width=640,
        distortion_model="plumb_bob",
        d=[0.1, -0.2, 0.0, 0.0, 0.01],
        k=[615.0, 0.0, 320.5, 0.0, 615.5, 240.25, 0.0, 0.0, 1.0],
        r=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
        p=[615.0, 0.0, 320.5, 0.0, 0.0, 615.5, 240.25, 0.0, 0.0, 0.0, 1.0, 0.0],
        binning_x=1,
        binning_y=2,
        roi=m.RegionOfInterest(1, 2, 3, 4, True),
    )
    return [
        m.stamp(12.5),
        _header("map"),
        m.Float64(0.731),
        m.Bool(True),
        m.String("narrow"),
        m.Vector3(1.0, 2.0, 3.0),
        m.Point(-1.0, 0.5, 2.0),
        m.quaternion_from_yaw(1.0),
        pose.pose,
        pose,
        m.PoseWithCovarianceStamped(_header("map"), pose),
        m.Twist(m.Vector3(0.8, 0, 0), m.Vector3(0, 0, 0.2)),
        m.TwistWithCovariance(m.Twist(m.Vector3(0.8, 0, 0), m.Vector3(0, 0, 0.2)), _covariance(2)),
        tf.transform,
        tf,
        m.Odometry(
            _header("odom"),
            "base_link",
            pose,
            m.TwistWithCovariance(m.Twist(m.Vector3(-0.4, 0, 0)), _covariance(3)),
        ),
        m.TFMessage([tf, tf]),
        m.JointState(_header(), ["steering", "fork_lift"], [0.25, 1.1], [0.0, 0.05], []),
        m.Range(_header("fork_tip_left"), m.Range.INFRARED, 0.05, 0.02, 4.0, math.inf),
        m.RangeWithVariance(_header("fork_tip_right"), m.Range.ULTRASOUND, 0.05, 0.02, 4.0, 1.25, 0.0001),
        image,
        info.roi,
        info,
        m.AckermannDrive(steering_angle=0.3, steering_angle_velocity=0.0, speed=-0.5, acceleration=1.5, jerk=0.0),
        m.AckermannDriveStamped(_header(), m.AckermannDrive(0.1, 0.0, 1.2)),
        m.KeyValue("estop", "true"),
        status,
        m.DiagnosticArray(_header(), [status, m.DiagnosticStatus(name="battery", values=[])]),
    ]


def test_every_message_has_a_sample() -> None:
    assert {type(s) for s in samples()} == set(m.ALL_MESSAGES)


@pytest.mark.parametrize("msg", samples(), ids=lambda s: type(s).__name__)
def test_cdr_bytes_equal_rosbags(stores: dict[str, Any], msg: Any) -> None:
    store = _store(stores, type(msg))
    ours = bytes(msg.serialize())
    theirs = bytes(store.serialize_cdr(_to_rosbags(store, msg), m.ros_type_name(type(msg))))
    assert ours == theirs
    back = type(msg).deserialize(ours)
    assert bytes(back.serialize()) == ours


@pytest.mark.parametrize("cls", m.ALL_MESSAGES, ids=lambda c: c.__name__)
def test_fields_follow_the_msg_definitions(stores: dict[str, Any], cls: Any) -> None:
    """Names and order as in the `.msg` file, and the DDS type name `pkg::msg::dds_::Type_`."""
    for distro, store in stores.items():
        if cls in (m.Range, m.RangeWithVariance) and m.range_type(distro) is not cls:  # type: ignore[arg-type]
            continue
        _consts, fields = store.fielddefs[m.ros_type_name(cls)]
        assert list(cls.__dataclass_fields__) == [name for name, _ in fields], distro
    store = _store(stores, cls)
    _consts, fields = store.fielddefs[m.ros_type_name(cls)]
    assert list(cls.__dataclass_fields__) == [name for name, _ in fields]
    assert cls.__idl_typename__.startswith(m.ros_type_name(cls).split("/")[0] + "::msg::dds_::")


def test_type_names_and_time_helpers() -> None:
    assert m.ros_type_name(m.AckermannDriveStamped) == "ackermann_msgs/msg/AckermannDriveStamped"
    assert m.MESSAGE_TYPES["tf2_msgs/msg/TFMessage"] is m.TFMessage
    assert m.MESSAGE_TYPES["sensor_msgs/msg/Range"] is m.range_type("humble") is m.Range
    assert m.ros_type_name(m.range_type("jazzy")) == "sensor_msgs/msg/Range"
    t = m.stamp(1.999_999_999_9)
    assert (t.sec, t.nanosec) in {(1, 999_999_999), (2, 0)}
    assert m.seconds(m.stamp(1234.5)) == pytest.approx(1234.5)
    for yaw in (-3.0, -0.5, 0.0, 1.0, 3.1):
        assert m.yaw_from_quaternion(m.quaternion_from_yaw(yaw)) == pytest.approx(yaw)


def test_topic_names() -> None:
    assert dds_topic_name("/odom") == "rt/odom"
    assert dds_topic_name("camera/color/image_raw") == "rt/camera/color/image_raw"
    for bad in ("", "/", "odom/", "//odom", "/1odom", "~/odom", "/od om", "/{ns}/odom"):
        with pytest.raises(TransportError):
            check_topic_name(bad)


def test_rclpy_import_guard() -> None:
    """Without a ROS 2 installation `auto` falls back to Cyclone DDS and `rclpy` says what is missing."""
    if rclpy_available():
        pytest.skip("rclpy is installed here")
    from palletpilot.executor.adapters.ros.rclpy_transport import RclpyTransport

    with pytest.raises(TransportError, match="rclpy"):
        RclpyTransport()


@pytest.fixture()
def loopback_dds(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> int:
    """Cyclone DDS on the loopback interface only, in a domain of its own."""
    from palletpilot.executor.adapters.ros.dds import loopback_env

    env = loopback_env(tmp_path)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    return int(env["ROS_DOMAIN_ID"])


def test_dds_round_trip(loopback_dds: int) -> None:
    """Publish on one participant, receive on another: every message, in order, with its receive time."""
    from palletpilot.executor.adapters.ros.dds import DdsTransport

    with DdsTransport() as a, DdsTransport() as b:
        assert a.domain_id == loopback_dds
        got: list[float] = []
        qos = QosSpec(depth=100)  # keep every one of the burst below
        sub = b.subscribe("/cmd", m.AckermannDriveStamped, qos, callback=lambda msg, t: got.append(msg.drive.speed))
        a.advertise("/cmd", m.AckermannDriveStamped, qos)
        t_end = time.monotonic() + 5.0
        while time.monotonic() < t_end and sub.count == 0:  # discovery
            a.publish("/cmd", m.AckermannDriveStamped(drive=m.AckermannDrive(speed=-1.0)))
            time.sleep(0.05)
        assert sub.count > 0, "no message within 5 s over loopback"
        got.clear()
        for i in range(50):
            a.publish("/cmd", m.AckermannDriveStamped(drive=m.AckermannDrive(speed=float(i))))
        t_end = time.monotonic() + 5.0
        while time.monotonic() < t_end and len(got) < 50:
            time.sleep(0.01)
        assert got == [float(i) for i in range(50)]
        latest = sub.latest()
        assert latest is not None and latest.msg.drive.speed == 49.0
        assert 0.0 <= sub.age() < 5.0
    assert os.environ["ROS_DOMAIN_ID"] == str(loopback_dds)

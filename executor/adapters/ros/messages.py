"""ROS 2 standard messages as Cyclone DDS IDL types: the same CDR bytes rclpy puts on the wire.

Each class is a `cyclonedds.idl.IdlStruct` dataclass whose DDS type name is the one rosidl generates
(`pkg::msg::dds_::Type_`), with the fields in the order and of the types of the `.msg` file
(ros2/common_interfaces, ros2/geometry2 for tf2_msgs, ros-drivers/ackermann_msgs branch `ros2`,
ros2/rcl_interfaces for builtin_interfaces), as of ROS 2 Humble and Jazzy. They agree except for
`sensor_msgs/Range`, which gained `variance` after Humble (`Range`, `RangeWithVariance`, `range_type`).
`tests/test_ros_messages.py` serialises every one with Cyclone DDS and with `rosbags` (its ROS 2 Humble
and Jazzy type stores: an independent CDR serialiser) and checks the bytes are identical. Serialisation
is XCDR1 (encapsulation `CDR_LE`, 8-byte alignment), as the rmw implementations use.

`.msg` to IDL: `float64` -> `float64`, `float32` -> `float32`, `uint8`/`byte` -> `uint8`/`byte`,
`bool` -> `bool`, `string` -> `str`, `T[]` -> `sequence[T]`, `T[N]` -> `array[T, N]`; `Image.data` is
carried as `bytes` (the same CDR, one copy instead of a list of ints). Every field has a default (zeros,
an identity quaternion, empty sequences), so a message is built with the fields one needs:
`Float64(data=0.4)`.

Helpers: `ros_type_name(cls)` (`sensor_msgs/msg/Image`), `MESSAGE_TYPES` (ROS name -> class),
`stamp(t_s)` / `seconds(Time)` (ROS time from and to float seconds), `quaternion_from_yaw` and
`yaw_from_quaternion` (rad, rotation about z; REP 103: x forward, y left, z up).
"""

# No `from __future__ import annotations`: cyclonedds resolves the field annotations as objects.
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import cyclonedds.idl.types as t
from cyclonedds.idl import IdlStruct
from cyclonedds.idl._machinery import BytesMachine


def _zeros(n: int) -> list[float]:
    return [0.0] * n


# -- builtin_interfaces, std_msgs ------------------------------------------------------------------
@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    """builtin_interfaces/Time: seconds and nanoseconds since the epoch (ROS time)."""

    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    """std_msgs/Header: when (`stamp`) and in which frame (`frame_id`) the data was taken."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Float64(IdlStruct, typename="std_msgs::msg::dds_::Float64_"):
    """std_msgs/Float64."""

    data: t.float64 = 0.0


@dataclass
class Bool(IdlStruct, typename="std_msgs::msg::dds_::Bool_"):
    """std_msgs/Bool."""

    data: bool = False


@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    """std_msgs/String (the safety scanners' field set selection)."""

    data: str = ""


# -- geometry_msgs ---------------------------------------------------------------------------------
@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    """geometry_msgs/Vector3."""

    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    """geometry_msgs/Point (m)."""

    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    """geometry_msgs/Quaternion (x, y, z, w; identity by default)."""

    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    """geometry_msgs/Pose."""

    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    """geometry_msgs/PoseWithCovariance (row-major 6 x 6 covariance of x, y, z, rot x, rot y, rot z)."""

    pose: Pose = field(default_factory=Pose)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: _zeros(36))


@dataclass
class PoseWithCovarianceStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"):
    """geometry_msgs/PoseWithCovarianceStamped: a localization fix (`T_map_base_link`)."""

    header: Header = field(default_factory=Header)
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    """geometry_msgs/Twist (m/s, rad/s)."""

    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    """geometry_msgs/TwistWithCovariance."""

    twist: Twist = field(default_factory=Twist)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: _zeros(36))


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    """geometry_msgs/Transform: the child frame's pose in the parent frame (`T_parent_child`)."""

    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    """geometry_msgs/TransformStamped: `header.frame_id` is the parent, `child_frame_id` the child."""

    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


# -- nav_msgs, tf2_msgs ----------------------------------------------------------------------------
@dataclass
class Odometry(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    """nav_msgs/Odometry: pose in `header.frame_id`, twist in `child_frame_id` (base_link)."""

    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = field(default_factory=TwistWithCovariance)


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    """tf2_msgs/TFMessage: what `/tf` and `/tf_static` carry."""

    transforms: t.sequence[TransformStamped] = field(default_factory=list)


# -- sensor_msgs -----------------------------------------------------------------------------------
@dataclass
class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    """sensor_msgs/JointState: positions (rad for revolute, m for prismatic joints) by joint name."""

    header: Header = field(default_factory=Header)
    name: t.sequence[str] = field(default_factory=list)
    position: t.sequence[t.float64] = field(default_factory=list)
    velocity: t.sequence[t.float64] = field(default_factory=list)
    effort: t.sequence[t.float64] = field(default_factory=list)


@dataclass
class Range(IdlStruct, typename="sensor_msgs::msg::dds_::Range_"):
    """sensor_msgs/Range as ROS 2 Humble has it (m; REP 117: +inf nothing detected within `max_range`)."""

    ULTRASOUND = 0
    INFRARED = 1

    header: Header = field(default_factory=Header)
    radiation_type: t.uint8 = 1
    field_of_view: t.float32 = 0.0
    min_range: t.float32 = 0.0
    max_range: t.float32 = 0.0
    range: t.float32 = 0.0


@dataclass
class RangeWithVariance(IdlStruct, typename="sensor_msgs::msg::dds_::Range_"):
    """sensor_msgs/Range from ROS 2 Jazzy on: `variance` (m^2) appended; the robot file's `ros_distro` picks."""

    ULTRASOUND = 0
    INFRARED = 1

    header: Header = field(default_factory=Header)
    radiation_type: t.uint8 = 1
    field_of_view: t.float32 = 0.0
    min_range: t.float32 = 0.0
    max_range: t.float32 = 0.0
    range: t.float32 = 0.0
    variance: t.float32 = 0.0


@dataclass
class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    """sensor_msgs/Image: `encoding` rgb8, bgr8, 16UC1 (depth, mm) or 32FC1 (depth, m); rows of `step` bytes."""

    header: Header = field(default_factory=Header)
    height: t.uint32 = 0
    width: t.uint32 = 0
    encoding: str = ""
    is_bigendian: t.uint8 = 0
    step: t.uint32 = 0
    data: t.sequence[t.uint8] = field(default_factory=bytes)


@dataclass
class RegionOfInterest(IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    """sensor_msgs/RegionOfInterest (pixels)."""

    x_offset: t.uint32 = 0
    y_offset: t.uint32 = 0
    height: t.uint32 = 0
    width: t.uint32 = 0
    do_rectify: bool = False


@dataclass
class CameraInfo(IdlStruct, typename="sensor_msgs::msg::dds_::CameraInfo_"):
    """sensor_msgs/CameraInfo: `k` the row-major 3 x 3 intrinsics of the image (pixels)."""

    header: Header = field(default_factory=Header)
    height: t.uint32 = 0
    width: t.uint32 = 0
    distortion_model: str = ""
    d: t.sequence[t.float64] = field(default_factory=list)
    k: t.array[t.float64, 9] = field(default_factory=lambda: _zeros(9))
    r: t.array[t.float64, 9] = field(default_factory=lambda: _zeros(9))
    p: t.array[t.float64, 12] = field(default_factory=lambda: _zeros(12))
    binning_x: t.uint32 = 0
    binning_y: t.uint32 = 0
    roi: RegionOfInterest = field(default_factory=RegionOfInterest)


# -- ackermann_msgs --------------------------------------------------------------------------------
@dataclass
class AckermannDrive(IdlStruct, typename="ackermann_msgs::msg::dds_::AckermannDrive_"):
    """ackermann_msgs/AckermannDrive: steering angle (rad), speed (m/s), acceleration (m/s^2), ..."""

    steering_angle: t.float32 = 0.0
    steering_angle_velocity: t.float32 = 0.0
    speed: t.float32 = 0.0
    acceleration: t.float32 = 0.0
    jerk: t.float32 = 0.0


@dataclass
class AckermannDriveStamped(IdlStruct, typename="ackermann_msgs::msg::dds_::AckermannDriveStamped_"):
    """ackermann_msgs/AckermannDriveStamped: the drive command, stamped when sent."""

    header: Header = field(default_factory=Header)
    drive: AckermannDrive = field(default_factory=AckermannDrive)


# -- diagnostic_msgs -------------------------------------------------------------------------------
@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    """diagnostic_msgs/KeyValue."""

    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    """diagnostic_msgs/DiagnosticStatus: `level` OK 0, WARN 1, ERROR 2, STALE 3."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3

    level: t.byte = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: t.sequence[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    """diagnostic_msgs/DiagnosticArray."""

    header: Header = field(default_factory=Header)
    status: t.sequence[DiagnosticStatus] = field(default_factory=list)


def _as_bytes(cls: type[IdlStruct], member: str) -> None:
    """Carry a `uint8[]` member as `bytes`: the type stays `sequence<uint8>` for DDS type matching, the CDR is
    the same (a uint32 length, then the bytes), but an image is one copy instead of a list of ints."""
    idl: Any = cls.__idl__
    idl.populate()
    for machine in (idl.v1_machine, idl.v2_machine):
        machine.members_machines[member] = BytesMachine()


_as_bytes(Image, "data")


ALL_MESSAGES: tuple[type[IdlStruct], ...] = (
    Time,
    Header,
    Float64,
    Bool,
    String,
    Vector3,
    Point,
    Quaternion,
    Pose,
    PoseWithCovariance,
    PoseWithCovarianceStamped,
    Twist,
    TwistWithCovariance,
    Transform,
    TransformStamped,
    Odometry,
    TFMessage,
    JointState,
    Range,
    RangeWithVariance,
    Image,
    RegionOfInterest,
    CameraInfo,
    AckermannDrive,
    AckermannDriveStamped,
    KeyValue,
    DiagnosticStatus,
    DiagnosticArray,
)


def ros_type_name(cls: type[IdlStruct]) -> str:
    """The ROS 2 name of a message class: `sensor_msgs::msg::dds_::Image_` -> `sensor_msgs/msg/Image`."""
    typename = str(cls.__idl_typename__)
    pkg, _msg, _dds, name = typename.split("::")
    return f"{pkg}/msg/{name.removesuffix('_')}"


MESSAGE_TYPES: dict[str, type[IdlStruct]] = {ros_type_name(c): c for c in ALL_MESSAGES if c is not RangeWithVariance}
"""ROS 2 type name (`nav_msgs/msg/Odometry`) -> IDL class (Humble's; `range_type` for Jazzy's Range)."""

RosDistro = Literal["humble", "jazzy"]
"""The ROS 2 release whose message definitions the truck uses (they differ in `sensor_msgs/Range` only)."""


def range_type(distro: RosDistro) -> type[Range] | type[RangeWithVariance]:
    """`sensor_msgs/Range` of a ROS 2 release: Humble's, or Jazzy's (and later) with `variance`."""
    return Range if distro == "humble" else RangeWithVariance


def stamp(t_s: float) -> Time:
    """ROS time of `t_s` seconds since the epoch (`time.time()`)."""
    sec = math.floor(t_s)
    return Time(sec=int(sec), nanosec=min(round((t_s - sec) * 1e9), 999_999_999))


def seconds(time: Time) -> float:
    """Seconds since the epoch of a ROS time."""
    return float(time.sec) + 1e-9 * float(time.nanosec)


def quaternion_from_yaw(yaw: float) -> Quaternion:
    """The rotation by `yaw` (rad) about z."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


def yaw_from_quaternion(q: Quaternion) -> float:
    """The heading (rad, about z) of a rotation; roll and pitch are ignored (a truck on a level floor)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))

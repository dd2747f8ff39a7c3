"""The robot file (`robot.yaml`): how a truck's ROS 2 topics, frames, QoS, rates and timeouts are wired.

`load_robot(path)` reads and checks it (`RobotConfigError`: one line per problem naming the field, the
CLI's exit 2). The example is `missions/robot.yaml`; README "On a real truck (ROS 2)" has the wiring
table. Every topic is a ROS 2 name, or a mapping `{name, qos: {reliability, depth, durability},
timeout_s}`; `timeout_s` is how old the topic's last message may be before the adapter refuses to
start (and, while running, stops the truck with `sensor_timeout`).

Frames follow REP 103 / 105: `map` (the localization frame: the roadmap's world frame), `odom`,
`base_link` (on the truck), `camera_color_optical_frame` (realsense-ros's optical frame: x right, y
down, z out of the lens). `base_link_to_forklift` places the executor's `forklift` frame (on the floor
midway between the forks, at the fork heels, x towards the fork tips) in `base_link`: x, y (m), yaw
(deg); identity when the truck's `base_link` is the forklift origin.

Joint states: `steering` (rad) times `steering_sign` is the executor's steering angle (its tangent over
the wheelbase is the path curvature, positive turning left driving forward: a rear-steered truck's
wheel joint usually has sign -1); `fork` (m) plus `fork_offset_m` is the fork bottoms' height above
the floor.

Safety (`diagnostic_msgs/DiagnosticArray` on `diagnostics`): the status named `safety.status` carries
the safety PLC's state as key / value strings: `estop` (true / false), `protective_field` (true: a
protective stop holds the truck), `warning_field` (true: speed capped), `speed_limit` (m/s, the cap;
default the vehicle file's `warning_speed`), `field_set` (`normal` / `narrow`), `direction`
(`forward` / `reverse`), `intrusions` (comma-separated names). Level ERROR (or STALE) on that status,
or ERROR on a status named in `safety.fault_statuses`, is a fault: the runner stops the truck.

Public API: `RobotConfig`, `RobotConfigError`, `TopicSpec`, `load_robot`, `topic_spec`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_core import PydanticCustomError

from palletpilot.executor.adapters.ros.messages import RosDistro
from palletpilot.executor.adapters.ros.transport import QosSpec, TransportError, check_topic_name
from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.fileio import FileModel, load_yaml_model


class RobotConfigError(PalletpilotError):
    """A robot file that cannot be used; one line per problem, naming the file and the field."""


_FRAME = Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$", max_length=200)]


class QosModel(FileModel):
    """A topic's QoS: reliability, keep-last depth, durability."""

    reliability: Literal["reliable", "best_effort"] = "reliable"
    depth: int = Field(10, ge=1, le=1000)
    durability: Literal["volatile", "transient_local"] = "volatile"

    def spec(self) -> QosSpec:
        """The transport's `QosSpec`."""
        return QosSpec(self.reliability, self.depth, self.durability)


class TopicSpec(FileModel):
    """One topic: its ROS 2 name, QoS, and for inputs how old its last message may be (s)."""

    name: str
    qos: QosModel = Field(default_factory=QosModel)
    timeout_s: float | None = Field(None, gt=0.0, le=60.0, description="inputs: the oldest usable message (s)")

    @field_validator("name")
    @classmethod
    def _ros_name(cls, name: str) -> str:
        try:
            return check_topic_name(name)
        except TransportError as exc:
            raise PydanticCustomError("topic_name", str(exc)) from None


def topic_spec(
    name: str,
    reliability: Literal["reliable", "best_effort"] = "reliable",
    depth: int = 10,
    timeout_s: float | None = None,
) -> TopicSpec:
    """A `TopicSpec` for defaults (`topic_spec("/odom", timeout_s=0.5)`)."""
    return TopicSpec(name=name, qos=QosModel(reliability=reliability, depth=depth), timeout_s=timeout_s)


def _topic(value: Any) -> Any:
    """A bare topic name is `{name: ...}`."""
    return {"name": value} if isinstance(value, str) else value


class Topics(FileModel):
    """Every topic the adapter uses; inputs have a timeout (s)."""

    odometry: TopicSpec = Field(default_factory=lambda: topic_spec("/odom", timeout_s=0.3))
    joint_states: TopicSpec = Field(default_factory=lambda: topic_spec("/joint_states", timeout_s=0.3))
    beam_left: TopicSpec = Field(default_factory=lambda: topic_spec("/forks/tip_range_left", timeout_s=0.5))
    beam_right: TopicSpec = Field(default_factory=lambda: topic_spec("/forks/tip_range_right", timeout_s=0.5))
    load: TopicSpec = Field(default_factory=lambda: topic_spec("/forks/load", timeout_s=1.0))
    diagnostics: TopicSpec = Field(default_factory=lambda: topic_spec("/diagnostics", timeout_s=1.0))
    drive: TopicSpec = Field(default_factory=lambda: topic_spec("/drive"))
    fork_height: TopicSpec = Field(default_factory=lambda: topic_spec("/forks/height_target"))
    emergency_stop: TopicSpec = Field(default_factory=lambda: topic_spec("/safety/emergency_stop"))
    field_set: TopicSpec = Field(default_factory=lambda: topic_spec("/safety/field_set"))

    @field_validator("*", mode="before")
    @classmethod
    def _bare_names(cls, value: Any) -> Any:
        return _topic(value)

    def inputs(self) -> dict[str, TopicSpec]:
        """The topics the adapter subscribes, by field name."""
        return {
            k: getattr(self, k) for k in ("odometry", "joint_states", "beam_left", "beam_right", "load", "diagnostics")
        }


class Frames(FileModel):
    """Frame ids (REP 105) and where the executor's `forklift` frame sits in `base_link`."""

    map: _FRAME = "map"
    odom: _FRAME | None = "odom"
    base_link: _FRAME = "base_link"
    camera: _FRAME = "camera_color_optical_frame"
    base_link_to_forklift: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="the forklift frame in base_link: x (m), y (m), yaw (deg)"
    )


class Localization(FileModel):
    """Where `T_map_base_link` comes from: tf (`map -> base_link`, or `map -> odom -> base_link`) or a pose topic."""

    source: Literal["tf", "pose"] = "tf"
    tf: TopicSpec = Field(default_factory=lambda: topic_spec("/tf", depth=100))
    pose: TopicSpec = Field(default_factory=lambda: topic_spec("/amcl_pose"))
    timeout_s: float = Field(0.5, gt=0.0, le=10.0, description="the oldest usable fix (s): the runner's watchdog")

    @field_validator("tf", "pose", mode="before")
    @classmethod
    def _bare_names(cls, value: Any) -> Any:
        return _topic(value)


class Joints(FileModel):
    """Joint names in `sensor_msgs/JointState` and how they map to the executor's readings."""

    steering: str = Field("steering_joint", min_length=1)
    steering_sign: Literal[1, -1] = 1
    fork: str = Field("fork_lift_joint", min_length=1)
    fork_offset_m: float = Field(0.0, ge=-1.0, le=1.0)


class Camera(FileModel):
    """The camera: `ros` (realsense-ros topics), `realsense` (pyrealsense2 in this process) or `none`."""

    source: Literal["ros", "realsense", "none"] = "ros"
    color: TopicSpec = Field(default_factory=lambda: topic_spec("/camera/camera/color/image_raw", depth=1))
    depth: TopicSpec = Field(
        default_factory=lambda: topic_spec("/camera/camera/aligned_depth_to_color/image_raw", depth=1)
    )
    info: TopicSpec = Field(default_factory=lambda: topic_spec("/camera/camera/color/camera_info", depth=1))
    timeout_s: float = Field(0.5, gt=0.0, le=10.0, description="the oldest usable frame (s)")
    pair_tolerance_s: float = Field(0.02, gt=0.0, le=1.0, description="colour and depth stamps at most this apart")
    serial: str | None = Field(None, description="realsense: the camera's serial (default: the only one)")
    rate_hz: float = Field(5.0, gt=0.0, le=60.0, description="sim serve: frames per second it publishes")

    @field_validator("color", "depth", "info", mode="before")
    @classmethod
    def _bare_names(cls, value: Any) -> Any:
        return _topic(value)


class Safety(FileModel):
    """How the safety PLC's state is read from the diagnostics (module docstring)."""

    status: str = Field("safety", min_length=1)
    fault_statuses: list[str] = Field(default_factory=list, description="more statuses whose ERROR is a fault")


class Rates(FileModel):
    """The control rate (Hz): the runner's tick and the drive command's rate."""

    control_hz: float = Field(20.0, ge=5.0, le=100.0)


class CalibrationCheck(FileModel):
    """The camera calibration `palletpilot robot --calibration` takes, and how old it may be (days)."""

    file: str | None = None
    max_age_days: float = Field(30.0, gt=0.0)


class RobotConfig(FileModel):
    """A robot file (module docstring)."""

    name: str = Field("truck", min_length=1, max_length=200)
    ros_distro: RosDistro = "humble"
    transport: Literal["auto", "dds", "rclpy"] = "auto"
    domain_id: int | None = Field(None, ge=0, le=232, description="null: ROS_DOMAIN_ID, else 0")
    vehicle: str | None = Field(None, description="vehicle file (default: the mission map's)")
    forks: str = "forks.yaml"
    command_timeout_s: float = Field(
        0.2, gt=0.0, le=2.0, description="the truck controller's: no drive command this long, it brakes"
    )
    rates: Rates = Field(default_factory=Rates)
    frames: Frames = Field(default_factory=Frames)
    localization: Localization = Field(default_factory=Localization)
    topics: Topics = Field(default_factory=Topics)
    joints: Joints = Field(default_factory=Joints)
    camera: Camera = Field(default_factory=Camera)
    safety: Safety = Field(default_factory=Safety)
    calibration: CalibrationCheck = Field(default_factory=CalibrationCheck)
    folder: Path = Field(Path("."), exclude=True)
    source: str = Field("robot.yaml", exclude=True)

    @model_validator(mode="after")
    def _distinct_topics(self) -> RobotConfig:
        seen: dict[str, str] = {}
        for where, spec in self.all_topics().items():
            other = seen.setdefault(spec.name.lstrip("/"), where)
            if other != where:
                raise PydanticCustomError(
                    "topic_twice", f"{where} and {other} are both '{spec.name}': every topic carries one thing"
                )
        return self

    def all_topics(self) -> dict[str, TopicSpec]:
        """Every topic in use, by its field path (`topics.odometry`, `camera.color`, ...)."""
        out = {f"topics.{k}": getattr(self.topics, k) for k in Topics.model_fields}
        loc = self.localization
        out["localization.tf" if loc.source == "tf" else "localization.pose"] = (
            loc.tf if loc.source == "tf" else loc.pose
        )
        if self.camera.source == "ros":
            out.update({f"camera.{k}": getattr(self.camera, k) for k in ("color", "depth", "info")})
        return out

    @property
    def control_dt(self) -> float:
        """The control period (s)."""
        return 1.0 / self.rates.control_hz

    def path(self, name: str) -> Path:
        """A file named in the robot file, resolved against its folder."""
        return self.folder / name


def load_robot(path: str | Path) -> RobotConfig:
    """Read and check a robot file; every problem raises `RobotConfigError` naming the file and the field."""
    config = load_yaml_model(path, RobotConfig, RobotConfigError)
    config.folder = Path(path).parent
    config.source = str(path)
    return config

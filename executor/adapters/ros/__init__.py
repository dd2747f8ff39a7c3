"""On-robot execution over ROS 2: the vehicle adapter, its camera sources and its transports.

Modules:

- `messages`: the ROS 2 standard messages as Cyclone DDS IDL types (the same CDR bytes rclpy produces).
- `transport`: the `Transport` interface (advertise, publish, subscribe, close), `open_transport` and an
  in-process `MemoryTransport`; `dds` (Cyclone DDS from PyPI: no ROS installation needed) and
  `rclpy_transport` (a sourced ROS 2) implement it.
- `config`: the robot file (`robot.yaml`): topics, frames, QoS, rates, timeouts, the safety convention.
- `vehicle`: `RosVehicle`, the executor's `VehiclePort` on those topics.
- `camera`: `RosCamera` (realsense-ros topics) and `RealSenseCamera` (pyrealsense2): frame bundles.

The composition roots over this adapter are apps: `executor.apps.robot` (`run_robot`), the VDA 5050 AGV's
`executor.apps.vda5050.robot_backend` (`open_backend`; both start through `startup`) and
`executor.apps.cli_robot` (the commands, and the `calibrate --ros-static-tf` output); the simulator playing
the truck on the same topics is `executor.apps.standin` (`palletpilot sim serve --ros`).

Frames follow REP 103 / 105 (`map`, `odom`, `base_link`, `camera_color_optical_frame`); units are SI (m,
rad, s) on every topic. The public names below load on first use, so importing the package stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Transport": "transport",
    "MemoryTransport": "transport",
    "QosSpec": "transport",
    "TransportError": "transport",
    "open_transport": "transport",
    "DdsTransport": "dds",
    "loopback_env": "dds",
    "RobotConfig": "config",
    "RobotConfigError": "config",
    "load_robot": "config",
    "RosVehicle": "vehicle",
    "RosCamera": "camera",
    "RealSenseCamera": "camera",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)

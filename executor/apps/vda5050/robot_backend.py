"""The VDA 5050 AGV on a real truck (`palletpilot agv --robot robot.yaml`): its vehicle backend over the ROS 2
adapter (`executor.adapters.ros`), the camera and perception in this process.

Public API: `open_backend`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from palletpilot.control.mpc import MpcConfig, MpcFollower
from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.adapters.local_perception import LocalPerception
from palletpilot.executor.adapters.ros.config import load_robot
from palletpilot.executor.adapters.ros.startup import RobotError, camera_grab, start_node
from palletpilot.executor.apps.vda5050.vehicle import Backend, TickClock
from palletpilot.executor.core.clock import WallClock
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.perception.labels_mode import DEFAULT_LABELS_MODE, LabelsMode
from palletpilot.perception.specs import load_forks


def open_backend(
    loaded: Any, robot_path: str | Path, wait_s: float = 5.0, labels: LabelsMode = DEFAULT_LABELS_MODE
) -> Any:
    """The VDA 5050 AGV's vehicle on a real truck (`palletpilot agv --robot robot.yaml`): a
    `executor.vda5050.vehicle.Backend` with `RosVehicle`, the camera, perception in this process and a
    wall clock at the robot file's rate that sends the drive command after every tick.

    `loaded`: the AGV's checked configuration (its roadmap and vehicle). Refuses (`RobotError`, one line
    each) as `run_robot` does: a bad robot or forks file, silent topics, no tf, a fault, no camera frame.
    The start node is the node the truck stands on, or None (the AGV then takes the nearest).
    """
    from palletpilot.executor.adapters.ros.camera import RealSenseCamera, RosCamera
    from palletpilot.executor.adapters.ros.transport import open_transport
    from palletpilot.executor.adapters.ros.vehicle import RosVehicle
    from palletpilot.perception.segmentation import DEFAULT_MODEL, OnnxSegmenter
    from palletpilot.perception.specs import PalletType

    problems: list[str] = []
    config = collect(problems, lambda: load_robot(robot_path))
    forks = collect(problems, lambda: load_forks(config.path(config.forks))) if config is not None else None
    raise_problems(problems, RobotError)
    assert config is not None and forks is not None
    params: VehicleParams = loaded.vehicle
    transport = open_transport(config.transport, config.domain_id)
    camera: RosCamera | RealSenseCamera | None = None
    try:
        vehicle = RosVehicle(transport, config, params)
        if config.camera.source == "ros":
            camera = RosCamera(transport, config, lambda: vehicle.fork_height)
        elif config.camera.source == "realsense":
            camera = RealSenseCamera(config.camera.serial, lambda: vehicle.fork_height)
        problems = vehicle.wait_ready(wait_s)
        t_end = time.monotonic() + (0.0 if problems else wait_s)
        while camera is not None and camera.problems() and time.monotonic() < t_end:
            time.sleep(0.05)
        problems += camera.problems() if camera is not None else []
        raise_problems([f"{config.source}: {p}" for p in problems], RobotError)
        try:
            node: str | None = start_node(loaded.roadmap, vehicle.localization())
        except RobotError:
            node = None
    except BaseException:
        if camera is not None:
            camera.close()
        transport.close()
        raise
    clock = TickClock(WallClock(dt=config.control_dt, step=vehicle.tick))
    vehicle.now = clock.now
    if camera is not None:
        camera.now = clock.now

    def close() -> None:
        vehicle.close()
        if camera is not None:
            camera.close()
        transport.close()

    return Backend(
        vehicle=vehicle,
        perception=LocalPerception(
            forks,
            PalletType.eur(),
            segmenter=None if labels == LabelsMode.GEOMETRY else OnnxSegmenter(DEFAULT_MODEL),
            labels=labels,
        ),
        grab=camera_grab(camera, config.source),
        clock=clock,
        params=params,
        forks=forks,
        follower=MpcFollower(params, MpcConfig()),
        start_node=node,
        close=close,
    )

"""Running a mission on a real truck over ROS 2: from files to a finished, reported run (`palletpilot robot`).

`run_robot(mission_path, robot_path, ...)` reads and checks every input first (the mission, its map, the
robot file, the vehicle and forks files, the calibration and its age: all problems at once, one line
each, `RobotError`), opens the transport (`executor.ros.transport.open_transport`), and refuses to start
while a required topic is silent for its timeout, tf (or the pose topic) gives no fix, the safety state
has a fault, or the camera gives no frame (waiting up to `wait_s` for the truck to come up). The start
node is the roadmap node the truck stands on (within 0.25 m and 10 deg), or `start` when given (checked
the same way). The mission is validated from there; then the runner drives the truck through
`RosVehicle` on a `WallClock` at the control rate (after each tick the drive command goes out), with
the runner's watchdogs and fail-safe stop, perception in this process or in the service, a journal when
asked, and the report in `report_dir` (as `palletpilot run`'s, without simulator truth).

The calibration (`--calibration FILE`, or the robot file's `calibration.file`) must be younger than
`calibration.max_age_days` (the file's modification time); it seeds perception's last good calibration,
which the Delivery's slot check uses when no Pickup calibrated on this run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from palletpilot.control.mpc import MpcConfig, MpcFollower
from palletpilot.control.vehicle import VehicleParams, load_vehicle
from palletpilot.executor.adapters.local_perception import LocalPerception
from palletpilot.executor.adapters.mcap.recording import Recorder, start_recording
from palletpilot.executor.adapters.ros.config import RobotConfig, load_robot
from palletpilot.executor.adapters.ros.startup import (
    RobotError,
    camera_grab,
    start_node,
)
from palletpilot.executor.adapters.stores.journal import Journal
from palletpilot.executor.adapters.stores.report import ms_stats, summary
from palletpilot.executor.apps import compose
from palletpilot.executor.core.behaviour import Settings
from palletpilot.executor.core.clock import WallClock
from palletpilot.executor.core.controls import Controls
from palletpilot.executor.core.mission import Mission, load_mission, validate_mission
from palletpilot.executor.core.runner import Runner
from palletpilot.executor.ports import PerceptionService
from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.perception.calibration_io import Calibration, load_calibration
from palletpilot.perception.labels_mode import DEFAULT_LABELS_MODE, LabelsMode
from palletpilot.perception.specs import ForkGeometry, load_forks
from palletpilot.roadmap import Roadmap, load_map, map_vehicle_file


@dataclass
class RobotRun:
    """A finished run on the truck."""

    success: bool
    runner: Runner
    summary: dict[str, Any]
    report: Path | None
    write_errors: list[str] = field(default_factory=list)


@dataclass
class Inputs:
    """Everything read from files before the truck is contacted."""

    mission: Mission
    roadmap: Roadmap
    config: RobotConfig
    params: VehicleParams
    forks: ForkGeometry
    calibration: Calibration | None


def calibration_problem(path: Path, max_age_days: float, now_s: float | None = None) -> str | None:
    """A line when the calibration file is older than `max_age_days` (its modification time), else None."""
    try:
        age_days = ((time.time() if now_s is None else now_s) - path.stat().st_mtime) / 86400.0
    except OSError:
        return None  # unreadable: `load_calibration` says why
    if age_days > max_age_days:
        return (
            f"{path}: the calibration is stale: {age_days:.1f} days old (limit {max_age_days:g} days, "
            "calibration.max_age_days): calibrate again (palletpilot calibrate ... --out FILE)"
        )
    return None


def load_inputs(
    mission_path: str | Path, robot_path: str | Path, calibration_path: str | Path | None = None, adapt: bool = True
) -> Inputs:
    """Read and check every file of a run; `RobotError` lists every problem of every file."""
    problems: list[str] = []
    mission = collect(problems, lambda: load_mission(mission_path))
    config = collect(problems, lambda: load_robot(robot_path))
    roadmap = collect(problems, lambda: load_map(mission.map_path)) if mission is not None else None
    params = forks = calibration = None
    if mission is not None and config is not None:
        vehicle_file = config.path(config.vehicle) if config.vehicle else map_vehicle_file(mission.map_path)
        if vehicle_file is None:
            problems.append(f"{robot_path}: vehicle: the mission's map names no vehicle file; give one here")
        else:
            params = collect(problems, lambda: load_vehicle(vehicle_file))
    if config is not None:
        forks = collect(problems, lambda: load_forks(config.path(config.forks)))
        cal_path = calibration_path or (config.path(config.calibration.file) if config.calibration.file else None)
        if cal_path is not None:
            calibration = collect(problems, lambda: load_calibration(cal_path))
            stale = calibration_problem(Path(cal_path), config.calibration.max_age_days)
            if stale is not None:
                problems.append(stale)
        if mission is not None and config.camera.source == "none":
            # Every pickup looks before the forks go in, --no-adapt too; a delivery without adaptation may
            # check its slot with the beams alone.
            looking = ("pickup", "delivery") if adapt else ("pickup",)
            if any(t.type in looking for t in mission.tasks):
                problems.append(
                    f"{robot_path}: camera.source: none, but the mission's "
                    f"{'pickups and deliveries look' if adapt else 'pickups look'} with the camera before the "
                    "forks go in (give a camera)"
                )
    raise_problems(problems, RobotError)
    assert mission is not None and roadmap is not None and config is not None
    assert params is not None and forks is not None
    return Inputs(mission, roadmap, config, params, forks, calibration)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_robot(
    mission_path: str | Path,
    robot_path: str | Path,
    *,
    report_dir: str | Path | None = None,
    journal: str | Path | None = None,
    calibration_path: str | Path | None = None,
    perception_mode: str = "local",
    perception_connect: Sequence[str] = (),
    adapt: bool = True,
    start: str | None = None,
    wait_s: float = 5.0,
    progress: TextIO | None = None,
    controls: Controls | None = None,
    settings: Settings | None = None,
    on_ready: Callable[[str], None] | None = None,
    foxglove: int | None = None,
    foxglove_host: str = "127.0.0.1",
    labels: LabelsMode = DEFAULT_LABELS_MODE,
) -> RobotRun:
    """Check, connect, refuse or run (module docstring); `RobotError` for every reason not to start.

    `labels`: which source selects perception's pixels (`perception.labels_mode`; fused by default).

    The report folder gets `run.mcap` (`executor.recording`); `foxglove`: also serve the run live over
    Foxglove WebSocket on `foxglove_host:foxglove` (a port that cannot be served: `RecordingError`)."""
    from palletpilot.executor.adapters.ros.camera import RealSenseCamera, RosCamera
    from palletpilot.executor.adapters.ros.transport import open_transport
    from palletpilot.executor.adapters.ros.vehicle import RosVehicle

    inputs = load_inputs(mission_path, robot_path, calibration_path, adapt)
    if journal is not None:
        _check_journal(Path(journal))
    config = inputs.config
    with contextlib.ExitStack() as stack:
        transport = open_transport(config.transport, config.domain_id)
        stack.callback(transport.close)
        vehicle = RosVehicle(transport, config, inputs.params)
        stack.callback(vehicle.close)
        camera: RosCamera | RealSenseCamera | None = None
        if config.camera.source == "ros":
            camera = RosCamera(transport, config, lambda: vehicle.fork_height)
        elif config.camera.source == "realsense":
            camera = RealSenseCamera(config.camera.serial, lambda: vehicle.fork_height)
            stack.callback(camera.close)
        problems = vehicle.wait_ready(wait_s)
        t_end = time.monotonic() + (wait_s if not problems else 0.0)
        while camera is not None and camera.problems() and time.monotonic() < t_end:
            time.sleep(0.05)
        problems += camera.problems() if camera is not None else []  # --no-adapt looks with it too
        raise_problems([f"{config.source}: {p}" for p in problems], RobotError)
        node = start_node(inputs.roadmap, vehicle.localization(), start)
        validate_mission(inputs.mission, inputs.roadmap, inputs.params, node, str(mission_path))
        if on_ready is not None:
            on_ready(node)
        return _execute(
            inputs, vehicle, camera, node, stack, mission_path, robot_path, report_dir, journal, perception_mode,
            perception_connect, adapt, progress, controls, settings, (foxglove, foxglove_host), labels,
        )  # fmt: skip


def _check_journal(path: Path) -> None:
    """Refuse, before anything connects, a journal that holds an unfinished run: `palletpilot robot` does
    not resume one (`RobotError`, one line); a finished run's journal is replaced when the run starts."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    try:
        old = Journal.open(path)
    except PalletpilotError:
        return  # not a journal: `Journal.create` refuses it with its reason
    try:
        unfinished = not old.finished
        last = old.last_checkpoint()
    finally:
        old.close()
    if unfinished:
        task = "" if last is None else f" (last checkpoint in task {last.get('task', '?')})"
        raise RobotError(
            f"{path}: holds an unfinished run{task}; `palletpilot robot` does not resume one: check the truck and "
            "its load by hand, then remove the file or give another --journal"
        )


def _execute(
    inputs: Inputs,
    vehicle: Any,
    camera: Any,
    node: str,
    stack: contextlib.ExitStack,
    mission_path: str | Path,
    robot_path: str | Path,
    report_dir: str | Path | None,
    journal: str | Path | None,
    perception_mode: str,
    perception_connect: Sequence[str],
    adapt: bool,
    progress: TextIO | None,
    controls: Controls | None,
    settings: Settings | None,
    live: tuple[int | None, str] = (None, "127.0.0.1"),
    labels: LabelsMode = DEFAULT_LABELS_MODE,
) -> RobotRun:
    """Build the runner on the connected truck (`compose`) and run the mission; write the report and
    `run.mcap`."""
    config, mission = inputs.config, inputs.mission
    settings = dataclasses.replace(settings or Settings(), adapt=adapt)
    looks = adapt or config.camera.source != "none"  # --no-adapt looks with the camera where there is one
    perception = _perception(inputs, stack, looks, perception_mode, perception_connect, labels)
    folder = Path(report_dir).resolve() if report_dir is not None else None
    recorder: Recorder | None = None  # started once the report folder is clean

    def step(dt: float) -> None:
        if recorder is not None:
            recorder.tick()  # the state the runner saw this tick
        vehicle.tick(dt)

    clock = WallClock(dt=config.control_dt, step=step)
    vehicle.now = clock.now
    if camera is not None:
        camera.now = clock.now
    run_id = uuid.uuid4().hex
    book = _journal(journal, run_id, mission_path, robot_path, mission, node, folder, adapt)
    if book is not None:
        stack.callback(book.close)
    if folder is not None:
        compose.prepare_report_dir(folder, fresh=True)
    events = compose.open_events(folder, stack)
    recorder = start_recording(folder, live[0], wall=True, host=live[1])  # RecordingError: a port in use
    if recorder is not None:
        stack.callback(recorder.close)
        if isinstance(perception, LocalPerception) and perception.segmenter is not None:
            perception.segmenter = recorder.wrap_segmenter(perception.segmenter)
    outputs = compose.Outputs(events, book, recorder)
    parts = compose.Parts(
        mission, inputs.roadmap, vehicle, perception, camera_grab(camera, config.source), clock, inputs.params,
        inputs.forks, node, MpcFollower(inputs.params, MpcConfig()),
    )  # fmt: skip
    runner = compose.build_runner(parts, outputs, settings, progress, controls)
    extra = functools.cache(lambda: _figures(runner, vehicle, clock, config.name, run_id, node, adapt))
    start = {"run_id": run_id, "robot": config.name, "clock": "wall", "start": node}
    success, write_errors = compose.run_and_finish(runner, outputs, extra, start)
    if recorder is not None:
        recorder.close()
        write_errors += recorder.errors
    report = compose.write_run_report(folder, runner, success, extra(), write_errors)
    return RobotRun(success, runner, summary(success, runner.results), report, write_errors)


def _perception(
    inputs: Inputs,
    stack: contextlib.ExitStack,
    looks: bool,
    perception_mode: str,
    perception_connect: Sequence[str],
    labels: LabelsMode,
) -> PerceptionService | None:
    """The truck's perception: in process (the shipped model unless `geometry`, the robot's calibration as
    the last good one), the perception service (stopped with `stack`), or none when nothing `looks` (a
    `--no-adapt` run without a camera, whose mission has no pickup: `load_inputs`)."""
    from palletpilot.perception.segmentation import DEFAULT_MODEL, OnnxSegmenter
    from palletpilot.perception.specs import PalletType

    if looks and perception_mode == "local":
        segmenter = None if labels == LabelsMode.GEOMETRY else OnnxSegmenter(DEFAULT_MODEL)
        local = LocalPerception(inputs.forks, PalletType.eur(), segmenter=segmenter, labels=labels)
        local.calibrator.last_good = inputs.calibration
        return local
    if not looks:
        return None
    from palletpilot.executor.adapters.zenoh.perception_remote import remote_perception

    service = remote_perception(
        perception_mode,  # type: ignore[arg-type]
        perception_connect,
        inputs.forks,
        PalletType.eur(),
        DEFAULT_MODEL,
        labels=labels,
    )
    return stack.enter_context(service)


def _journal(
    journal: str | Path | None,
    run_id: str,
    mission_path: str | Path,
    robot_path: str | Path,
    mission: Mission,
    node: str,
    folder: Path | None,
    adapt: bool,
) -> Journal | None:
    """The run's SQLite journal at `journal` (None: none), created with the run's identity in its meta."""
    if journal is None:
        return None
    meta = {
        "run_id": run_id,
        "kind": "robot",
        "mission": str(Path(mission_path).resolve()),
        "mission_sha256": _sha256(Path(mission_path)),
        "map_sha256": _sha256(mission.map_path),
        "robot": str(Path(robot_path).resolve()),
        "start": node,
        "report_dir": None if folder is None else str(folder),
        "adapt": adapt,
        "clock": "wall",
    }
    return Journal.create(journal, meta)


def _figures(
    runner: Runner, vehicle: Any, clock: WallClock, robot: str, run_id: str, node: str, adapt: bool
) -> dict[str, Any]:
    """The run's figures in report.json besides the tasks (also in run.mcap's `/report/run`)."""
    return {
        "run_id": run_id,
        "robot": robot,
        "start": node,
        "adapt": adapt,
        "clock": clock.stats(),
        "solve_ms": ms_stats(runner.ctx.follower.log.solve_s),
        "stops": runner.stops,
        "drive_commands_sent": vehicle.commands_sent,
        "localization_age_ms": ms_stats(getattr(vehicle, "localization_age_s", [])),
    }

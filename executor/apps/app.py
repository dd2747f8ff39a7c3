"""Running a mission in the simulated warehouse: from files to a finished, reported run.

`run_simulated(mission_path, scenario_path=None, ...)` loads and validates the mission against its map
and the vehicle, builds the simulator (the scenario's, or the default warehouse: the mission's map, the
forklift at the first charging node, an empty pallet exactly at every pickup node), wires the
scenario's injected faults (`sim.faults`), runs the tasks on a simulated or wall clock, journals the
progress when asked (`journal=`), and writes the report. `resume_simulated(journal)` continues an
interrupted run from its journal, in the same world. Both return a `SimRun`.

Report folder: a new run removes the previous run's files first, so a folder never mixes two runs; a
resumed run appends to its own `events.jsonl`. Files are written atomically; a write that fails after
the mission ran is recorded in `SimRun.write_errors` (the CLI exits 3 when the mission succeeded).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TextIO

from palletpilot.control.mpc import MpcConfig, MpcFollower
from palletpilot.control.vehicle import VehicleParams, load_vehicle
from palletpilot.executor.adapters.local_perception import LocalPerception
from palletpilot.executor.adapters.mcap.recording import Recorder, SimFeed, start_recording
from palletpilot.executor.adapters.stores.journal import Journal, JournalError
from palletpilot.executor.adapters.stores.report import ms_stats, summary
from palletpilot.executor.adapters.stores.trajectory_log import TrajectoryLog
from palletpilot.executor.apps.compose import (
    Outputs,
    Parts,
    build_runner,
    open_events,
    prepare_report_dir,
    run_and_finish,
    write_run_report,
)
from palletpilot.executor.core.behaviour import Settings
from palletpilot.executor.core.clock import Clock, SimClock, WallClock
from palletpilot.executor.core.controls import Controls
from palletpilot.executor.core.mission import Mission, MissionError, load_mission, validate_mission
from palletpilot.executor.core.resume import ResumeError, ResumePoint
from palletpilot.executor.core.runner import Runner
from palletpilot.executor.ports import PerceptionService
from palletpilot.geometry.errors import collect, did_you_mean, raise_problems
from palletpilot.geometry.fileio import bundled_path, validate_model
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.labels_mode import SIM_TRUTH, LabelsMode
from palletpilot.perception.segmentation import DEFAULT_MODEL, OnnxSegmenter
from palletpilot.roadmap import NodeType, Roadmap, load_map, map_vehicle_file
from palletpilot.sim.faults import FaultInjector
from palletpilot.sim.scenario import Scenario, SimError, load_scenario
from palletpilot.sim.simulator import Simulator

if TYPE_CHECKING:  # zenoh loads only for a run that uses the perception service
    from palletpilot.executor.adapters.zenoh.perception_remote import PerceptionMode

ClockKind = Literal["sim", "wall"]
Labels = Literal["model", "geometry", "fused", "truth"]
"""How perception selects its pixels in a simulated run (`perception.labels_mode`): depth geometry with the
shipped ONNX model's hints on the simulator's RGB (`fused`, the default, as on a truck), depth alone
(`geometry`), the model alone (`model`), or the simulator's exact labels in the model's place (`truth`)."""


def labels_mode(labels: str) -> LabelsMode:
    """The perception mode of a run's `labels`: `truth` is the model mode fed the simulator's labels."""
    return LabelsMode.MODEL if labels == SIM_TRUTH else LabelsMode(labels)


@dataclass
class SimRun:
    """A finished simulated run."""

    success: bool
    runner: Runner
    sim: Simulator
    summary: dict[str, Any]
    report: Path | None
    write_errors: list[str] = field(default_factory=list)


def default_scenario(mission: Mission) -> Scenario:
    """The default simulated warehouse for a mission: aligned empty pallets at its pickup nodes."""
    roadmap = load_map(mission.map_path)
    chargers = [n.id for n in roadmap.nodes() if n.type is NodeType.CHARGING]
    if not chargers:
        raise SimError(f"{mission.map_path}: no charging node to start the default warehouse from")
    pickups = [t.node for t in mission.tasks if t.type == "pickup"]
    missions = bundled_path("missions")
    sc = Scenario.model_validate(
        {
            "map": str(mission.map_path.resolve()),
            "forks": str((missions / "forks.yaml").resolve()),
            "start": chargers[0],
            "pallets": [{"node": n} for n in pickups],
        }
    )
    sc.folder = missions
    sc.source = f"{mission.map_path} (the default warehouse)"
    return sc


def _sha256(path: Path) -> str:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise ResumeError(f"{path}: cannot read: {exc.strerror or exc}") from None


def run_simulated(
    mission_path: str | Path,
    scenario_path: str | Path | None = None,
    seed: int | None = None,
    report_dir: str | Path | None = None,
    adapt: bool = True,
    settings: Settings | None = None,
    progress: TextIO | None = None,
    scenario: Scenario | None = None,
    on_start: Callable[[Runner], None] | None = None,
    clock: ClockKind = "sim",
    journal: str | Path | None = None,
    controls: Controls | None = None,
    labels: Labels = "fused",
    perception: PerceptionMode = "local",
    perception_connect: Sequence[str] = (),
    foxglove: int | None = None,
    record: bool = True,
    foxglove_host: str = "127.0.0.1",
) -> SimRun:
    """Validate and run a mission in the simulator; write the report when `report_dir` is given.

    `clock`: `sim` (simulated time, deterministic) or `wall` (real time at 20 Hz). `journal`: an SQLite
    file that records the progress for `resume_simulated`. `on_start(runner)` is called once the
    runner exists and before it runs. `controls`: pause / cancel flags (the CLI's signal handlers).
    `labels`: which pixels perception takes for the pallet, the floor and the forks (`Labels`): `fused`
    (depth geometry, with the shipped ONNX model's hints on the simulator's RGB, as on a truck),
    `geometry` (depth alone), `model` (the model alone) or `truth` (the simulator's exact labels, with its
    label noise, as the model's; for comparison).
    `perception`: `local` (in this process), `remote` (the `palletpilot perception serve` service at
    `perception_connect`) or `serve-local` (a service started for the run; `executor.perception_remote`).
    `foxglove`: also serve the run live over Foxglove WebSocket on `foxglove_host` at this port
    (`executor.recording`; a port that cannot be served raises `RecordingError` before the run). The
    report folder gets `run.mcap` unless `record` is False.
    """
    mission, roadmap, vehicle, sim, scenario = _load_run(mission_path, scenario_path, scenario, seed)
    folder = Path(report_dir).resolve() if report_dir is not None else None
    book = None
    if journal is not None:
        meta = {
            "run_id": uuid.uuid4().hex,
            "mission": str(Path(mission_path).resolve()),
            "mission_sha256": _sha256(Path(mission_path)),
            "map_sha256": _sha256(mission.map_path),
            "scenario": scenario.model_dump(mode="json"),
            "scenario_folder": str(Path(scenario.folder).resolve()),
            "seed": sim.seed,
            "report_dir": None if folder is None else str(folder),
            "adapt": adapt,
            "clock": clock,
            "labels": labels,
        }
        book = Journal.create(journal, meta)
    run_id = book.meta["run_id"] if book is not None else uuid.uuid4().hex
    if folder is not None:
        prepare_report_dir(folder, fresh=True)
    return _execute(
        mission,
        roadmap,
        vehicle,
        sim,
        scenario,
        folder,
        RunOptions(adapt, clock, labels, perception, tuple(perception_connect), foxglove, foxglove_host, record),
        settings,
        progress,
        on_start,
        book,
        controls,
        run_id,
        None,
    )


def _load_run(
    mission_path: str | Path, scenario_path: str | Path | None, scenario: Scenario | None, seed: int | None
) -> tuple[Mission, Roadmap, VehicleParams, Simulator, Scenario]:
    """Read and check every input of a run before anything moves; all problems of all files at once.

    Order: the mission's schema, its map, the scenario's schema; then the tasks against the map and the
    vehicle (from the scenario's start, or the default warehouse's charger), and the scenario against
    the map (its start, pallet nodes, overlaps) by building the simulator. A `MissionError` (or the
    first file's own error) lists every line.
    """
    where = str(mission_path)
    mission = load_mission(mission_path)  # the rest needs its map and tasks
    problems: list[str] = []
    roadmap = collect(problems, lambda: _load_mission_map(mission, where))
    if scenario is None and scenario_path is not None:
        scenario = collect(problems, lambda: load_scenario(scenario_path))
        if scenario is None:
            raise_problems(problems, MissionError)
    if roadmap is None:
        raise_problems(problems, MissionError)
    assert roadmap is not None
    vehicle_file = map_vehicle_file(mission.map_path)
    if vehicle_file is None and scenario is not None and scenario.vehicle:
        vehicle_file = scenario.path(scenario.vehicle)
    vehicle = collect(problems, lambda: load_vehicle(vehicle_file)) if vehicle_file is not None else None
    start = scenario.start if scenario is not None else _default_start(roadmap)
    if scenario is not None:
        problems += _map_mismatch(mission, scenario, scenario_path)
    elif start is None:
        problems.append(f"{mission.map_path}: no charging node to start the default warehouse from")
    if vehicle is not None:  # without one the simulator says why
        # from an unknown start (the scenario's problem) only the tasks themselves are checked
        valid_start = start if start is not None and start in roadmap else None
        collect(problems, lambda: validate_mission(mission, roadmap, vehicle, valid_start, where))
    if scenario is None and not problems:
        scenario = default_scenario(mission)
    sim = collect(problems, lambda: Simulator(scenario, seed=seed)) if scenario is not None else None
    raise_problems(problems, MissionError)
    assert sim is not None and scenario is not None
    return mission, roadmap, vehicle or sim.vehicle, sim, scenario


def _load_mission_map(mission: Mission, where: str) -> Roadmap:
    """The mission's map; a missing one named with the mission file, its `map:` field and the path it resolved to."""
    if mission.map_path.is_dir():
        raise MissionError(f"{where}: map: '{mission.map}': cannot read: Is a directory: {mission.map_path.resolve()}")
    if not mission.map_path.exists():
        folder = mission.map_path.parent
        near = did_you_mean(mission.map_path.name, [p.name for p in folder.glob("*.yaml")]) if folder.is_dir() else ""
        raise MissionError(
            f"{where}: map: '{mission.map}': no such file: {mission.map_path.resolve()} "
            f"(relative to the mission's folder){near}"
        )
    return load_map(mission.map_path)


def _default_start(roadmap: Roadmap) -> str | None:
    """Where the default warehouse starts the forklift: the map's first charging node."""
    return next((n.id for n in roadmap.nodes() if n.type is NodeType.CHARGING), None)


def _map_mismatch(mission: Mission, scenario: Scenario, scenario_path: str | Path | None) -> list[str]:
    """A problem line when the scenario's map is not the mission's (same content), else []."""
    scenario_map = scenario.path(scenario.map)
    try:
        same = _sha256(scenario_map) == _sha256(mission.map_path)
    except ResumeError:  # unreadable: the map loaders name the file
        return []
    if same:
        return []
    source = scenario_path if scenario_path is not None else "the scenario"
    return [
        f"{source}: map: {scenario_map} is not the mission's map {mission.map_path}: the simulated "
        "warehouse must be the one the mission plans on"
    ]


def resume_simulated(
    journal: str | Path,
    progress: TextIO | None = None,
    on_start: Callable[[Runner], None] | None = None,
    controls: Controls | None = None,
    settings: Settings | None = None,
) -> SimRun:
    """Continue an interrupted simulated run from its journal, in the same world; report as the run's own."""
    book = Journal.open(journal)
    if book.finished:
        book.close()
        raise JournalError(f"{journal}: the run it records has finished; nothing to resume")
    meta = book.meta
    mission_path = Path(meta["mission"])
    if _sha256(mission_path) != meta["mission_sha256"]:
        raise ResumeError(f"{mission_path}: changed since the run started; the journal cannot be resumed")
    mission = load_mission(mission_path)
    if _sha256(mission.map_path) != meta["map_sha256"]:
        raise ResumeError(f"{mission.map_path}: changed since the run started; the journal cannot be resumed")
    scenario = validate_model(meta["scenario"], Scenario, f"{journal}: scenario", ResumeError)
    scenario.folder = Path(meta["scenario_folder"])
    sim = Simulator(scenario, seed=int(meta["seed"]))
    point = ResumePoint(book.checkpoints(), resumes=book.mark_resumed())
    if point.world is None:
        raise ResumeError(f"{journal}: the checkpoint has no simulator state to continue from")
    sim.restore(point.world)
    roadmap = load_map(mission.map_path)
    vehicle_file = map_vehicle_file(mission.map_path)
    vehicle = load_vehicle(vehicle_file) if vehicle_file else sim.vehicle
    folder = Path(meta["report_dir"]) if meta.get("report_dir") else None
    if folder is not None:
        prepare_report_dir(folder, fresh=False)
    return _execute(
        mission,
        roadmap,
        vehicle,
        sim,
        scenario,
        folder,
        # journals from before the `labels` option ran on the simulator's labels
        RunOptions(bool(meta["adapt"]), meta.get("clock", "sim"), labels=meta.get("labels", "truth")),
        settings,
        progress,
        on_start,
        book,
        controls,
        str(meta["run_id"]),
        point,
    )


@dataclass(frozen=True)
class RunOptions:
    """How a simulated run runs, fixed before it starts (the arguments of `run_simulated`): `adapt`, the
    `clock` kind, the `labels` perception takes, the `perception` mode and where its service is, the live
    view's port and host (`foxglove`, None: none), and whether run.mcap is written (`record`)."""

    adapt: bool = True
    clock: ClockKind = "sim"
    labels: Labels = "fused"
    perception: PerceptionMode = "local"
    perception_connect: tuple[str, ...] = ()
    foxglove: int | None = None
    foxglove_host: str = "127.0.0.1"
    record: bool = True


def _execute(
    mission: Mission,
    roadmap: Any,
    vehicle: Any,
    sim: Simulator,
    scenario: Scenario,
    folder: Path | None,
    options: RunOptions,
    settings: Settings | None,
    progress: TextIO | None,
    on_start: Callable[[Runner], None] | None,
    book: Journal | None,
    controls: Controls | None,
    run_id: str,
    point: ResumePoint | None,
) -> SimRun:
    """The simulator's `Parts` and the run's `Outputs`, wired by `compose`; run, then the report."""
    settings = dataclasses.replace(settings or Settings(), adapt=options.adapt)
    wall = options.clock == "wall"
    injector = FaultInjector(scenario.faults, sim, realtime=wall)
    if point is not None:
        injector.skip_until(point.t)
        injector.skip_states(point.started_states())
    recorder = start_recording(
        folder if options.record else None, options.foxglove, wall, point is not None, options.foxglove_host
    )
    if recorder is not None and recorder.port is not None and progress is not None:
        progress.write(f"foxglove: live on ws://{options.foxglove_host}:{recorder.port}\n")
    log: TrajectoryLog | None = None

    def step(dt: float) -> None:
        if recorder is not None:
            recorder.tick()  # the state the runner saw this tick, before the world moves on
        sim.step(dt)
        injector.poll(sim.time)
        if log is not None:
            pose = sim.true_pose
            log.row(sim.time, pose.x, pose.y, pose.yaw, sim.speed, sim.fork_height, sim.load_detected())

    with contextlib.ExitStack() as stack:
        if recorder is not None:  # the file finished, the port freed, however the run ends
            stack.callback(recorder.close)
        perception, grab = _perception(sim, injector, recorder, stack, options, camera=not settings.paper_baseline)
        start_s = point.t if point is not None else 0.0
        clock: Clock = WallClock(step=step, start_s=start_s) if wall else SimClock(step, start_s=start_s)
        events = open_events(folder, stack, append=point is not None)
        if folder is not None:
            log = TrajectoryLog(folder / "trajectory.csv", resume_t=point.t if point else None)
            stack.callback(log.close)
        if book is not None:
            stack.callback(book.close)
        outputs = Outputs(events, book, recorder)
        parts = Parts(
            mission, roadmap, injector.vehicle, perception, grab, clock, vehicle, sim.forks, scenario.start,
            _follower(vehicle, wall, injector), (injector.observe,),
        )  # fmt: skip
        world = sim.snapshot if book is not None else None
        runner = build_runner(parts, outputs, settings, progress, controls, point, world, SimFeed(sim))
        start = {"run_id": run_id, "seed": sim.seed, "clock": options.clock} if point is None else None
        success, write_errors = run_and_finish(
            runner, outputs, lambda: _extra(sim, clock, options.adapt, run_id, point, injector, runner), start, on_start
        )
    if recorder is not None:
        write_errors += recorder.errors
    extra = _extra(sim, clock, options.adapt, run_id, point, injector, runner)
    truth = [(p.T_world_pallet).to_se2() for p in sim.pallets]
    initial = [(p.initial if p.initial is not None else p.T_world_pallet).to_se2() for p in sim.pallets]
    report = write_run_report(folder, runner, success, extra, write_errors, truth, sim.obstacle_outlines(), initial)
    return SimRun(success, runner, sim, summary(success, runner.results), report, write_errors)


def _follower(vehicle: VehicleParams, wall: bool, injector: FaultInjector) -> MpcFollower:
    """The MPC path follower. Simulated time waits for each solve: no wall-clock deadline, so the machine's
    load cannot change a seeded run (the report gives the solve times). On a wall clock a late solve brakes."""
    deadline = MpcConfig().solve_deadline_s if wall else None
    follower = MpcFollower(vehicle, MpcConfig(solve_deadline_s=deadline))
    follower.step_fault = injector.step_failure
    return follower


def _perception(
    sim: Simulator,
    injector: FaultInjector,
    recorder: Recorder | None,
    stack: contextlib.ExitStack,
    options: RunOptions,
    camera: bool = True,
) -> tuple[PerceptionService | None, Callable[[], FrameBundle]]:
    """Perception of a simulated run and the camera's `grab`: in process, or the service (`remote`,
    `serve-local`), stopped with `stack` however the run ends; see `_local_perception`. None only without
    `camera` (the bench's paper baseline): `--no-adapt` keeps the camera's checks."""
    perception, grab = _local_perception(sim, injector, recorder, camera, options.labels, options.perception)
    if camera and options.perception != "local":
        from palletpilot.executor.adapters.zenoh.perception_remote import remote_perception

        service = remote_perception(
            options.perception,
            options.perception_connect,
            sim.forks,
            sim.pallet_type,
            DEFAULT_MODEL,
            labels=labels_mode(options.labels),
        )
        perception = injector.perception(stack.enter_context(service))
    return perception, grab


def _local_perception(
    sim: Simulator,
    injector: FaultInjector,
    recorder: Recorder | None,
    camera: bool,
    labels: Labels,
    perception_mode: PerceptionMode,
) -> tuple[PerceptionService | None, Callable[[], FrameBundle]]:
    """In-process perception of a simulated run (None without `camera` or with a service) and the camera's
    `grab`: without the simulator's labels unless `labels` is `truth`, segmented by the shipped model in
    this process for `fused` and `model` (a service segments with its own)."""
    perception: PerceptionService | None = None
    grab: Callable[[], FrameBundle] = injector.grab
    if not camera:
        return perception, grab
    segmenter = None
    if labels != SIM_TRUTH:  # the truck's view: no labels from the simulator
        grab = _without_labels(injector.grab)
        if labels != LabelsMode.GEOMETRY and perception_mode == "local":  # RGB through the shipped model
            segmenter = OnnxSegmenter(DEFAULT_MODEL)
    if recorder is not None and segmenter is not None:  # run.mcap: the labels perception segmented
        segmenter = recorder.wrap_segmenter(segmenter)
    if perception_mode == "local":
        local = LocalPerception(sim.forks, sim.pallet_type, segmenter=segmenter, labels=labels_mode(labels))
        perception = injector.perception(local)
    return perception, grab


def _without_labels(grab: Callable[[], FrameBundle]) -> Callable[[], FrameBundle]:
    """`grab` whose frames carry no labels: perception must segment the RGB itself."""

    def frame() -> FrameBundle:
        return dataclasses.replace(grab(), labels=None)

    return frame


def _extra(
    sim: Simulator,
    clock: Clock,
    adapt: bool,
    run_id: str,
    point: ResumePoint | None,
    injector: FaultInjector,
    runner: Runner,
) -> dict[str, Any]:
    """The run's figures in report.json besides the tasks (also in run.mcap's `/report/run`)."""
    return {
        "run_id": run_id,
        "seed": sim.seed,
        "adapt": adapt,
        "simulated_s": round(sim.time, 2),
        "resumed": 0 if point is None else point.resumes,
        "clock": clock.stats(),
        "solve_ms": ms_stats(runner.ctx.follower.log.solve_s),
        "collisions": sim.collisions,
        "stops": runner.stops,
        "faults_injected": injector.injected,
        "pallets": sim.pallet_records(),
    }

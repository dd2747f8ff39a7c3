"""The one way a run is put together, for every composition root: `run` and `test` (`executor.apps.app`,
the simulator), `robot` (`executor.apps.robot`, a truck over ROS 2) and every leg of the VDA 5050 AGV
(`executor.apps.vda5050.agv`: its order's planner, the heading the truck stands with).

A backend brings its `Parts` (the vehicle, perception, the camera's `grab`, the clock, the path follower,
its observers); the run's `Outputs` are its report folder's events file, its journal and its recorder.
`build_runner` wires them in one order: the recorder wraps the vehicle and the camera and subscribes as a
`RunObserver` before the runner exists, so nothing is swapped into a runner after it is built.
`run_and_finish` logs `run_start`, runs, and finishes the recording and the journal in one order;
`write_run_report` writes report.json and trajectory.png.

Public API: `Parts`, `Outputs`, `prepare_report_dir`, `open_events`, `build_runner`, `run_and_finish`,
`write_run_report`, `first_reason`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from palletpilot.executor.adapters.stores.report import REPORT_FILES, write_report
from palletpilot.executor.core.behaviour import Settings
from palletpilot.executor.core.controls import Controls
from palletpilot.executor.core.mission import Mission
from palletpilot.executor.core.resume import Checkpointer, ResumePoint
from palletpilot.executor.core.runner import Runner
from palletpilot.executor.ports import Clock, PerceptionService, RunObserver, VehiclePort
from palletpilot.geometry import SE2, OutputError, PalletpilotError

if TYPE_CHECKING:
    import numpy as np

    from palletpilot.control.follower import Follower
    from palletpilot.control.vehicle import VehicleParams
    from palletpilot.executor.adapters.mcap.recording import Recorder, SimFeed
    from palletpilot.executor.adapters.stores.journal import Journal
    from palletpilot.perception.frames import FrameBundle
    from palletpilot.perception.specs import ForkGeometry
    from palletpilot.roadmap import Planner, Roadmap


@dataclass(frozen=True)
class Parts:
    """What a backend brings to a run (SI units, world frame): the mission on its roadmap, the vehicle and
    its parameters, perception and the camera's `grab`, the clock, the forks, the node the truck starts
    at, the path follower, and the backend's own observers (the simulator's fault injector). `planner`:
    how the tasks' routes are planned (None: the roadmap's own `Planner`); `start_heading`: the truck's
    yaw at `start_node` (rad; None: the node's yaw)."""

    mission: Mission
    roadmap: Roadmap
    vehicle: VehiclePort
    perception: PerceptionService | None
    grab: Callable[[], FrameBundle]
    clock: Clock
    params: VehicleParams
    forks: ForkGeometry
    start_node: str
    follower: Follower
    observers: tuple[RunObserver, ...] = ()
    planner: Planner | None = None
    start_heading: float | None = None


@dataclass(frozen=True)
class Outputs:
    """Where a run leaves its trace: `events` (events.jsonl, open), the SQLite `book` (journal), the MCAP
    `recorder`; each None when the run has none."""

    events: TextIO | None = None
    book: Journal | None = None
    recorder: Recorder | None = None


def prepare_report_dir(folder: Path, fresh: bool) -> None:
    """Create the report folder; a fresh run (not a resumed one) removes the previous run's report files
    first, so a folder never mixes two runs. `OutputError` (one line) when it cannot."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if fresh:
            for name in REPORT_FILES:
                with contextlib.suppress(FileNotFoundError):
                    (folder / name).unlink()
    except OSError as exc:
        raise OutputError(f"{folder}: cannot prepare the report folder: {exc.strerror or exc}") from None


def open_events(folder: Path | None, stack: contextlib.ExitStack, append: bool = False) -> TextIO | None:
    """`folder/events.jsonl` open for the run (appended to on a resume), closed with `stack`; None without a
    folder. An unwritable file is an `OutputError` (one line)."""
    if folder is None:
        return None
    try:
        return stack.enter_context((folder / "events.jsonl").open("a" if append else "w"))
    except OSError as exc:
        raise OutputError(f"{folder / 'events.jsonl'}: cannot write: {exc.strerror or exc}") from None


def build_runner(
    parts: Parts,
    outputs: Outputs,
    settings: Settings,
    progress: TextIO | None = None,
    controls: Controls | None = None,
    resume: ResumePoint | None = None,
    world: Callable[[], dict[str, Any]] | None = None,
    sim: SimFeed | None = None,
) -> Runner:
    """The runner of `parts`, recorded and journalled by `outputs`: the recorder wraps the vehicle and the
    camera and observes the events from the start; the journal gets the checkpoints (`world`: the
    simulator's state with each). `resume`: continue from this checkpoint. A recorder in a session (the
    AGV's, one runner per leg) wrapped the vehicle and the camera once when the session started: the
    parts bring those wrappers, and the recorder only observes this runner."""
    vehicle, grab, observers = parts.vehicle, parts.grab, list(parts.observers)
    recorder = outputs.recorder
    if recorder is not None:
        if not recorder.in_session:
            vehicle = recorder.wrap_vehicle(vehicle)
            grab = recorder.wrap_grab(grab)
        observers.append(recorder.on_event)
    runner = Runner(
        parts.mission,
        parts.roadmap,
        vehicle,
        parts.perception,
        grab,
        parts.clock,
        parts.params,
        parts.forks,
        parts.start_node,
        settings=settings,
        follower=parts.follower,
        events=outputs.events,
        progress=progress,
        controls=controls,
        checkpointer=Checkpointer(outputs.book, world) if outputs.book is not None else None,
        resume=resume,
        listeners=observers,
        planner=parts.planner,
        start_heading=parts.start_heading,
    )
    if recorder is not None:
        recorder.attach(runner, sim)
    return runner


def first_reason(runner: Runner) -> str | None:
    """The reason of the run's first failed task, None when none failed."""
    return next((r.reason for r in runner.results if r.reason), None)


def run_and_finish(
    runner: Runner,
    outputs: Outputs,
    extra: Callable[[], dict[str, Any]],
    start: dict[str, Any] | None,
    on_start: Callable[[Runner], None] | None = None,
) -> tuple[bool, list[str]]:
    """Log `run_start` with `start` (None: a resumed run logs none), call `on_start(runner)`, run, then
    finish the recording (with `extra()`, the report's figures) and the journal. Returns the success and
    the outputs that could not be written (one line each); never raises for those."""
    if start is not None:
        runner.log("run_start", **start)
    if on_start is not None:
        on_start(runner)
    success = runner.run()
    write_errors: list[str] = []
    if outputs.recorder is not None:
        outputs.recorder.finish(success, extra())
    if outputs.book is not None:
        try:
            outputs.book.finish(success, None if success else first_reason(runner))
        except PalletpilotError as exc:
            write_errors.append(str(exc))
    return success, write_errors


def write_run_report(
    folder: Path | None,
    runner: Runner,
    success: bool,
    extra: dict[str, Any],
    write_errors: list[str],
    truth_pallets: list[SE2] | None = None,
    obstacles: list[tuple[str, str, np.ndarray]] | None = None,
    truth_initial: list[SE2] | None = None,
) -> Path | None:
    """report.json and trajectory.png of a finished run in `folder` (None: no report); returns the JSON's
    path, or None with the reason added to `write_errors` when it could not be written. `truth_pallets`
    (at the end), `truth_initial` (at the start), `obstacles` (world frame): what only a simulator knows."""
    if folder is None:
        return None
    try:
        return write_report(
            folder,
            runner.mission.name,
            success,
            runner.results,
            runner.ctx.roadmap,
            runner.trajectory,
            runner.ctx.memory.planned_paths,
            truth_pallets=truth_pallets,
            extra=extra,
            obstacles=obstacles,
            truth_initial=truth_initial,
        )
    except OutputError as exc:
        write_errors.append(str(exc))
        return None

"""Checkpoints of a running mission and resuming from them (with `executor.journal`).

The runner writes a checkpoint at the start of every state and after every finished task: where the
mission stands (task index, state), the task memory (`TaskMemory.to_json`, under `ctx`: node, heading,
attempts, the calibration, the last pallet estimate, the route that reached the pre-pallet node, the
temporary nodes of re-plans with the node their curve joins and the nodes backed along to it; what it
leaves out and why: `NOT_JOURNALLED`), whether the forks carry a load, the finished
tasks' results, the trajectory and planned paths since the previous checkpoint, and, in the
simulator, the whole world (`Simulator.snapshot`). Each is committed before the state starts acting.

A resume re-enters the checkpointed state with the memory it had: a state is a safe point because it
starts from a standing vehicle (each state's work begins with the truck's own stop or drive commands).
So a pickup resumed after its lift continues with the load on the forks and never lifts again, and a
delivery resumed knows the load is on the forks. In the simulator the world is restored from the same
checkpoint; on a robot the truck must stand where the checkpoint says (`check_pose`).

Public API: `Checkpointer`, `ResumePoint`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from palletpilot.executor.core.results import TaskResult
from palletpilot.geometry import SE2, PalletpilotError

if TYPE_CHECKING:
    from palletpilot.executor.adapters.stores.journal import Journal
    from palletpilot.executor.core.runner import Runner

RESUME_POSE_TOLERANCE_M = 0.25
RESUME_YAW_TOLERANCE_DEG = 10.0


class ResumeError(PalletpilotError):
    """The journal cannot be resumed here (the truck is elsewhere, the files changed); one line."""


class Checkpointer:
    """Writes the runner's checkpoints to a journal; `world()` adds the simulator's state when given."""

    def __init__(self, journal: Journal, world: Callable[[], dict[str, Any]] | None = None) -> None:
        self.journal = journal
        self.world = world
        self._trajectory_n = 0
        self._planned_n = 0

    def skip_history(self, runner: Runner) -> None:
        """After a resume: the restored trajectory and paths are already in the journal."""
        self._trajectory_n = len(runner.trajectory)
        self._planned_n = len(runner.ctx.memory.planned_paths)

    def checkpoint(self, runner: Runner, index: int, state: str | None, current: TaskResult | None) -> None:
        """Commit one checkpoint (see the module docstring)."""
        memory = runner.ctx.memory
        pose = runner.vehicle.localization()
        doc = {
            "t": runner.clock.now(),
            "paused_total_s": runner.paused_total_s,
            "task": index,
            "state": state,
            "pose": [pose.x, pose.y, pose.yaw],
            "load": bool(runner.vehicle.load_detected()),
            "ctx": memory.to_json(),
            "results": [r.to_json() for r in runner.results],
            "current": None if current is None else current.to_json(),
            "stops": runner.stops,
            "trajectory": runner.trajectory[self._trajectory_n :],
            "planned": memory.planned_paths[self._planned_n :],
            "world": None if self.world is None else self.world(),
        }
        self.journal.checkpoint(doc)
        self._trajectory_n = len(runner.trajectory)
        self._planned_n = len(memory.planned_paths)


class ResumePoint:
    """Where an interrupted run continues: the last checkpoint, with the history before it."""

    def __init__(self, checkpoints: list[dict[str, Any]], resumes: int) -> None:
        if not checkpoints:
            raise ResumeError("the journal has no checkpoint yet: start the mission again instead")
        self.checkpoints = checkpoints
        self.last = checkpoints[-1]
        self.resumes = resumes

    @property
    def task_index(self) -> int:
        """The task to continue."""
        return int(self.last["task"])

    @property
    def state(self) -> str | None:
        """The state to re-enter (None: the task starts afresh)."""
        state = self.last["state"]
        return None if state is None else str(state)

    @property
    def t(self) -> float:
        """The runner's clock at the checkpoint (s)."""
        return float(self.last["t"])

    @property
    def world(self) -> dict[str, Any] | None:
        """The simulator's state at the checkpoint, if it was recorded."""
        world = self.last.get("world")
        return world if isinstance(world, dict) else None

    def started_states(self) -> list[tuple[int, str]]:
        """(task index, state) of every state started before the interruption, the re-entered one included."""
        started = [(int(r["index"]), str(st["state"])) for r in self.last["results"] for st in r["states"]]
        current = self.last["current"] or {}
        started += [(self.task_index, str(st["state"])) for st in current.get("states", [])]
        if self.state is not None:
            started.append((self.task_index, self.state))
        return started

    def check_pose(self, T_world_forklift: SE2, load: bool) -> None:
        """A real truck must stand where the checkpoint says, with the same load; else `ResumeError`."""
        x, y, yaw = self.last["pose"]
        dist = math.hypot(T_world_forklift.x - x, T_world_forklift.y - y)
        dyaw = abs(math.degrees(math.remainder(T_world_forklift.yaw - yaw, math.tau)))
        if dist > RESUME_POSE_TOLERANCE_M or dyaw > RESUME_YAW_TOLERANCE_DEG:
            raise ResumeError(
                f"the truck is {dist:.2f} m and {dyaw:.1f} deg from where the journal left it "
                f"(limits {RESUME_POSE_TOLERANCE_M} m, {RESUME_YAW_TOLERANCE_DEG} deg): bring it back or start anew"
            )
        if bool(self.last["load"]) != bool(load):
            had = "a load" if self.last["load"] else "no load"
            raise ResumeError(f"the journal left the forks with {had}, the load sensor says otherwise")

    def restore_runner(self, runner: Runner) -> None:
        """Finished tasks, history and mission-wide memory into a new runner."""
        last, memory = self.last, runner.ctx.memory
        runner.results = [TaskResult.from_json(r) for r in last["results"]]
        runner.trajectory = [(t, x, y, yaw) for cp in self.checkpoints for t, x, y, yaw in cp["trajectory"]]
        memory.planned_paths = [[(x, y) for x, y in path] for cp in self.checkpoints for path in cp["planned"]]
        runner.stops = list(last["stops"])
        runner.paused_total_s = float(last["paused_total_s"])
        memory.restore_position(last["ctx"])
        memory.last_motion_s = self.t
        if runner.checkpointer is not None:
            runner.checkpointer.skip_history(runner)

    def restore_task(self, runner: Runner, result: TaskResult) -> None:
        """The interrupted task's memory and record, its temporary nodes back in the overlay."""
        from palletpilot.executor.core.pickup import add_temporary_nodes

        current = self.last["current"] or {}
        result.start_s = float(current.get("start_s", self.t))
        result.states = list(current.get("states", []))
        result.record.update(current.get("record", {}))
        for spec in runner.ctx.memory.restore_task(self.last["ctx"]):
            add_temporary_nodes(runner.ctx, spec)
        runner.log("task_resumed", task=result.index, state=self.state, attempts=runner.ctx.memory.attempts)

"""Task state machines: states and transitions as data, and the behaviour of every state.

Every task type is a `transitions` state machine built from `TASK_SPECS` (states, transitions); the
behaviours live in `executor.driving` (moving the truck) and `executor.pickup` (the adaptive Pickup's
perception, re-plan and safety check), on the base of `executor.behaviour`. Every state has a timeout;
any failure ends the task in `failed` with a reason code (`executor.errors`), and the runner stops the
vehicle.

The adaptive Pickup follows ARCHITECTURE.md: drive to the pre-pallet node, calibrate, raise the forks,
estimate the pallet; when misaligned, lower the forks, back off to the node before the pre-pallet
node, add temporary pallet and pre-pallet nodes from the estimate joined by a feasible curve (to that
node, or when none fits, to one further back along the route: `Settings.replan_back_nodes`; when no
node gives one curve, a manoeuvre of forward and reverse moves: `executor.core.manoeuvre`), approach
the new pre-pallet node (backing to the further node first) and repeat (at most `max_attempts`
estimates); then the proximity safety check, enter, lift, reverse out, return to the roadmap (through
the node the temporary nodes are joined to) and remove the temporary nodes. `--no-adapt` does not
re-plan but keeps the camera's checks (calibrate, estimate, refuse a pallet the forks do not fit as it
stands, the entry volume, the safety check); the paper's original Pickup (no camera, beams only) is
`pickup_paper`, a baseline for `bench missions` that no truck runs.

Public API: `TASK_SPECS`, `TaskSpec`, `build_machine`, `mermaid`, `behaviours`, and re-exported for
callers: `Settings`, `Context`, `Behaviour`, `TaskFailed` and the reason codes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from palletpilot.executor.core.behaviour import Behaviour, Context, Settings, TemporaryNodes
from palletpilot.executor.core.driving import Charge, FollowRoute, ReturnToRoadmap, SetForks, Wait, travel_height
from palletpilot.executor.core.entry import CheckVolume, entry_pocket_fit, entry_volume, slot_volume
from palletpilot.executor.core.errors import (
    CALIBRATION_FAILED,
    CANCELLED,
    COLLISION,
    CONTROLLER_ERROR,
    INTERNAL_ERROR,
    NO_FEASIBLE_APPROACH,
    NO_LOAD,
    NO_ROUTE,
    PALLET_NOT_FOUND,
    PALLET_NOT_LIFTED,
    PATH_BLOCKED,
    SAFETY_CHECK_FAILED,
    SENSOR_TIMEOUT,
    SLOT_OCCUPIED,
    STILL_MISALIGNED,
    TIMEOUT,
    VEHICLE_FAULT,
    TaskFailed,
)
from palletpilot.executor.core.manoeuvre import exit_route
from palletpilot.executor.core.mission import WaitTask
from palletpilot.executor.core.pickup import CalibrateCamera, EstimatePallet, Replan, SafetyCheck, approach_route
from palletpilot.executor.ports.vocabulary import Outcome
from palletpilot.roadmap.planner import Route

__all__ = [
    "CALIBRATION_FAILED",
    "CANCELLED",
    "COLLISION",
    "CONTROLLER_ERROR",
    "INTERNAL_ERROR",
    "NO_FEASIBLE_APPROACH",
    "NO_LOAD",
    "NO_ROUTE",
    "PALLET_NOT_FOUND",
    "PALLET_NOT_LIFTED",
    "PATH_BLOCKED",
    "PICKUP_KINDS",
    "SAFETY_CHECK_FAILED",
    "SENSOR_TIMEOUT",
    "SLOT_OCCUPIED",
    "STILL_MISALIGNED",
    "TASK_SPECS",
    "TIMEOUT",
    "VEHICLE_FAULT",
    "Behaviour",
    "Context",
    "Settings",
    "TaskFailed",
    "TaskSpec",
    "TemporaryNodes",
    "behaviours",
    "build_machine",
    "mermaid",
    "pickup_kind",
]

# -- the machines as data ---------------------------------------------------------------------------


@dataclass(frozen=True)
class TaskSpec:
    """States (in order; `succeeded` and `failed` are final) and transitions (trigger, source, dest)."""

    states: tuple[str, ...]
    transitions: tuple[tuple[str, str, str], ...]


_FINAL = (Outcome.SUCCEEDED.value, Outcome.FAILED.value)
TASK_SPECS: dict[str, TaskSpec] = {
    "pickup": TaskSpec(
        (
            "drive_to_pre_pallet",
            "calibrate",
            "raise_forks",
            "estimate_pallet",
            "lower_forks",
            "back_off",
            "replan",
            "approach",
            "check_entry",
            "safety_check",
            "enter",
            "lift",
            "reverse_out",
            "lower_to_travel",
            "return_to_roadmap",
            *_FINAL,
        ),
        (
            ("done", "drive_to_pre_pallet", "calibrate"),
            ("done", "calibrate", "raise_forks"),
            ("done", "raise_forks", "estimate_pallet"),
            ("aligned", "estimate_pallet", "check_entry"),
            ("misaligned", "estimate_pallet", "lower_forks"),
            ("done", "lower_forks", "back_off"),
            ("done", "back_off", "replan"),
            ("done", "replan", "approach"),
            ("done", "approach", "calibrate"),
            ("done", "check_entry", "safety_check"),
            ("done", "safety_check", "enter"),
            ("done", "enter", "lift"),
            ("done", "lift", "reverse_out"),
            ("done", "reverse_out", "lower_to_travel"),
            ("done", "lower_to_travel", "return_to_roadmap"),
            ("done", "return_to_roadmap", "succeeded"),
            ("fail", "*", "failed"),
        ),
    ),
    # `--no-adapt`: no re-plan, but the camera still looks before the forks go in: calibrate, estimate,
    # and enter only a pallet the forks fit as it stands (`EstimatePallet` refuses a misaligned one).
    "pickup_no_adapt": TaskSpec(
        (
            "drive_to_pre_pallet",
            "calibrate",
            "raise_forks",
            "estimate_pallet",
            "check_entry",
            "safety_check",
            "enter",
            "lift",
            "reverse_out",
            "lower_to_travel",
            *_FINAL,
        ),
        (
            ("done", "drive_to_pre_pallet", "calibrate"),
            ("done", "calibrate", "raise_forks"),
            ("done", "raise_forks", "estimate_pallet"),
            ("aligned", "estimate_pallet", "check_entry"),
            ("done", "check_entry", "safety_check"),
            ("done", "safety_check", "enter"),
            ("done", "enter", "lift"),
            ("done", "lift", "reverse_out"),
            ("done", "reverse_out", "lower_to_travel"),
            ("done", "lower_to_travel", "succeeded"),
            ("fail", "*", "failed"),
        ),
    ),
    # The paper's original Pickup, beams only, no camera: a baseline for `bench missions` alone
    # (`Settings.paper_baseline`); no command that drives a truck (run, robot, agv) reaches it.
    "pickup_paper": TaskSpec(
        (
            "drive_to_pre_pallet",
            "raise_forks",
            "safety_check",
            "enter",
            "lift",
            "reverse_out",
            "lower_to_travel",
            *_FINAL,
        ),
        (
            ("done", "drive_to_pre_pallet", "raise_forks"),
            ("done", "raise_forks", "safety_check"),
            ("done", "safety_check", "enter"),
            ("done", "enter", "lift"),
            ("done", "lift", "reverse_out"),
            ("done", "reverse_out", "lower_to_travel"),
            ("done", "lower_to_travel", "succeeded"),
            ("fail", "*", "failed"),
        ),
    ),
    "delivery": TaskSpec(
        ("drive_to_pre_drop", "raise_forks", "check_slot", "enter", "lower", "reverse_out", "lower_to_travel", *_FINAL),
        (
            ("done", "drive_to_pre_drop", "raise_forks"),
            ("done", "raise_forks", "check_slot"),
            ("done", "check_slot", "enter"),
            ("done", "enter", "lower"),
            ("done", "lower", "reverse_out"),
            ("done", "reverse_out", "lower_to_travel"),
            ("done", "lower_to_travel", "succeeded"),
            ("fail", "*", "failed"),
        ),
    ),
    "move": TaskSpec(("drive", *_FINAL), (("done", "drive", "succeeded"), ("fail", "*", "failed"))),
    "charge": TaskSpec(
        ("drive", "charge", *_FINAL),
        (("done", "drive", "charge"), ("done", "charge", "succeeded"), ("fail", "*", "failed")),
    ),
    "wait": TaskSpec(("wait", *_FINAL), (("done", "wait", "succeeded"), ("fail", "*", "failed"))),
}


PICKUP_KINDS = ("pickup", "pickup_no_adapt", "pickup_paper")
"""The task machines of a mission's `pickup`: adaptive, `--no-adapt` (camera checks, no re-plan) and the
paper's beams-only baseline (`bench missions` only); `pickup_kind` picks one."""


def pickup_kind(settings: Settings) -> str:
    """The machine a mission's `pickup` task runs under `settings`: `pickup` when it adapts, else
    `pickup_no_adapt` (the camera's checks stay), `pickup_paper` only for the bench's baseline."""
    if settings.adapt:
        return "pickup"
    return "pickup_paper" if settings.paper_baseline else "pickup_no_adapt"


class MachineModel:
    """The object a task's `transitions` machine drives; `state` names the current state."""

    state: str


def build_machine(task: str, initial: str | None = None) -> MachineModel:
    """A fresh machine of a task type from `TASK_SPECS`, in its first state or `initial` (a resume)."""
    from transitions import Machine

    spec = TASK_SPECS[task]
    model = MachineModel()
    Machine(
        model=model,
        states=list(spec.states),
        transitions=[{"trigger": t, "source": s, "dest": d} for t, s, d in spec.transitions],
        initial=initial or spec.states[0],
        auto_transitions=False,
    )
    return model


def mermaid(task: str) -> str:
    """The state diagram of a task type as Mermaid `stateDiagram-v2` text, from its `TaskSpec`: the first
    state is entered from the start, every transition is drawn once with its trigger, a `fail` from `*`
    leaves every state that is not final, and the final states end the task."""
    spec = TASK_SPECS[task]
    lines = ["stateDiagram-v2", f"    [*] --> {spec.states[0]}"]
    for trigger, source, dest in spec.transitions:
        sources = [st for st in spec.states if st not in _FINAL] if source == "*" else [source]
        lines += [f"    {src} --> {dest}: {trigger}" for src in sources]
    lines += [f"    {final} --> [*]" for final in _FINAL if final in spec.states]
    return "\n".join(lines) + "\n"


def _pallet_height(ctx: Context) -> float:
    task = ctx.memory.load_task()
    return ctx.roadmap.node(task.node).height if task.height is None else task.height


def _check_lifted(ctx: Context) -> None:
    if not ctx.vehicle.load_detected():
        raise TaskFailed(PALLET_NOT_LIFTED, "the forks were raised but carry no load")


def _check_loaded(ctx: Context) -> None:
    if not ctx.vehicle.load_detected():
        raise TaskFailed(NO_LOAD, "a delivery with empty forks: the load sensor feels no load")


def _check_released(ctx: Context) -> None:
    if ctx.vehicle.load_detected():
        raise TaskFailed(PALLET_NOT_LIFTED, "the forks were lowered but still carry the load")


def _edge_route(start: Callable[[Context], str], end: Callable[[Context], str]) -> Callable[[Context], Route]:
    def route(ctx: Context) -> Route:
        return Route([start(ctx), end(ctx)], [ctx.roadmap.edge(start(ctx), end(ctx))])

    return route


def behaviours(task_type: str, settings: Settings) -> dict[str, Callable[[], Behaviour]]:
    """Factories of the behaviour of every non-final state of a task type."""
    s = settings
    pre = lambda ctx: ctx.memory.pre_node  # noqa: E731
    pallet = lambda ctx: ctx.memory.pallet_node  # noqa: E731
    before = lambda ctx: ctx.memory.node_before or ""  # noqa: E731
    entry_height = lambda ctx: _pallet_height(ctx) + s.fork_clearance  # noqa: E731
    if task_type in PICKUP_KINDS:
        table: dict[str, Callable[[], Behaviour]] = {
            "drive_to_pre_pallet": lambda: FollowRoute(pre),
            "raise_forks": lambda: SetForks(entry_height),
            "safety_check": SafetyCheck,
            "enter": lambda: FollowRoute(pallet, via=_edge_route(pre, pallet)),
            "lift": lambda: SetForks(lambda ctx: entry_height(ctx) + s.lift_delta, check=_check_lifted),
            "reverse_out": lambda: FollowRoute(pre, via=_edge_route(pallet, pre)),
            "lower_to_travel": lambda: SetForks(travel_height),
        }
        if task_type != "pickup_paper":  # the camera looks before the forks go in
            table.update(
                {
                    "calibrate": CalibrateCamera,
                    "estimate_pallet": EstimatePallet,
                    "check_entry": lambda: CheckVolume(
                        entry_volume, PATH_BLOCKED, "the pallet's entry volume", fit=entry_pocket_fit
                    ),
                }
            )
        if task_type == "pickup":
            table.update(
                {
                    "lower_forks": lambda: SetForks(lambda ctx: ctx.params.mast.travel_height_empty),
                    "back_off": lambda: FollowRoute(before, via=exit_route),
                    "replan": Replan,
                    "approach": lambda: FollowRoute(pre, via=approach_route),
                    "return_to_roadmap": ReturnToRoadmap,
                }
            )
        return table
    if task_type == "delivery":
        carry = lambda ctx: _pallet_height(ctx) + s.fork_clearance + s.lift_delta  # noqa: E731
        return {
            "drive_to_pre_drop": lambda: FollowRoute(pre, check=_check_loaded),
            "raise_forks": lambda: SetForks(carry),
            "check_slot": lambda: CheckVolume(slot_volume, SLOT_OCCUPIED, "the drop slot"),
            "enter": lambda: FollowRoute(pallet, via=_edge_route(pre, pallet)),
            "lower": lambda: SetForks(entry_height, check=_check_released),
            "reverse_out": lambda: FollowRoute(pre, via=_edge_route(pallet, pre)),
            "lower_to_travel": lambda: SetForks(travel_height),
        }
    if task_type == "move":
        return {"drive": lambda: FollowRoute(lambda ctx: ctx.memory.node_task().node)}
    if task_type == "charge":
        return {
            "drive": lambda: FollowRoute(lambda ctx: ctx.memory.node_task().node),
            "charge": Charge,
        }
    if task_type == "wait":
        return {"wait": lambda: Wait(lambda ctx: ctx.memory.task_of(WaitTask).seconds)}
    raise KeyError(task_type)

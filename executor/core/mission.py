"""Mission files (YAML) and their validation against the map, before anything moves.

```yaml
name: pick up a misplaced pallet and deliver it
map: warehouse.yaml               # relative to this file
pallet_type: eur                  # optional: the pallets this mission handles (a built-in name or a
                                  # pallet type file relative to this file; default eur)
return_on_failure: true           # optional: after a failed task wait at the nearest parking node
blocked_wait_s: 30                # optional: a blocked path holds a task this long (s), then path_blocked
tasks:
  - {type: pickup, node: floor_b2}              # height (m): default the pallet node's height
  - {type: pickup, node: floor_a1, pallet_type: industrial}   # this pallet's own type
  - {type: delivery, node: drop, height: 0.0}   # put the pallet down at a drop (or pallet) node
  - {type: move, node: a_top, return_on_failure: false}   # per task (pickup, delivery, move)
  - {type: charge, node: charger, minutes: 5}   # or until_level: 0.9 (needs a battery reading)
  - {type: wait, seconds: 10}
```

Validation reports every problem, one line each, naming the task: unknown node, a node of the wrong
type for the task, a height outside the mast's range, a node that cannot be reached from where
the previous task leaves the forklift, and a pallet type that is neither built in nor a valid file.

The pallet type is what the Pickup is told to look for (a pallet of another type is refused,
`pallet_not_found`) and what it aligns the forks with; a delivery puts down the pallet of the last
pickup (or, loaded at the start, the mission's type).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, model_validator

from palletpilot.control.vehicle import VehicleParams
from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.errors import did_you_mean, raise_problems
from palletpilot.geometry.fileio import FileModel, load_yaml_model
from palletpilot.perception.specs import PalletType, pallet_type_in
from palletpilot.roadmap import NodeType, Planner, Roadmap, RoadmapError


class MissionError(PalletpilotError):
    """A mission that cannot be run as written; one line per problem."""


class _Task(FileModel):
    pass


_RETURN_ON_FAILURE = Field(
    None, description="after this task fails, wait at the nearest parking node; default: the mission's"
)


class PickupTask(_Task):
    """Pick up the pallet at a pallet node (adapting to where it really is)."""

    type: Literal["pickup"]
    node: str
    height: float | None = Field(None, ge=0.0, le=20.0, description="pallet height (m); default: the node's")
    pallet_type: str | None = Field(None, min_length=1, max_length=4096, description="default: the mission's")
    return_on_failure: bool | None = _RETURN_ON_FAILURE


class DeliveryTask(_Task):
    """Put the carried pallet down at a drop or pallet node."""

    type: Literal["delivery"]
    node: str
    height: float | None = Field(None, ge=0.0, le=20.0, description="drop height (m); default: the node's")
    return_on_failure: bool | None = _RETURN_ON_FAILURE


class MoveTask(_Task):
    """Drive to a node."""

    type: Literal["move"]
    node: str
    return_on_failure: bool | None = _RETURN_ON_FAILURE


class ChargeTask(_Task):
    """Drive to a charging node and charge for some minutes or until a battery level."""

    type: Literal["charge"]
    node: str
    minutes: float | None = Field(None, gt=0, le=24 * 60)
    until_level: float | None = Field(None, gt=0, le=1)

    @model_validator(mode="after")
    def _one_end(self) -> ChargeTask:
        if (self.minutes is None) == (self.until_level is None):
            raise ValueError("give either minutes or until_level")
        return self


class WaitTask(_Task):
    """Stand still for some seconds."""

    type: Literal["wait"]
    seconds: float = Field(gt=0, le=86_400, description="at most a day (s)")


Task = Annotated[PickupTask | DeliveryTask | MoveTask | ChargeTask | WaitTask, Field(discriminator="type")]

NODE_TYPES: dict[str, tuple[NodeType, ...]] = {
    "pickup": (NodeType.PALLET,),
    "delivery": (NodeType.DROP, NodeType.PALLET),
    "charge": (NodeType.CHARGING,),
}


class Mission(FileModel):
    """A mission file: a name, a map and the tasks in order."""

    name: str = "mission"
    map: str
    loaded_at_start: bool = False
    """The forks carry a load when the mission starts (default: empty)."""
    pallet_type: str = Field("eur", min_length=1, max_length=4096)
    """The pallets this mission handles: a built-in name (`perception.specs.PALLET_NAMES`) or a pallet type
    file relative to the mission; a pickup task's own `pallet_type` overrides it."""
    return_on_failure: bool | None = None
    """After a failed task (not a collision, sensor timeout, internal error, vehicle or localization fault
    or a cancel: then the truck stays stopped), leave for the nearest parking node of the map and wait
    there. A pickup, delivery or move task's own `return_on_failure` overrides it; None: the executor's
    `Settings.return_on_failure` (off)."""
    blocked_wait_s: float | None = Field(None, gt=0.0, le=3600.0)
    """How long (s) a blocked path or entry holds a task before `path_blocked` / `slot_occupied`
    (default: the executor's `Settings.blocked_wait_s`, 30 s)."""
    tasks: list[Task] = Field(min_length=1, max_length=10_000)
    folder: Path = Field(Path("."), exclude=True)

    @property
    def map_path(self) -> Path:
        """The map file, resolved against the mission's folder."""
        return self.folder / self.map

    def returns_on_failure(self, task: object, default: bool) -> bool:
        """Whether a failed `task` sends the truck to a parking node: the task's own `return_on_failure`,
        else the mission's, else `default` (the executor's setting)."""
        own = getattr(task, "return_on_failure", None)
        if own is not None:
            return bool(own)
        return default if self.return_on_failure is None else self.return_on_failure

    def pallet_types(self, where: str = "mission") -> list[PalletType]:
        """The type of the pallet each task handles: a pickup's own `pallet_type` or the mission's; a
        delivery (and any other task) that of the pallet on the forks, i.e. the last pickup's, else the
        mission's. Raises `MissionError` with one line per bad name (`where: tasks[i].pallet_type: ...`)."""
        problems: list[str] = []
        cache: dict[str, PalletType] = {}

        def resolve(name: str, field: str) -> PalletType:
            if name not in cache:
                try:
                    cache[name] = pallet_type_in(name, self.folder)
                except PalletpilotError as exc:
                    problems.extend(f"{where}: {field}: {line}" for line in exc.problems)
                    cache[name] = PalletType.eur()
            return cache[name]

        default = resolve(self.pallet_type, "pallet_type")
        carried, out = default, []
        for i, task in enumerate(self.tasks):
            if isinstance(task, PickupTask):
                own = task.pallet_type
                carried = default if own is None else resolve(own, f"tasks[{i}].pallet_type")
            out.append(carried)
        raise_problems(problems, MissionError)
        return out


def load_mission(path: str | Path) -> Mission:
    """Read a mission file; schema problems raise `MissionError` (one line each, with the field)."""
    mission = load_yaml_model(path, Mission, MissionError)
    mission.folder = Path(path).parent
    return mission


def validate_mission(mission: Mission, roadmap: Roadmap, vehicle: VehicleParams, start: str | None, where: str) -> None:
    """Check every task against the map and the vehicle; raise `MissionError` listing all problems.

    Reachability is checked along the chain: from `start`, each task's node must be reachable from
    where the previous task left the forklift (a pickup or delivery ends at its pre-pallet node). The
    load is followed too: no pickup while the forks carry a load, no delivery with empty forks.
    `start` None (an unknown start, reported elsewhere): reachability is not checked.
    """
    problems: list[str] = []
    try:
        mission.pallet_types(where)
    except MissionError as exc:
        problems += exc.problems
    planner = Planner(roadmap)
    here = start
    mast = vehicle.mast
    loaded_by: str | None = "the start (loaded_at_start)" if mission.loaded_at_start else None
    for i, task in enumerate(mission.tasks):
        label = f"{where}: tasks[{i}] ({task.type}"
        node_id = getattr(task, "node", None)
        if task.type == "pickup":
            if loaded_by is not None:
                problems.append(f"{label}): a pickup while the forks still carry the load from {loaded_by}")
            loaded_by = f"tasks[{i}]"
        elif task.type == "delivery":
            if loaded_by is None:
                problems.append(f"{label}): a delivery with empty forks: no pickup (or loaded_at_start) before it")
            loaded_by = None
        if getattr(task, "until_level", None) is not None and vehicle.battery is None:
            problems.append(f"{label}): until_level needs a battery model (`battery` in the vehicle file)")
        if node_id is None:
            continue
        label += f" {node_id})"
        if node_id not in roadmap:
            problems.append(
                f"{label}: unknown node '{node_id}'{did_you_mean(node_id, [n.id for n in roadmap.nodes()])}"
            )
            continue
        node = roadmap.node(node_id)
        allowed = NODE_TYPES.get(task.type)
        if allowed and node.type not in allowed:
            want = " or ".join(t.value for t in allowed)
            problems.append(f"{label}: node '{node_id}' is a {node.type.value} node, a {task.type} needs a {want} node")
            continue
        height = getattr(task, "height", None)
        if height is None and task.type in ("pickup", "delivery"):
            height = node.height  # the node's own height, which the task would use
        if height is not None and not (mast.min_height <= height <= mast.max_height - 0.15):
            problems.append(
                f"{label}: height {height:.2f} m is outside the mast's range "
                f"{mast.min_height:.2f}..{mast.max_height - 0.15:.2f} m (lift margin 0.15 m)"
            )
        target = node.pre_pallet if task.type in ("pickup", "delivery") and node.pre_pallet else node_id
        if task.type in ("pickup", "delivery") and not node.pre_pallet:
            problems.append(f"{label}: node '{node_id}' names no pre-pallet node to approach it from")
            continue
        try:
            if here is not None:
                planner.plan(here, target)
        except RoadmapError:
            problems.append(f"{label}: node '{target}' cannot be reached from '{here}'")
            continue
        here = target
    if problems:
        raise MissionError(problems[0] if len(problems) == 1 else f"{where}: {len(problems)} problems", problems)

"""What a scenario places, loaded and checked before a `sim.simulator.Simulator` runs it.

- `_load_references`: the scenario's map, vehicle and forks, with its node references checked (the start
  node; each pallet's node exists and is a pallet node; no two pallets at one node); every problem of every
  file and field is one line of one `SimError` (`scenario.yaml: pallets[2].node: unknown node 'x'`).
- `_pallet_types`: each placed pallet's type (a built-in name or a file relative to the scenario), its
  problems likewise.
- `overlap_problems`: placements that cannot be: the truck at its start node touching anything, pallets
  overlapping each other or anything else (people, boxes, racks, walls).
- `_person_solid`: a person (standing or walking) as a solid for the contact tests (`sim.contacts`).

Public API: `overlap_problems` (also importable from `sim.simulator`). Package-internal (used by
`sim.simulator`): `_load_references`, `_pallet_types`, `_person_solid`.
"""

from __future__ import annotations

from palletpilot.control.vehicle import VehicleParams, load_vehicle
from palletpilot.geometry import SE2, PalletpilotError
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.perception.specs import ForkGeometry, PalletType, load_forks, pallet_type_in
from palletpilot.roadmap import NodeType, Roadmap, load_map, map_vehicle_file
from palletpilot.sim.contacts import Solid, box_solid, first_contact
from palletpilot.sim.scenario import Scenario, SimError

__all__ = ["overlap_problems"]


def _load_references(scenario: Scenario, start: str | None) -> tuple[Roadmap, VehicleParams, ForkGeometry]:
    """The scenario's map, vehicle and forks, with its node references checked: every problem of every
    file and field is one line of the `SimError` (`scenario.yaml: pallets[2].node: unknown node 'x'`)."""
    where, problems = scenario.source, list[str]()
    map_path = scenario.path(scenario.map)
    roadmap = collect(problems, lambda: load_map(map_path))
    vehicle_path = (
        scenario.path(scenario.vehicle) if scenario.vehicle else collect(problems, lambda: map_vehicle_file(map_path))
    )
    vehicle = None
    if vehicle_path is None and not problems:
        problems.append(f"{where}: vehicle: the scenario names no vehicle file and its map has none")
    elif vehicle_path is not None:
        vehicle = collect(problems, lambda: load_vehicle(vehicle_path))
    forks = collect(problems, lambda: load_forks(scenario.path(scenario.forks)))
    if roadmap is not None:
        field, node_id = ("start", scenario.start) if start is None else ("--at", start)
        if node_id not in roadmap:
            problems.append(f"{where}: {field}: unknown node '{node_id}' (not in {scenario.map})")
        for i, placement in enumerate(scenario.pallets):
            if placement.node is None:
                continue
            if placement.node not in roadmap:
                problems.append(f"{where}: pallets[{i}].node: unknown node '{placement.node}' (not in {scenario.map})")
            elif (node := roadmap.node(placement.node)).type is not NodeType.PALLET:
                problems.append(
                    f"{where}: pallets[{i}].node: '{node.id}' is a {node.type.value} node, not a pallet node"
                )
        placed = [p.node for p in scenario.pallets if p.node is not None]
        for node_id in sorted({n for n in placed if placed.count(n) > 1}):
            problems.append(f"{where}: pallets: two pallets placed at node '{node_id}'")
    raise_problems(problems, SimError)
    assert roadmap is not None and vehicle is not None and forks is not None
    return roadmap, vehicle, forks


def _pallet_types(scenario: Scenario) -> list[PalletType]:
    """Each placed pallet's type (`pallets[i].type`: a built-in name or a file relative to the scenario)."""
    out, problems, cache = [], [], {}
    for i, placement in enumerate(scenario.pallets):
        name = placement.type
        if name not in cache:
            try:
                cache[name] = pallet_type_in(name, scenario.folder)
            except PalletpilotError as exc:
                problems += [f"{scenario.source}: pallets[{i}].type: {line}" for line in exc.problems]
                continue
        out.append(cache[name])
    raise_problems(problems, SimError)
    return out


def overlap_problems(
    start: tuple[list[Solid], list[tuple[str, list[Solid]]]], where: str, start_node: str, tol: float = 0.01
) -> list[str]:
    """Placements that cannot be: the truck at its start node touching anything, and pallets overlapping
    each other or anything else (people, boxes, racks, walls) by more than `tol` (m).

    People and boxes may stand next to each other (a person beside a box is no fault of the scenario).
    """
    truck, things = start
    problems = []
    for name, solids in things:
        if first_contact(truck, solids, tol):
            problems.append(f"{where}: start: the truck at '{start_node}' overlaps {name}")
    pallets = [(n, s) for n, s in things if n.startswith("pallets[")]
    for i, (name, solids) in enumerate(pallets):
        for other, theirs in [*pallets[i + 1 :], *[t for t in things if not t[0].startswith("pallets[")]]:
            if first_contact(solids, theirs, tol):
                problems.append(f"{where}: {name} overlaps {other}")
    return problems


def _person_solid(id_: str, pose: SE2) -> Solid:
    """A standing person as a solid: legs, torso and arms of `world.person_mesh` (0.26 x 0.62 x 1.75 m)."""
    return box_solid("person", id_, pose, (-0.13, -0.31, 0.0), (0.13, 0.31, 1.75))

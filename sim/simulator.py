"""The simulated warehouse: a scenario's map, pallets and clutter, the forklift, its camera and sensors.

`Simulator` is what the executor drives in tests, demos and benchmarks. It offers what the robot
offers (the vehicle and camera ports of ARCHITECTURE.md) plus the truth that only tests may read:

- `localization()` -> `T_world_forklift` with the scenario's noise; `drive(speed, steering)`; `stop()`;
  `set_fork_height(h)` and `fork_height`; `proximity_ranges()` -> (left, right) beam ranges (m);
- `grab()` -> a `FrameBundle` rendered from the camera on the fork carriage (truth in `*_true` keys);
- `step(dt)` advances simulated time: driving, lifting, pallets riding on the forks, collisions;
- `snapshot()` -> plain JSON of the exact state, `restore(doc)` returns to it (`sim.snapshot`).

Pickup physics (entering, lifting, carrying, setting down) is `sim.pallets.PalletPhysics`; contacts
with everything else `sim.contacts`; the safety scanners `sim.scanner`. Walking people give way to
the truck (`WALKER_YIELD_M`, and they never step into its protective field). What the scenario places is
loaded and checked in `sim.placements` (map, vehicle, forks, node references, pallet types, overlaps at the
start: `overlap_problems`, importable from here too).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import open3d as o3d

from palletpilot.control.safety import FIELD_SETS, TRAVEL_DIRECTIONS, SafetyState
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.errors import raise_problems
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.specs import PalletType, pallet_pose_at_node
from palletpilot.roadmap import NodeType
from palletpilot.sim.camera import CameraModel, RaycastRenderer
from palletpilot.sim.contacts import Contact, Solid, box_solid, first_contact, first_pair, rack_solids, solid_corners
from palletpilot.sim.forklift import LocalizationNoise, SimForklift
from palletpilot.sim.pallets import PalletPhysics, RackSupport, SimPallet
from palletpilot.sim.placements import _load_references, _pallet_types, _person_solid, overlap_problems
from palletpilot.sim.scanner import SimScanner
from palletpilot.sim.scenario import Scenario, SimError
from palletpilot.sim.snapshot import restore_snapshot, take_snapshot
from palletpilot.sim.solid_cache import SolidCache, WorldSolids
from palletpilot.sim.world import (
    LabeledMesh,
    Rack,
    floor_mesh,
    forks_mesh,
    o3d_tensor,
    object_box_mesh,
    pallet_mesh,
    person_mesh,
    wall_mesh,
)

CONTROL_DT = 0.05
"""Control period (s): the executor ticks at 20 Hz."""

BEAM_MAX_RANGE_M = 4.0
"""Range of the fork-tip proximity beams (m); farther hits read as `inf`."""

CARGO_SIZE = (1.15, 0.78, 0.9)
"""Cargo box on a loaded EUR pallet (m, x y z); other types: `cargo_size`."""


def cargo_size(pallet: PalletType) -> tuple[float, float, float]:
    """The cargo box on a loaded pallet of this type (m, x y z): 5 cm shorter and 2 cm narrower than it."""
    return (round(pallet.length - 0.05, 6), round(pallet.width - 0.02, 6), CARGO_SIZE[2])


WALKER_YIELD_M = 0.5
"""A walking person waits rather than come closer than this (m) to the truck."""


class Simulator(PalletPhysics):
    """A running simulated warehouse for one scenario (deterministic for its seed)."""

    def __init__(self, scenario: Scenario, seed: int | None = None, start: str | None = None) -> None:
        self.scenario = scenario
        self.seed = scenario.seed if seed is None else seed
        self.rng = np.random.default_rng(self.seed)
        self.roadmap, self.vehicle, self.forks = _load_references(scenario, start)
        self.pallet_type = PalletType.eur()  # what the executor is told; each pallet has its own (`SimPallet.type`)

        start_id = start or scenario.start
        start_node = self.roadmap.node(start_id)
        self.forklift = SimForklift(
            self.vehicle,
            start_node.pose,
            np.random.default_rng(self.rng.integers(2**32)),
            slip_sigma=scenario.noise.slip_sigma,
        )
        self.localization_noise = LocalizationNoise(
            scenario.noise.localization_xy_sigma, math.radians(scenario.noise.localization_yaw_sigma_deg)
        )
        self._loc_rng = np.random.default_rng(self.rng.integers(2**32))
        self._cam_rng = np.random.default_rng(self.rng.integers(2**32))
        self.camera = CameraModel.d435(scenario.camera.width, scenario.camera.height)
        self.T_forklift_camera_true = self._perturbed_mount()
        self.time = 0.0
        self.walk_t = [0.0] * len(scenario.clutter)  # how long each person has walked (s; waiting stops it)
        self.battery_level: float | None = scenario.battery_level if self.vehicle.battery is not None else None
        self._chargers = [n.pose for n in self.roadmap.nodes() if n.type is NodeType.CHARGING]
        self.collisions: list[dict[str, Any]] = []  # contacts: t_s, kind, id, part, message (the first stops all)
        self.scanner = SimScanner(self.vehicle)

        self.pallets: list[SimPallet] = []
        types = _pallet_types(scenario)
        for i, placement in enumerate(scenario.pallets):
            pt, condition = types[i], placement.condition()
            if placement.node is None:  # free on the floor
                assert placement.x is not None and placement.y is not None
                T_world_pallet = SE2(placement.x, placement.y, math.radians(placement.yaw_deg)).to_se3()
                self.pallets.append(
                    SimPallet("", T_world_pallet, placement.loaded, id=f"pallets[{i}]", type=pt, condition=condition)
                )
                continue
            node = self.roadmap.node(placement.node)
            misplacement = SE2(placement.dx, placement.dy, math.radians(placement.dyaw_deg)).to_se3()
            T_world_pallet = pallet_pose_at_node(node.pose, node.height) @ misplacement
            self.pallets.append(
                SimPallet(node.id, T_world_pallet, placement.loaded, id=node.id, type=pt, condition=condition)
            )
        self._racks = self._build_racks()
        self._fixed_mesh = self._build_fixed_mesh()
        self._fixed_solids = self._build_fixed_solids()
        self._solid_cache = SolidCache(self._fixed_solids)
        self._forks_local = forks_mesh(self.forks, 0.0, SE3.identity())  # forklift frame, lift height 0
        self._renderer: RaycastRenderer | None = None
        self._beam_scene: o3d.t.geometry.RaycastingScene | None = None
        raise_problems(overlap_problems(self._start_solids(), scenario.source, start_id), SimError)

    # -- world ----------------------------------------------------------------------------
    def _perturbed_mount(self) -> SE3:
        mount = self.scenario.camera.mount.T_forklift_camera()
        p = self.scenario.camera.perturbation
        if p.xyz_sigma == 0.0 and p.angle_sigma_deg == 0.0:
            return mount
        d_xyz = self.rng.normal(0.0, p.xyz_sigma, 3)
        d_rpy = np.radians(self.rng.normal(0.0, p.angle_sigma_deg, 3))
        return SE3.from_translation(*d_xyz) @ mount @ SE3.from_xyz_rpy((0, 0, 0), d_rpy)

    def _start_solids(self) -> tuple[list[Solid], list[tuple[str, list[Solid]]]]:
        """The truck at its start, and every placed thing (pallets by scenario index, clutter, racks)."""
        hull, forks = self._truck_solids()
        things = [(f"pallets[{i}]", self._pallet_solids(p)) for i, p in enumerate(self.pallets)]
        things += [(s.id if s.kind != "rack" else f"the rack at '{s.id}'", [s]) for s in self._fixed_solids]
        things += [(s.id, [s]) for s in self._walker_solids()]
        return hull + forks, things

    def _build_racks(self) -> list[RackSupport]:
        racks = []
        for node in self.roadmap.nodes():
            if node.type in (NodeType.PALLET, NodeType.DROP) and node.height > 0.0:
                rack = Rack(
                    bays=1, bay_width=2.7, depth=1.1, height=node.height + 1.6, levels=(node.height,), slots_per_bay=1
                )
                # The rack bay sits so that a pallet placed exactly at the node overhangs the front beam.
                T_world_floor_pallet = pallet_pose_at_node(node.pose, 0.0)
                T_world_rack = T_world_floor_pallet @ SE3.from_translation(rack.pallet_overhang, 0.0, 0.0)
                racks.append(RackSupport(T_world_rack, rack, node.height, node.id))
        return racks

    def _floor_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The warehouse floor's (x, y) corners (m): the map's nodes with 6 m to spare, walls around."""
        xy = np.array([n.pose.xy for n in self.roadmap.nodes()])
        return xy.min(axis=0) - 6.0, xy.max(axis=0) + 6.0

    def _build_fixed_mesh(self) -> LabeledMesh:
        lo, hi = self._floor_bounds()
        corners = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]
        parts = [floor_mesh(lo[0], lo[1], hi[0], hi[1])]
        parts += [wall_mesh(corners[k], corners[(k + 1) % 4]) for k in range(4)]
        parts += [r.rack.mesh(r.T_world_rack) for r in self._racks]
        for c in self.scenario.clutter:
            if c.path:
                continue  # walking: drawn where it is at each frame (`_walker_meshes`)
            pose = SE2(c.x, c.y, math.radians(c.yaw_deg))
            parts.append(person_mesh(pose) if c.kind == "person" else object_box_mesh(pose, c.size))
        return LabeledMesh.merge(parts)

    def _walker_poses(self) -> list[tuple[int, SE2]]:
        """The walking people (clutter index) and where they are now (world)."""
        return [(i, SE2(*c.pose_at(self.walk_t[i]))) for i, c in enumerate(self.scenario.clutter) if c.path]

    def _walk(self, dt: float) -> None:
        """Walk the people on by `dt` (s); one who would come within `WALKER_YIELD_M` of the truck, or
        step into its protective field, waits (people give way to a forklift), so a walker never steps
        into the truck. One the truck has come close to walks on only where it does not come closer."""
        if not any(c.path for c in self.scenario.clutter):
            return
        truck: list[Solid] = []
        m, f = WALKER_YIELD_M, 0.1
        field = [dataclasses.replace(s, z=(0.0, 2.0)) for s in self.scanner.protective_zone]

        def near(pose: SE2) -> bool:
            zone = box_solid("person", "", pose, (-0.13 - m, -0.31 - m, 0.0), (0.13 + m, 0.31 + m, 1.75))
            if first_contact(truck, [zone]) is not None:
                return True
            return (
                first_contact(
                    field, [box_solid("person", "", pose, (-0.13 - f, -0.31 - f, 0), (0.13 + f, 0.31 + f, 1.75))]
                )
                is not None
            )

        body, front = self.vehicle.body, self._front_x()
        T_fw = self.true_pose.inv()

        def clearance(pose: SE2) -> float:  # outside the truck's footprint rectangle (m, negative inside)
            x, y = T_fw.apply([pose.x, pose.y])
            return max(body.rear_x - x, x - front, abs(y) - 0.5 * body.width)

        for i, c in enumerate(self.scenario.clutter):
            if not c.path:
                continue
            if not truck:
                hull, forks = self._truck_solids()
                truck = hull + forks
            here, ahead = SE2(*c.pose_at(self.walk_t[i])), SE2(*c.pose_at(self.walk_t[i] + dt))
            if not near(ahead) or (near(here) and clearance(ahead) >= clearance(here) - 1e-3):
                self.walk_t[i] += dt

    def _walker_meshes(self) -> list[LabeledMesh]:
        return [person_mesh(pose) for _, pose in self._walker_poses()]

    def _walker_solids(self) -> list[Solid]:
        return [_person_solid(f"clutter[{i}]", pose) for i, pose in self._walker_poses()]

    def _build_fixed_solids(self) -> list[Solid]:
        """Walls, rack uprights and beams, standing people and boxes as solids for the contact test."""
        lo, hi = self._floor_bounds()
        t = 0.1  # half the wall thickness
        origin = SE2(0.0, 0.0, 0.0)
        solids = [
            box_solid("wall", "south", origin, (lo[0], lo[1] - t, 0.0), (hi[0], lo[1] + t, 4.0)),
            box_solid("wall", "north", origin, (lo[0], hi[1] - t, 0.0), (hi[0], hi[1] + t, 4.0)),
            box_solid("wall", "west", origin, (lo[0] - t, lo[1], 0.0), (lo[0] + t, hi[1], 4.0)),
            box_solid("wall", "east", origin, (hi[0] - t, lo[1], 0.0), (hi[0] + t, hi[1], 4.0)),
        ]
        for r in self._racks:
            solids += rack_solids(r.rack, r.T_world_rack.to_se2(), r.node)
        for i, c in enumerate(self.scenario.clutter):
            pose = SE2(c.x, c.y, math.radians(c.yaw_deg))
            if c.path:
                continue  # walking: `_walker_solids`
            if c.kind == "person":
                solids.append(_person_solid(f"clutter[{i}]", pose))
            else:
                sx, sy, sz = c.size
                solids.append(
                    box_solid("box", f"clutter[{i}]", pose, (-0.5 * sx, -0.5 * sy, 0.0), (0.5 * sx, 0.5 * sy, sz))
                )
        return solids

    def obstacle_outlines(self) -> list[tuple[str, str, np.ndarray]]:
        """Racks, people and boxes for drawing: (kind, id, floor corners (4, 2) in the world frame, m)."""
        solids = self._fixed_solids + self._walker_solids()
        return [(s.kind, s.id, solid_corners(s)) for s in solids if s.kind != "wall"]

    def pallet_records(self) -> list[dict[str, Any]]:
        """Every pallet for the report: `id` (its node), `node`, `initial` and `final` true pose (`x_m`,
        `y_m`, `yaw_deg` of the pallet frame: the entry face's centre), `loaded`, `carried` (ever lifted)."""

        def pose(T: SE3) -> dict[str, float]:
            p2 = T.to_se2()
            return {"x_m": round(p2.x, 4), "y_m": round(p2.y, 4), "yaw_deg": round(math.degrees(p2.yaw), 3)}

        return [
            {
                "id": p.id,
                "node": p.node or None,
                "initial": pose(p.initial if p.initial is not None else p.T_world_pallet),
                "final": pose(p.T_world_pallet),
                "loaded": p.loaded,
                "carried": p.lifted,
                "on_forks": p.carried,
            }
            for p in self.pallets
        ]

    def _pallet_solids(self, p: SimPallet, kind: str = "pallet") -> list[Solid]:
        """A pallet (and its load) as solids: the whole pallet box, the cargo box."""
        pt, pose = p.type, p.T_world_pallet.to_se2()
        z0 = float(p.T_world_pallet.t[2])
        load_kind = "load" if kind == "pallet" else "carried load"
        solids = [box_solid(kind, p.id, pose, (0.0, -0.5 * pt.width, z0), (pt.length, 0.5 * pt.width, z0 + pt.height))]
        if p.loaded:
            cx, cy, cz = cargo_size(pt)
            overhang = p.condition.overhang_m if p.condition is not None else 0.0
            x0, top = (-overhang if overhang > 0.0 else 0.5 * (pt.length - cx)), z0 + pt.height
            solids.append(box_solid(load_kind, p.id, pose, (x0, -0.5 * cy, top), (x0 + cx, 0.5 * cy, top + cz)))
        return solids

    def _truck_solids(self) -> tuple[list[Solid], list[Solid]]:
        """The truck as solids: (body and carried pallets with loads, forks and backrest)."""
        pose, body = self.true_pose, self.vehicle.body
        hull = [
            box_solid(
                "body",
                "truck",
                pose,
                (body.rear_x, -0.5 * body.width, 0.0),
                (body.front_x, 0.5 * body.width, body.height),
            )
        ]
        for p in self.pallets:
            if p.carried:
                hull += self._pallet_solids(p, kind="carried pallet")
        forks = [box_solid(name, "truck", pose, lo, hi) for name, lo, hi in self._fork_boxes()]
        return hull, forks

    def _check_contacts(self) -> None:
        """Record the first contact of the truck with anything and stop it there: the body and a carried
        pallet against everything (static solids, walking people, resting pallets and loads), then the
        forks and backrest against all but the resting pallets, which they meet through their boards and
        blocks (`_contact`)."""
        if self.collisions:
            return
        world = self._world_solids()
        carried = [s for p in self.pallets if p.carried for s in self._pallet_solids(p, kind="carried pallet")]
        body = self.vehicle.body
        box = (np.array([body.rear_x, -0.5 * body.width, 0.0]), np.array([body.front_x, 0.5 * body.width, body.height]))
        truck = self._solid_cache.truck(self.true_pose, box, self._fork_set(), carried)
        forks = np.arange(len(truck)) > len(carried)  # the parts after the body and the carried ones
        pair = first_pair(truck, world.solids, mask=~(forks[:, None] & world.pallet[None, :]))
        if pair is not None:
            contact = Contact(truck.kinds[pair[0]], world.solids.solids[pair[1]])
            self._collide(contact.to_json(self.time))

    def _world_solids(self) -> WorldSolids:
        """What the truck can meet now: static solids, walking people, resting pallets and their loads."""
        return self._solid_cache.world(self.pallets, self._walker_solids(), self._pallet_solids)

    def _collide(self, record: dict[str, Any]) -> None:
        self.collisions.append(record)
        self.forklift.stop()
        self.forklift.state.v = 0.0  # blocked

    def _pallet_mesh(self, p: SimPallet) -> LabeledMesh:
        cargo = cargo_size(p.type) if p.loaded else None
        return pallet_mesh(p.T_world_pallet, p.type, cargo_size=cargo, condition=p.condition)

    def _static_changed(self) -> None:
        self._renderer = None
        self._beam_scene = None
        self._solid_cache.clear()

    def static_changed(self) -> None:
        """Say that the set of resting pallets changed from outside the simulation (a restored state): the
        camera's and the beams' scenes are rebuilt on their next use."""
        self._static_changed()

    def _static_meshes(self) -> LabeledMesh:
        return LabeledMesh.merge([self._fixed_mesh] + [self._pallet_mesh(p) for p in self.pallets if not p.carried])

    # -- vehicle port ---------------------------------------------------------------------
    @property
    def true_pose(self) -> SE2:
        """The forklift's true `T_world_forklift` (truth: tests and reports only)."""
        return self.forklift.state.pose

    def localization(self) -> SE2:
        """`T_world_forklift` as localization reports it (with the scenario's noise)."""
        return self.localization_noise.measure(self.true_pose, self._loc_rng)

    def drive(self, speed: float, steering: float) -> None:
        """Drive command: speed (m/s, negative in reverse) and steering angle (rad). Ignored after a collision
        or a safety stop."""
        if self.collisions or self.forklift.emergency:
            self.forklift.stop()
            return
        self.forklift.command(speed, steering)

    def stop(self) -> None:
        """Brake to a standstill."""
        self.forklift.stop()

    def emergency_stop(self) -> None:
        """The truck's safety stop: brake at `emergency_decel` whatever the drive commands (latched)."""
        self.forklift.emergency_stop()

    def localization_stamp(self) -> float:
        """When the last localization fix was taken (s, simulated): every call measures anew."""
        return self.time

    @property
    def speed(self) -> float:
        """Measured speed (m/s)."""
        return self.forklift.state.v

    @property
    def steering(self) -> float:
        """Measured steering angle (rad)."""
        return self.forklift.state.steering

    def set_fork_height(self, height: float) -> None:
        """Fork height target (m, fork bottoms above the floor)."""
        self.forklift.command_fork_height(height)

    @property
    def fork_height(self) -> float:
        """Measured fork height (m)."""
        return self.forklift.state.fork_height

    def load_detected(self) -> bool:
        """True when a pallet rides on the forks (the mast's pressure sensor)."""
        return any(p.carried for p in self.pallets)

    def faults(self) -> list[str]:
        """Safety faults: the contacts of the forks or backrest with a pallet."""
        return [f"collision: {c['message']}" for c in self.collisions]

    def safety_state(self) -> SafetyState:
        """The safety scanners' state after the last step (`control.safety.SafetyState`)."""
        return self.scanner.state

    def set_safety_field_set(self, name: str, direction: str = "forward") -> None:
        """Select the scanners' field case: the set (`normal`, or `narrow` for entering a pallet or a floor
        drop slot) and the direction of travel the truck is about to drive (`forward`, `reverse`)."""
        if name not in FIELD_SETS:
            raise SimError(f"unknown safety field set '{name}' (one of {', '.join(FIELD_SETS)})")
        if direction not in TRAVEL_DIRECTIONS:
            raise SimError(f"unknown direction of travel '{direction}' (one of {', '.join(TRAVEL_DIRECTIONS)})")
        self.scanner.select(
            "narrow" if name == "narrow" else "normal", "reverse" if direction == "reverse" else "forward"
        )

    def _front_x(self) -> float:
        """The truck's leading end going forward (m, forklift frame): the fork tips or a carried pallet."""
        front = self.forks.tip_x
        carried = [p for p in self.pallets if p.carried]
        if carried:
            T_fw = self.T_world_forklift3.inv()
            for p in carried:
                far = T_fw @ p.T_world_pallet @ SE3.from_translation(p.type.length, 0.0, 0.0)
                front = max(front, float(far.t[0]))
        return front

    def _update_scanner(self, dt: float) -> None:
        """Run the scanners and hand their stop and speed cap to the truck."""
        if not self.scanner.enabled:
            return
        fl = self.forklift
        # The scan plane meets walls, racks, people, boxes, resting pallets and their loads.
        world = self._world_solids().solids
        state = self.scanner.update(dt, self.true_pose, fl.state.v, fl.speed_cmd, self._front_x(), world)
        fl.protective_stop = state.protective_stop
        fl.speed_cap = state.speed_limit

    @property
    def T_world_forklift3(self) -> SE3:
        """True forklift pose as SE3 (on the floor)."""
        return self._solid_cache.pose3(self.true_pose)

    def proximity_ranges(self) -> tuple[float, float]:
        """Ranges (m) of the (left, right) beams shot forward from the fork tips at mid-blade height.

        A beam through a pallet pocket passes the whole pallet; a beam on a block stops at the entry
        face. `inf` when nothing is within `BEAM_MAX_RANGE_M`.
        """
        if self._beam_scene is None:
            self._beam_scene = o3d.t.geometry.RaycastingScene()
            self._beam_scene.add_triangles(self._static_meshes().to_open3d())
        T = self.T_world_forklift3
        z = self.fork_height + 0.5 * self.forks.thickness
        origins = T.apply(np.array([[self.forks.tip_x, y, z] for y in self.forks.centres_y]))
        direction = T.apply_vectors([1.0, 0.0, 0.0])
        rays = np.hstack([origins, np.tile(direction, (2, 1))]).astype(np.float32)
        t = self._beam_scene.cast_rays(o3d_tensor(rays))["t_hit"].numpy()
        walkers = self._walker_meshes()
        if walkers:  # people walking: a scene of where they are now
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(LabeledMesh.merge(walkers).to_open3d())
            t = np.minimum(t, scene.cast_rays(o3d_tensor(rays))["t_hit"].numpy())
        ranges = [float(r) if r <= BEAM_MAX_RANGE_M else math.inf for r in t]
        return ranges[0], ranges[1]

    # -- camera port ----------------------------------------------------------------------
    def T_world_camera_true(self) -> SE3:
        """True camera pose: forklift pose, carriage lift, mount."""
        return self.T_world_forklift3 @ SE3.from_translation(0, 0, self.fork_height) @ self.T_forklift_camera_true

    def grab(self) -> FrameBundle:
        """Render one RGB-D frame (depth, labels, RGB) from the carriage camera."""
        if self._renderer is None:
            self._renderer = RaycastRenderer(self._static_meshes())
        dynamic = [self._forks_local.transformed(self.T_world_forklift3 @ SE3.from_translation(0, 0, self.fork_height))]
        dynamic += [self._pallet_mesh(p) for p in self.pallets if p.carried]
        dynamic += self._walker_meshes()
        truth = {"T_forklift_camera_true": self.T_forklift_camera_true.matrix}
        target = self.pallet_ahead()
        if target is not None:
            truth["T_forklift_pallet_true"] = (self.T_world_forklift3.inv() @ target.T_world_pallet).matrix
        frame = self._renderer.render(
            self.T_world_camera_true(),
            self.camera,
            self.scenario.camera.noise,
            self._cam_rng,
            dynamic=dynamic,
            fork_height=self.fork_height,
            truth=truth,
        )
        return dataclasses.replace(frame, stamp_s=self.time)

    def pallet_ahead(self, max_range_m: float = 6.0) -> SimPallet | None:
        """The nearest resting pallet in front of the forks (within 45 deg of the fork axis), if any."""
        best, best_d = None, max_range_m
        T_fw = self.T_world_forklift3.inv()
        for p in self.pallets:
            if p.carried:
                continue
            local = T_fw.apply(p.T_world_pallet.t)
            d = math.hypot(local[0], local[1])
            if local[0] > 0 and abs(math.atan2(local[1], local[0])) < math.radians(45) and d < best_d:
                best, best_d = p, d
        return best

    # -- snapshots ------------------------------------------------------------------------
    def snapshot(self) -> dict:
        """The simulator's exact state as plain JSON, for crash-safe resume (layout: `sim.snapshot`).

        Holds what evolves while it runs (simulated time; the forklift's pose, speed, steering, fork
        height, commands and odometer; every pallet's pose, load and carried state; the collisions; the
        states of all random generators) plus what is fixed at construction (seed, perturbed camera mount).
        """
        return take_snapshot(self)

    def restore(self, doc: dict) -> None:
        """Return to the state of a `snapshot()`, bit for bit; caches of the resting pallets are dropped.

        Meant for a simulator built from the same scenario (and seed) as the snapshot's. Only the evolving
        parts differ from a fresh build; the seed and camera mount are restored too. Raises `SimError`
        (one line) for another snapshot format version, pallets that do not match the scenario's (count
        or nodes) or a malformed snapshot, and then leaves the simulator unchanged.
        """
        restore_snapshot(self, doc)

    # -- time -----------------------------------------------------------------------------
    def step(self, dt: float = CONTROL_DT) -> None:
        """Advance simulated time by `dt` (s): vehicle, mast, battery, carried pallets, contacts."""
        height_before = self.fork_height
        self._update_scanner(dt)
        self.forklift.step(dt)
        self._walk(dt)
        self.time += dt
        self._update_battery(dt, max(self.fork_height - height_before, 0.0))
        self._update_pallets()
        self._check_contacts()

    def _update_battery(self, dt: float, rise_m: float) -> None:
        """Drain by distance and lifting; charge while standing within 0.3 m of a charging node."""
        battery = self.vehicle.battery
        if battery is None or self.battery_level is None:
            return
        level = self.battery_level - abs(self.speed) * dt * battery.drain_per_km / 1000.0
        level -= rise_m * battery.drain_per_lift_m
        here = self.true_pose
        if abs(self.speed) < 1e-3 and any(here.distance_to(c) < 0.3 for c in self._chargers):
            level += battery.charge_per_min * dt / 60.0
        self.battery_level = min(max(level, 0.0), 1.0)

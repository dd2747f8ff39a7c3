"""Contacts between the truck and everything in the simulated warehouse.

Every physical thing is a `Solid`: an upright box (a rectangle on the floor, turned by a yaw, and a
z range) with a `kind` (`person`, `box`, `rack`, `pallet`, `load`, `wall`) and an `id` (a pallet's node,
a clutter entry's index, a rack's node and part). The truck is a few such boxes too (`truck_boxes`):
its body, the two forks and the load backrest at the current lift height, and a carried pallet with its
load. `first_contact` returns the first pair that overlaps by more than a tolerance, tested by
separating axes on the floor plane plus the z ranges. The fine contact of the forks with a pallet's
boards and blocks (the pockets) stays in `sim.simulator`; here the forks meet pallets only through
their loads.

All poses are in the world frame (SE2 on the floor, yaw about z); sizes in metres.

Public API: `Solid`, `Contact`, `box_solid`, `rack_solids`, `first_contact`, `overlapping`,
`solid_corners`. The body's size is the vehicle file's `body` (`control.vehicle.BodyParams`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from palletpilot.geometry import SE2
from palletpilot.sim.world import Rack


@dataclass(frozen=True)
class Solid:
    """An upright box: centre `pose` on the floor (world frame), `half` sizes along its x and y (m), and
    the z range `z` (bottom, top, m)."""

    kind: str
    id: str
    pose: SE2
    half: tuple[float, float]
    z: tuple[float, float]

    @property
    def radius(self) -> float:
        """Radius (m) of the circle around its footprint."""
        return math.hypot(*self.half)


@dataclass(frozen=True)
class Contact:
    """A truck part (`part`: body, left fork, ..., carried load) touching a solid."""

    part: str
    solid: Solid

    def to_json(self, t_s: float) -> dict[str, object]:
        """The report's record: time, object kind and id, truck part and a readable message."""
        s = self.solid
        return {
            "t_s": round(t_s, 3),
            "kind": s.kind,
            "id": s.id,
            "part": self.part,
            "message": f"t={t_s:.2f} s: {self.part} hit {s.kind} '{s.id}'",
        }


def solid_corners(solid: Solid) -> np.ndarray:
    """The four floor corners (4, 2) of a solid in the world frame, counter-clockwise."""
    hx, hy = solid.half
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    c, s = math.cos(solid.pose.yaw), math.sin(solid.pose.yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.array([solid.pose.x, solid.pose.y])


def _overlap(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Do two convex quadrilaterals (4, 2) overlap by more than `tol` (m) along every separating axis?"""
    for quad in (a, b):
        for k in range(2):
            edge = quad[k + 1] - quad[k]
            axis = np.array([-edge[1], edge[0]]) / np.linalg.norm(edge)
            pa, pb = a @ axis, b @ axis
            if min(pa.max(), pb.max()) - max(pa.min(), pb.min()) <= tol:
                return False
    return True


def overlapping(part: Solid, world: Sequence[Solid], tol: float = 1e-3) -> Iterator[Solid]:
    """The world solids that overlap `part` by more than `tol` (m), in the order of `world`."""
    if not world:
        return
    centres = np.array([[s.pose.x, s.pose.y] for s in world])
    radii = np.array([s.radius for s in world])
    near = np.hypot(*(centres - [part.pose.x, part.pose.y]).T) < radii + part.radius
    if not near.any():
        return
    a = solid_corners(part)
    for i in np.flatnonzero(near):
        solid = world[int(i)]
        if min(part.z[1], solid.z[1]) - max(part.z[0], solid.z[0]) <= tol:
            continue
        if _overlap(a, solid_corners(solid), tol):
            yield solid


def first_contact(truck: Sequence[Solid], world: Sequence[Solid], tol: float = 1e-3) -> Contact | None:
    """The first truck part that overlaps a world solid by more than `tol` (m), or None."""
    for part in truck:
        for solid in overlapping(part, world, tol):
            return Contact(part.kind, solid)
    return None


def box_solid(kind: str, id_: str, pose: SE2, lo: ArrayLike, hi: ArrayLike) -> Solid:
    """A solid from a box given by its corners `lo`, `hi` (x, y, z) in the frame of `pose` (SE2)."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    cx, cy = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])
    centre = pose @ SE2(cx, cy, 0.0)
    return Solid(kind, id_, centre, (0.5 * (hi[0] - lo[0]), 0.5 * (hi[1] - lo[1])), (float(lo[2]), float(hi[2])))


def rack_solids(rack: Rack, T_world_rack: SE2, id_: str) -> list[Solid]:
    """A rack's uprights and beams (`world.Rack.mesh`) as solids of kind `rack`, ids `ID upright K`,
    `ID beam K`."""
    ux, uy = rack.upright_size
    bx, bz = rack.beam_size
    solids = []
    for k in range(rack.bays + 1):
        y = (k - 0.5 * rack.bays) * rack.bay_width
        for j, x0 in enumerate((0.0, rack.depth - ux)):
            lo, hi = (x0, y - 0.5 * uy, 0.0), (x0 + ux, y + 0.5 * uy, rack.height)
            solids.append(box_solid("rack", f"{id_} upright {2 * k + j}", T_world_rack, lo, hi))
    y0, y1 = -0.5 * rack.bays * rack.bay_width, 0.5 * rack.bays * rack.bay_width
    for i, z in enumerate(rack.levels):
        for j, x0 in enumerate((0.0, rack.depth - bx)):
            lo, hi = (x0, y0, z - bz), (x0 + bx, y1, z)
            solids.append(box_solid("rack", f"{id_} beam {2 * i + j}", T_world_rack, lo, hi))
    return solids

"""Contacts between the truck and everything in the simulated warehouse.

Every physical thing is a `Solid`: an upright box (a rectangle on the floor, turned by a yaw, and a
z range) with a `kind` (`person`, `box`, `rack`, `pallet`, `load`, `wall`) and an `id` (a pallet's node,
a clutter entry's index, a rack's node and part). The truck is a few such boxes too (`truck_boxes`):
its body, the two forks and the load backrest at the current lift height, and a carried pallet with its
load. `first_contact` returns the first pair that overlaps by more than a tolerance, tested by
separating axes on the floor plane plus the z ranges. The fine contact of the forks with a pallet's
boards and blocks (the pockets) stays in `sim.simulator`; here the forks meet pallets only through
their loads.

The tests are vectorised: a `SolidSet` holds the floor corners, edge normals, z ranges and bounding
boxes of many solids as arrays, built once for what never moves (walls, racks, standing clutter) and
once per placement for resting pallets; `LocalBoxes` places boxes given in a moving frame (the
truck's parts, the scanner fields) with one array operation. `overlap_matrix` tests every part against
every solid at once: bounding boxes and z ranges first, separating axes only for the pairs left.

All poses are in the world frame (SE2 on the floor, yaw about z); sizes in metres.

Public API: `Solid`, `SolidSet`, `LocalBoxes`, `EMPTY`, `Contact`, `box_solid`, `rack_solids`,
`first_contact`, `first_pair`, `overlapping`, `overlap_matrix`, `solid_corners`. The body's size is the
vehicle file's `body` (`control.vehicle.BodyParams`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from palletpilot.geometry import SE2
from palletpilot.sim.world import Rack

_SIGNS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])  # corner order, counter-clockwise


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


@dataclass(frozen=True, eq=False)
class SolidSet:
    """Upright boxes with their floor geometry as arrays, for vectorised tests (world frame, m).

    `kinds` names each box (a solid's kind, a truck part, a field); `corners` (N, 4, 2) counter-clockwise;
    `axes` (N, 2, 2) the unit normals of the first two edges (a rectangle's separating axes); `lo`, `hi`
    (N, 3) the bounding box: x and y of the corners, the bottom and top. `solids` holds the `Solid`s
    themselves when the set was built from them (`of`), and is empty for boxes placed from a moving frame.
    """

    kinds: tuple[str, ...]
    corners: np.ndarray
    axes: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    solids: tuple[Solid, ...] = ()

    @classmethod
    def of(cls, solids: Sequence[Solid] | SolidSet) -> SolidSet:
        """The set of these solids (world frame); a `SolidSet` is returned as it is."""
        if isinstance(solids, SolidSet):
            return solids
        if not solids:
            return EMPTY
        pose = np.array([(s.pose.x, s.pose.y, s.pose.yaw) for s in solids])
        local = np.array([s.half for s in solids])[:, None, :] * _SIGNS  # (N, 4, 2) about each centre
        c, s = np.cos(pose[:, 2])[:, None], np.sin(pose[:, 2])[:, None]
        x, y = local[..., 0], local[..., 1]
        corners = np.stack([x * c - y * s + pose[:, 0:1], x * s + y * c + pose[:, 1:2]], axis=-1)
        edges = corners[:, 1:3] - corners[:, 0:2]  # (N, 2, 2): the edges 0-1 and 1-2
        normals = np.stack([-edges[..., 1], edges[..., 0]], axis=-1)
        axes = normals / np.sqrt((normals * normals).sum(axis=-1, keepdims=True))
        z = np.array([s.z for s in solids], dtype=float)
        lo, hi = _bounds(corners, z)
        return cls(tuple(s.kind for s in solids), corners, axes, lo, hi, tuple(solids))

    @classmethod
    def boxes(cls, kinds: Sequence[str], lo: np.ndarray, hi: np.ndarray, frame: SE2) -> SolidSet:
        """Boxes given by their corners `lo`, `hi` (K, 3, m) in a moving frame that stands at `frame` (SE2,
        world), placed in the world frame (`LocalBoxes`)."""
        return LocalBoxes.of(kinds, lo, hi).placed(frame)

    def __len__(self) -> int:
        return len(self.kinds)

    def __add__(self, other: SolidSet) -> SolidSet:
        """Both sets, this one's boxes first; `solids` only when both have theirs."""
        if not len(other):
            return self
        if not len(self):
            return other
        whole = len(self.solids) == len(self) and len(other.solids) == len(other)
        return SolidSet(
            self.kinds + other.kinds,
            np.concatenate([self.corners, other.corners]),
            np.concatenate([self.axes, other.axes]),
            np.concatenate([self.lo, other.lo]),
            np.concatenate([self.hi, other.hi]),
            self.solids + other.solids if whole else (),
        )


@dataclass(frozen=True, eq=False)
class LocalBoxes:
    """Axis-aligned boxes in a moving frame (the truck's parts, its scanner fields): `kinds`, floor
    `corners` (K, 4, 2, counter-clockwise from lo) and `z` (K, 2) in that frame (m), kept so that placing
    them at a pose is one array operation (`placed`)."""

    kinds: tuple[str, ...]
    corners: np.ndarray
    z: np.ndarray

    @classmethod
    def of(cls, kinds: Sequence[str], lo: np.ndarray, hi: np.ndarray) -> LocalBoxes:
        """The boxes with corners `lo`, `hi` (K, 3, m)."""
        xy = np.concatenate([lo[:, :2], hi[:, :2]], axis=1)  # x0 y0 x1 y1
        return cls(tuple(kinds), xy[:, _CORNER_INDEX], np.array([lo[:, 2], hi[:, 2]]).T)

    def placed(self, frame: SE2) -> SolidSet:
        """The boxes in the world with their frame at `frame` (SE2, world)."""
        if not self.kinds:
            return EMPTY
        c, s = math.cos(frame.yaw), math.sin(frame.yaw)
        corners = self.corners @ np.array([[c, s], [-s, c]]) + np.array([frame.x, frame.y])
        axes = np.array([[[-s, c], [-c, -s]]] * len(self.kinds))  # the edges' normals, the same for all
        return SolidSet(self.kinds, corners, axes, *_bounds(corners, self.z))


_CORNER_INDEX = np.array([[0, 1], [2, 1], [2, 3], [0, 3]])  # (x0, y0), (x1, y0), (x1, y1), (x0, y1)

EMPTY = SolidSet((), np.zeros((0, 4, 2)), np.zeros((0, 2, 2)), np.zeros((0, 3)), np.zeros((0, 3)))
"""The set of no solids."""


def _bounds(corners: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding boxes (lo, hi, each (N, 3)) of floor `corners` (N, 4, 2) over the z ranges `z` (N, 2)."""
    return (
        np.concatenate([corners.min(axis=1), z[:, :1]], axis=1),
        np.concatenate([corners.max(axis=1), z[:, 1:]], axis=1),
    )


def overlap_matrix(parts: SolidSet, world: SolidSet, tol: float = 1e-3, mask: np.ndarray | None = None) -> np.ndarray:
    """(P, N) bool: part `i` overlaps solid `j` by more than `tol` (m) in z and along every separating
    axis of the two rectangles; `mask` (P, N) leaves out the pairs where it is False. Pairs whose
    bounding boxes do not overlap on the floor are never tested further: along x or y their overlap is
    at least the depth the separating axes would find."""
    extent = np.minimum(parts.hi[:, None], world.hi[None]) - np.maximum(parts.lo[:, None], world.lo[None])
    near = (extent > (0.0, 0.0, tol)).all(axis=-1)  # (P, N): bounding boxes on the floor, z ranges by tol
    if mask is not None:
        near &= mask
    pi, wi = np.nonzero(near)
    if not pi.size:
        return near
    a, b = parts.corners[pi], world.corners[wi]  # (K, 4, 2)
    axes = np.concatenate([parts.axes[pi], world.axes[wi]], axis=1).transpose(0, 2, 1)  # (K, 2, 4 axes)
    pa, pb = a @ axes, b @ axes  # (K, 4 corners, 4 axes)
    depth = np.minimum(pa.max(axis=1), pb.max(axis=1)) - np.maximum(pa.min(axis=1), pb.min(axis=1))
    near[pi, wi] = (depth > tol).all(axis=-1)
    return near


def first_pair(
    parts: SolidSet, world: SolidSet, tol: float = 1e-3, mask: np.ndarray | None = None
) -> tuple[int, int] | None:
    """(part, solid) indices of the first part (in order) that overlaps a solid, and its first solid;
    `mask` (P, N) leaves out the pairs where it is False. None when nothing overlaps."""
    if not len(parts) or not len(world):
        return None
    hits = overlap_matrix(parts, world, tol, mask)
    rows = np.flatnonzero(hits.any(axis=1))
    if not rows.size:
        return None
    i = int(rows[0])
    return i, int(np.argmax(hits[i]))


def solid_corners(solid: Solid) -> np.ndarray:
    """The four floor corners (4, 2) of a solid in the world frame, counter-clockwise."""
    hx, hy = solid.half
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    c, s = math.cos(solid.pose.yaw), math.sin(solid.pose.yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.array([solid.pose.x, solid.pose.y])


def overlapping(part: Solid, world: Sequence[Solid] | SolidSet, tol: float = 1e-3) -> Iterator[Solid]:
    """The world solids that overlap `part` by more than `tol` (m), in the order of `world`."""
    solids = SolidSet.of(world)
    if not len(solids):
        return
    for j in np.flatnonzero(overlap_matrix(SolidSet.of([part]), solids, tol)[0]):
        yield solids.solids[int(j)]


def first_contact(
    truck: Sequence[Solid] | SolidSet, world: Sequence[Solid] | SolidSet, tol: float = 1e-3
) -> Contact | None:
    """The first truck part that overlaps a world solid by more than `tol` (m), or None."""
    parts, solids = SolidSet.of(truck), SolidSet.of(world)
    pair = first_pair(parts, solids, tol)
    if pair is None:
        return None
    return Contact(parts.kinds[pair[0]], solids.solids[pair[1]])


def box_solid(kind: str, id_: str, pose: SE2, lo: ArrayLike, hi: ArrayLike) -> Solid:
    """A solid from a box given by its corners `lo`, `hi` (x, y, z) in the frame of `pose` (SE2)."""
    x0, y0, z0 = np.asarray(lo, dtype=float).tolist()
    x1, y1, z1 = np.asarray(hi, dtype=float).tolist()
    centre = pose @ SE2(0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.0)
    return Solid(kind, id_, centre, (0.5 * (x1 - x0), 0.5 * (y1 - y0)), (z0, z1))


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

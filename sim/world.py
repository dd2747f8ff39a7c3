"""The simulated warehouse as triangle meshes with a semantic class, albedo and texture per triangle.

Every builder returns a `LabeledMesh` already placed in the frame of the pose it was given
(normally the world frame, z up, floor at z = 0). Parts are Open3D primitives (boxes, cylinders,
spheres) whose triangles carry:

- `classes`: `SemanticClass` id of the object (drivable floor, vertical walls and racks, pallets, ...);
- `albedo`: linear RGB reflectance in [0, 1];
- `texture` and `tangent_u` / `tangent_v`: which procedural texture the camera applies and its
  in-plane axes (for wood, `tangent_u` runs along the grain).

Frames (ARCHITECTURE.md): `pallet` has its origin at the centre of the entry face on the pallet's
underside, x into the pallet along the pockets, z up; `forklift` has its origin on the floor midway
between the forks, x towards the fork tips, z up; a rack's origin is on the floor at the centre of
its aisle face, x into the rack, y along it, z up.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike

from palletpilot.geometry import SE2, SE3
from palletpilot.perception.frames import SemanticClass
from palletpilot.perception.specs import ForkGeometry, PalletPart, PalletType


class Texture(IntEnum):
    """Procedural texture applied by the camera (see `sim.camera`)."""

    PLAIN = 0
    CONCRETE = 1
    WOOD = 2
    CARDBOARD = 3
    PAINTED_METAL = 4
    FABRIC = 5


# Base colours (linear albedo) of the default materials.
CONCRETE_GREY = (0.50, 0.50, 0.48)
WALL_WHITE = (0.78, 0.77, 0.72)
RACK_BLUE = (0.10, 0.22, 0.55)
BEAM_ORANGE = (0.85, 0.38, 0.08)
PINE = (0.72, 0.55, 0.34)
CARDBOARD_BROWN = (0.62, 0.45, 0.28)
FORK_STEEL = (0.12, 0.12, 0.13)
HI_VIS_YELLOW = (0.85, 0.80, 0.10)
DENIM = (0.15, 0.20, 0.35)
SKIN = (0.76, 0.57, 0.45)
BIN_GREEN = (0.15, 0.45, 0.20)


def o3d_tensor(array: np.ndarray) -> o3d.core.Tensor:
    """`o3d.core.Tensor(array)`: a CPU tensor copy of `array`, same dtype.

    open3d's stubs make `dtype` and `device` required; at runtime they default to the array's dtype and the CPU.
    """
    return o3d.core.Tensor(array)  # type: ignore[call-overload]


def _as_pose(T: SE3 | SE2) -> SE3:
    return T.to_se3() if isinstance(T, SE2) else T


@dataclass(frozen=True)
class LabeledMesh:
    """A triangle mesh with per-triangle semantic class, albedo and texture, in one frame (usually world).

    vertices (N, 3) float64 m; triangles (M, 3) int32, counter-clockwise seen from outside;
    classes (M,) uint8; albedo (M, 3) float32; texture (M,) uint8; tangent_u / tangent_v (M, 3)
    float32 unit vectors in the triangle plane.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    classes: np.ndarray
    albedo: np.ndarray
    texture: np.ndarray
    tangent_u: np.ndarray
    tangent_v: np.ndarray

    @property
    def n_triangles(self) -> int:
        """Number of triangles."""
        return int(self.triangles.shape[0])

    def transformed(self, T_b_a: SE3 | SE2) -> LabeledMesh:
        """The same mesh mapped from its frame a into frame b (points and tangents)."""
        T = _as_pose(T_b_a)
        return LabeledMesh(
            vertices=T.apply(self.vertices),
            triangles=self.triangles,
            classes=self.classes,
            albedo=self.albedo,
            texture=self.texture,
            tangent_u=T.apply_vectors(self.tangent_u).astype(np.float32),
            tangent_v=T.apply_vectors(self.tangent_v).astype(np.float32),
        )

    def with_class(self, cls: SemanticClass) -> LabeledMesh:
        """The same mesh with every triangle relabelled to `cls`."""
        return LabeledMesh(
            self.vertices,
            self.triangles,
            np.full_like(self.classes, int(cls)),
            self.albedo,
            self.texture,
            self.tangent_u,
            self.tangent_v,
        )

    @classmethod
    def merge(cls, meshes: Sequence[LabeledMesh]) -> LabeledMesh:
        """Concatenate meshes (all in the same frame) into one."""
        if not meshes:
            return cls.empty()
        offsets = np.cumsum([0] + [m.vertices.shape[0] for m in meshes[:-1]])
        return cls(
            vertices=np.concatenate([m.vertices for m in meshes]),
            triangles=np.concatenate([m.triangles + off for m, off in zip(meshes, offsets, strict=True)]).astype(
                np.int32
            ),
            classes=np.concatenate([m.classes for m in meshes]),
            albedo=np.concatenate([m.albedo for m in meshes]),
            texture=np.concatenate([m.texture for m in meshes]),
            tangent_u=np.concatenate([m.tangent_u for m in meshes]),
            tangent_v=np.concatenate([m.tangent_v for m in meshes]),
        )

    @classmethod
    def empty(cls) -> LabeledMesh:
        """A mesh without triangles."""
        z3 = np.zeros((0, 3), np.float32)
        return cls(
            np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.uint8), z3, np.zeros(0, np.uint8), z3, z3
        )

    @classmethod
    def from_open3d(
        cls,
        mesh: o3d.geometry.TriangleMesh,
        semantic: SemanticClass,
        albedo: ArrayLike,
        texture: Texture = Texture.PLAIN,
        grain: ArrayLike | None = None,
    ) -> LabeledMesh:
        """Wrap a legacy Open3D mesh: one class, albedo and texture for all its triangles.

        `grain` is the direction (in the mesh frame) the texture's u axis follows; it defaults to the
        mesh's longest bounding-box axis (so board textures run along the board).
        """
        mesh.compute_triangle_normals()
        vertices = np.asarray(mesh.vertices, dtype=float)
        triangles = np.asarray(mesh.triangles, dtype=np.int32)
        normals = np.asarray(mesh.triangle_normals, dtype=float)
        m = triangles.shape[0]
        extent = vertices.max(axis=0) - vertices.min(axis=0)
        order = np.argsort(-extent)
        axes = np.eye(3)[order]
        first = axes[0] if grain is None else np.asarray(grain, dtype=float) / np.linalg.norm(grain)
        u = first - (normals @ first)[:, None] * normals
        # Where the grain is along the normal (end faces), fall back to the next axis.
        for fallback in axes[1:]:
            weak = np.linalg.norm(u, axis=1) < 1e-3
            if not weak.any():
                break
            u[weak] = fallback - (normals[weak] @ fallback)[:, None] * normals[weak]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        v = np.cross(normals, u)
        return cls(
            vertices=vertices,
            triangles=triangles,
            classes=np.full(m, int(semantic), np.uint8),
            albedo=np.tile(np.asarray(albedo, np.float32), (m, 1)),
            texture=np.full(m, int(texture), np.uint8),
            tangent_u=u.astype(np.float32),
            tangent_v=v.astype(np.float32),
        )

    def to_open3d(self) -> o3d.t.geometry.TriangleMesh:
        """An Open3D tensor mesh with triangle attributes `classes` (uint8) and `colors` (albedo), for viewing."""
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d_tensor(self.vertices.astype(np.float32))
        mesh.triangle.indices = o3d_tensor(self.triangles)
        mesh.triangle["classes"] = o3d_tensor(self.classes)
        mesh.triangle.colors = o3d_tensor(self.albedo)
        return mesh


def box_mesh(
    lo: ArrayLike,
    hi: ArrayLike,
    semantic: SemanticClass,
    albedo: ArrayLike,
    texture: Texture = Texture.PLAIN,
    grain: ArrayLike | None = None,
) -> LabeledMesh:
    """An axis-aligned box from corner `lo` to corner `hi` (m) in its own frame (12 outward triangles)."""
    lo = np.asarray(lo, dtype=float)
    size = np.asarray(hi, dtype=float) - lo
    if np.any(size <= 0):
        raise ValueError(f"box_mesh: hi must exceed lo on every axis, got size {size.tolist()}")
    box = o3d.geometry.TriangleMesh.create_box(width=size[0], height=size[1], depth=size[2])
    box.translate(lo)
    return LabeledMesh.from_open3d(box, semantic, albedo, texture, grain)


# -- static structure -------------------------------------------------------------------------------


def floor_mesh(x_min: float, y_min: float, x_max: float, y_max: float, thickness: float = 0.1) -> LabeledMesh:
    """The drivable concrete floor, top face at z = 0 over [x_min, x_max] x [y_min, y_max] (world frame, m)."""
    return box_mesh(
        (x_min, y_min, -thickness), (x_max, y_max, 0.0), SemanticClass.DRIVABLE, CONCRETE_GREY, Texture.CONCRETE
    )


def wall_mesh(start_xy: ArrayLike, end_xy: ArrayLike, height: float = 4.0, thickness: float = 0.2) -> LabeledMesh:
    """A wall (class vertical) along the floor segment start -> end (world xy, m), centred on the segment."""
    start = np.asarray(start_xy, dtype=float)
    delta = np.asarray(end_xy, dtype=float) - start
    length = float(np.hypot(*delta))
    box = box_mesh(
        (0.0, -0.5 * thickness, 0.0),
        (length, 0.5 * thickness, height),
        SemanticClass.VERTICAL,
        WALL_WHITE,
        Texture.CONCRETE,
    )
    return box.transformed(SE2(start[0], start[1], float(np.arctan2(delta[1], delta[0]))))


@dataclass(frozen=True)
class Rack:
    """A pallet rack (class vertical): `bays` bays along y, beam pairs (front and back) at `levels`.

    Rack frame: origin on the floor at the centre of the aisle face, x into the rack, y along it, z up.
    `levels` are the heights (m) of the beam tops; pallets also stand on the floor (level index 0).
    """

    bays: int = 2
    bay_width: float = 2.7
    depth: float = 1.1
    height: float = 3.6
    levels: tuple[float, ...] = (1.3, 2.6)
    upright_size: tuple[float, float] = (0.09, 0.08)  # along x (depth), along y
    beam_size: tuple[float, float] = (0.05, 0.12)  # along x, along z
    slots_per_bay: int = 3
    pallet_overhang: float = 0.05  # pallet front beyond the front beam (m)

    def bay_centre_y(self, bay: int) -> float:
        """y (m) of a bay's centre line in the rack frame."""
        return (bay - 0.5 * (self.bays - 1)) * self.bay_width

    def mesh(self, T_world_rack: SE3 | SE2) -> LabeledMesh:
        """Uprights and beams placed in the world."""
        ux, uy = self.upright_size
        bx, bz = self.beam_size
        parts = []
        for k in range(self.bays + 1):
            y = (k - 0.5 * self.bays) * self.bay_width
            for x0 in (0.0, self.depth - ux):
                parts.append(
                    box_mesh(
                        (x0, y - 0.5 * uy, 0.0),
                        (x0 + ux, y + 0.5 * uy, self.height),
                        SemanticClass.VERTICAL,
                        RACK_BLUE,
                        Texture.PAINTED_METAL,
                        grain=(0, 0, 1),
                    )
                )
        y0, y1 = -0.5 * self.bays * self.bay_width, 0.5 * self.bays * self.bay_width
        for z in self.levels:
            for x0 in (0.0, self.depth - bx):
                parts.append(
                    box_mesh(
                        (x0, y0, z - bz),
                        (x0 + bx, y1, z),
                        SemanticClass.VERTICAL,
                        BEAM_ORANGE,
                        Texture.PAINTED_METAL,
                        grain=(0, 1, 0),
                    )
                )
        return LabeledMesh.merge(parts).transformed(T_world_rack)

    def slot_pose(self, bay: int, level: int, slot: int) -> SE3:
        """`T_rack_pallet` of a pallet slot: level 0 is the floor, level k >= 1 the k-th beam pair."""
        if not (0 <= bay < self.bays and 0 <= level <= len(self.levels) and 0 <= slot < self.slots_per_bay):
            raise ValueError(f"Rack.slot_pose: no slot bay={bay} level={level} slot={slot}")
        pitch = self.bay_width / self.slots_per_bay
        y = self.bay_centre_y(bay) + (slot - 0.5 * (self.slots_per_bay - 1)) * pitch
        z = 0.0 if level == 0 else self.levels[level - 1]
        return SE3.from_translation(-self.pallet_overhang, y, z)


# -- objects ----------------------------------------------------------------------------------------


PLASTIC_BLUE = (0.10, 0.20, 0.42)
FILM_CLEAR = (0.80, 0.82, 0.84)
FILM_GAP_M = 0.003
"""Stretch film stands this far (m) off what it wraps."""


@dataclass(frozen=True)
class PalletCondition:
    """How one real pallet differs from its type's drawing, and how its load stands on it.

    - `tolerance_m`: every face of every board and block is off the drawing by up to +-tolerance/2
      (uniform), so sizes are off by up to +-tolerance and positions by +-tolerance/2; faces on the
      floor stay on it.
    - `chipped_blocks`: that many blocks of the entry row (at random) miss a chunk of `chip_m` on
      their entry face: a corner (chip_m on each side) or a whole vertical edge (chip_m deep and wide).
    - `missing_bottom_boards`: indices of bottom boards that are gone (runners right to left,
      perimeter boards front to back); the blocks above stay where they were.
    - `overhang_m`: the load's front stands this far past the entry face.
    - `film`: the load and the top deck are wrapped in stretch film (class cargo), which hangs down
      over the top deck's front (past the entry face with an overhanging load).
    `seed` draws the tolerances and the chips.
    """

    tolerance_m: float = 0.0
    seed: int = 0
    chipped_blocks: int = 0
    chip_m: float = 0.03
    missing_bottom_boards: tuple[int, ...] = ()
    overhang_m: float = 0.0
    film: bool = False


def _box_minus(lo: np.ndarray, hi: np.ndarray, klo: np.ndarray, khi: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The box [lo, hi] without the box [klo, khi] (clipped to it) as up to six boxes."""
    klo, khi = np.maximum(klo, lo), np.minimum(khi, hi)
    if np.any(khi <= klo):
        return [(lo, hi)]
    out = []
    cur_lo, cur_hi = lo.copy(), hi.copy()
    for axis in range(3):
        if klo[axis] > cur_lo[axis]:
            a_hi = cur_hi.copy()
            a_hi[axis] = klo[axis]
            out.append((cur_lo.copy(), a_hi))
        if khi[axis] < cur_hi[axis]:
            b_lo = cur_lo.copy()
            b_lo[axis] = khi[axis]
            out.append((b_lo, cur_hi.copy()))
        cur_lo[axis], cur_hi[axis] = klo[axis], khi[axis]
    return out


def pallet_parts(pallet: PalletType, condition: PalletCondition | None = None) -> list[PalletPart]:
    """The boards and blocks of one real pallet: the type's parts (`PalletType.parts`) as `condition` changes them."""
    parts = pallet.parts()
    if condition is None or condition == PalletCondition(overhang_m=condition.overhang_m, film=condition.film):
        return parts
    rng = np.random.default_rng(condition.seed)
    out: list[PalletPart] = []
    for part in parts:
        if part.kind == "bottom_board" and int(part.name.rsplit("_", 1)[1]) in condition.missing_bottom_boards:
            continue
        lo, hi = part.lo.copy(), part.hi.copy()
        if condition.tolerance_m > 0.0:
            half = 0.5 * condition.tolerance_m
            d_lo, d_hi = rng.uniform(-half, half, 3), rng.uniform(-half, half, 3)
            d_lo[2] = 0.0 if lo[2] <= 0.0 else d_lo[2]  # on the floor stays on the floor
            lo, hi = lo + d_lo, hi + d_hi
        out.append(PalletPart(part.name, part.kind, lo, hi))
    n_chip = min(condition.chipped_blocks, 3)
    if n_chip:
        front = [i for i, p in enumerate(out) if p.kind == "block" and p.name.startswith("block_0")]
        for i in rng.choice(front, size=min(n_chip, len(front)), replace=False):
            block = out[int(i)]
            c = condition.chip_m
            lo, hi = block.lo, block.hi
            left = bool(rng.random() < 0.5)
            ky = (hi[1] - c, hi[1]) if left else (lo[1], lo[1] + c)
            shape = rng.integers(3)  # 0: top corner, 1: bottom corner, 2: the whole vertical edge
            kz = ((hi[2] - c, hi[2]), (lo[2], lo[2] + c), (lo[2], hi[2]))[int(shape)]
            klo, khi = np.array([lo[0], ky[0], kz[0]]), np.array([lo[0] + c, ky[1], kz[1]])
            pieces = [
                PalletPart(f"{block.name}_{k}", "block", a, b) for k, (a, b) in enumerate(_box_minus(lo, hi, klo, khi))
            ]
            out[int(i)] = pieces[0]
            out.extend(pieces[1:])
    return out


def pallet_mesh(
    T_world_pallet: SE3 | SE2,
    pallet: PalletType | None = None,
    cargo_size: ArrayLike | None = None,
    wood: ArrayLike = PINE,
    condition: PalletCondition | None = None,
) -> LabeledMesh:
    """A pallet from its real parts (boards and blocks), optionally loaded with a cargo box.

    `cargo_size` (x, y, z in m) puts a cardboard box (class cargo) centred on the top deck (with
    `condition.overhang_m`, its front that far past the entry face); the pallet's own triangles are
    then pallet-full (8) instead of pallet-empty (7). `condition` (`PalletCondition`) gives build
    tolerances, damage and stretch film. Parts alternate slightly in tone, as boards from different
    planks do; a plastic pallet (`material: plastic`) is one plain colour.
    """
    pallet = pallet or PalletType.eur()
    semantic = SemanticClass.PALLET_EMPTY if cargo_size is None else SemanticClass.PALLET_FULL
    plastic = pallet.material == "plastic"
    base = np.asarray(PLASTIC_BLUE if plastic else wood, dtype=float)
    parts = []
    for i, part in enumerate(pallet_parts(pallet, condition)):
        tone = base * (0.92 + 0.08 * ((i * 7) % 5) / 4.0)
        grain = (1, 0, 0) if part.kind in ("top_board", "bottom_board") else (0, 1, 0)
        if part.kind == "block":
            grain = (0, 0, 1)
            tone = tone * 0.9  # blocks are often chipboard, a little darker
        if plastic:
            parts.append(box_mesh(part.lo, part.hi, semantic, base, Texture.PLAIN))
        else:
            parts.append(box_mesh(part.lo, part.hi, semantic, tone, Texture.WOOD, grain=grain))
    if cargo_size is not None:
        cx, cy, cz = np.asarray(cargo_size, dtype=float)
        overhang = 0.0 if condition is None else condition.overhang_m
        x0 = -overhang if overhang > 0.0 else 0.5 * (pallet.length - cx)
        lo, hi = np.array([x0, -0.5 * cy, pallet.height]), np.array([x0 + cx, 0.5 * cy, pallet.height + cz])
        if condition is not None and condition.film:
            g = FILM_GAP_M
            parts.append(box_mesh(lo - g, hi + g, SemanticClass.CARGO, FILM_CLEAR, Texture.PLAIN))
            # The film also wraps the top deck, down to the cross boards (from the load's front when it overhangs).
            skirt_lo = np.array([min(x0, 0.0) - g, -0.5 * pallet.width - g, pallet.height - pallet.top_board_thickness])
            skirt_hi = np.array([max(x0 + cx, pallet.length) + g, 0.5 * pallet.width + g, pallet.height + g])
            parts.append(box_mesh(skirt_lo, skirt_hi, SemanticClass.CARGO, FILM_CLEAR, Texture.PLAIN))
        else:
            parts.append(box_mesh(lo, hi, SemanticClass.CARGO, CARDBOARD_BROWN, Texture.CARDBOARD, grain=(0, 0, 1)))
    return LabeledMesh.merge(parts).transformed(T_world_pallet)


def person_mesh(T_world_person: SE3 | SE2, height: float = 1.75) -> LabeledMesh:
    """A standing person (class person): legs, torso, arms and head; frame on the floor between the feet, x forward."""
    s = height / 1.75
    parts = []
    for y in (-0.1, 0.1):
        leg = o3d.geometry.TriangleMesh.create_cylinder(radius=0.075 * s, height=0.85 * s, resolution=12)
        leg.translate((0.0, y * s, 0.425 * s))
        parts.append(LabeledMesh.from_open3d(leg, SemanticClass.PERSON, DENIM, Texture.FABRIC, grain=(0, 0, 1)))
    parts.append(
        box_mesh(
            (-0.12 * s, -0.2 * s, 0.85 * s),
            (0.12 * s, 0.2 * s, 1.45 * s),
            SemanticClass.PERSON,
            HI_VIS_YELLOW,
            Texture.FABRIC,
            grain=(0, 0, 1),
        )
    )
    for y in (-0.26, 0.26):
        arm = o3d.geometry.TriangleMesh.create_cylinder(radius=0.05 * s, height=0.6 * s, resolution=10)
        arm.translate((0.0, y * s, 1.12 * s))
        parts.append(LabeledMesh.from_open3d(arm, SemanticClass.PERSON, HI_VIS_YELLOW, Texture.FABRIC, grain=(0, 0, 1)))
    head = o3d.geometry.TriangleMesh.create_sphere(radius=0.11 * s, resolution=10)
    head.translate((0.0, 0.0, 1.58 * s))
    parts.append(LabeledMesh.from_open3d(head, SemanticClass.PERSON, SKIN, Texture.PLAIN))
    return LabeledMesh.merge(parts).transformed(T_world_person)


def object_box_mesh(
    T_world_box: SE3 | SE2,
    size: ArrayLike = (0.6, 0.4, 0.5),
    albedo: ArrayLike = BIN_GREEN,
) -> LabeledMesh:
    """A free-standing box (class other-object), frame at the centre of its bottom face, size (x, y, z) in m."""
    sx, sy, sz = np.asarray(size, dtype=float)
    box = box_mesh(
        (-0.5 * sx, -0.5 * sy, 0.0), (0.5 * sx, 0.5 * sy, sz), SemanticClass.OTHER_OBJECT, albedo, Texture.PAINTED_METAL
    )
    return box.transformed(T_world_box)


def _prism_mesh(polygon_xz: np.ndarray, y0: float, y1: float) -> o3d.geometry.TriangleMesh:
    """A prism along y over [y0, y1] whose cross-section is the convex polygon `polygon_xz` ((K, 2): x, z).

    Triangles face outwards (checked against the centroid, which a convex prism contains).
    """
    k = len(polygon_xz)
    xz = np.asarray(polygon_xz, dtype=float)
    vertices = np.vstack(
        [np.column_stack([xz[:, 0], np.full(k, y), xz[:, 1]]) for y in (y0, y1)]
    )  # 0..k-1 at y0, k..2k-1 at y1
    tris = [(0, i, i + 1) for i in range(1, k - 1)] + [(k, k + i + 1, k + i) for i in range(1, k - 1)]
    for i in range(k):
        j = (i + 1) % k
        tris += [(i, j, k + j), (i, k + j, k + i)]
    tri = np.array(tris, dtype=np.int32)
    centre = vertices.mean(axis=0)
    a, b, c = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3.0 - centre) < 0.0
    tri[inward] = tri[inward][:, ::-1]
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(tri))


def fork_blade_sections(forks: ForkGeometry, lift_height: float = 0.0, fillet_steps: int = 6) -> list[np.ndarray]:
    """The blade's side profile (x, z; forklift frame) as convex polygons: the full-thickness box, the
    tapered wedge at the tip (when the file gives a taper) and slices of the heel fillet (a heel radius)."""
    h = lift_height
    x_heel, x_taper, x_tip = forks.heel_x, forks.taper_start_x, forks.tip_x
    t = forks.thickness
    sections = []
    if forks.tapered:
        sections.append(np.array([[x_heel, h], [x_taper, h], [x_taper, h + t], [x_heel, h + t]]))
        top_tip, bottom_tip = float(forks.top_z(x_tip)), float(forks.bottom_z(x_tip))
        sections.append(np.array([[x_taper, h], [x_tip, h + bottom_tip], [x_tip, h + top_tip], [x_taper, h + t]]))
    else:
        sections.append(np.array([[x_heel, h], [x_tip, h], [x_tip, h + t], [x_heel, h + t]]))
    r = forks.heel_radius
    if r > 0.0:
        xs = x_heel + np.linspace(0.0, r, fillet_steps + 1)
        zs = forks.top_z(xs)
        for i in range(fillet_steps):
            sections.append(
                np.array([[xs[i], h + t], [xs[i + 1], h + t], [xs[i + 1], h + zs[i + 1]], [xs[i], h + zs[i]]])
            )
    return sections


def forks_mesh(forks: ForkGeometry, lift_height: float, T_world_forklift: SE3 | SE2) -> LabeledMesh:
    """The ego forklift's two fork blades (class forks) at lift height (m), placed with `T_world_forklift`.

    A box blade as before; with a blade profile in the forks file, the full-thickness part, the
    tapered tip (a wedge whose top or bottom slopes) and the heel fillet (`fork_blade_sections`).
    """
    parts = []
    for cy in forks.centres_y:
        y0, y1 = cy - 0.5 * forks.width, cy + 0.5 * forks.width
        for section in fork_blade_sections(forks, lift_height):
            prism = _prism_mesh(section, y0, y1)
            parts.append(
                LabeledMesh.from_open3d(prism, SemanticClass.FORKS, FORK_STEEL, Texture.PAINTED_METAL, grain=(1, 0, 0))
            )
    return LabeledMesh.merge(parts).transformed(T_world_forklift)


# -- an example warehouse ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ExampleWorld:
    """A small warehouse for demos, tests and benchmarks (all poses in the world frame).

    `static` holds the floor, walls, a rack with pallets, a person and a bin; `pallet` is the pallet
    standing in front of the forklift at `T_world_pallet`; the forks are dynamic (lift height) and are
    built with `forks_mesh` per frame.
    """

    static: LabeledMesh
    T_world_forklift: SE3
    T_world_pallet: SE3
    pallet: PalletType


def example_world(
    T_world_forklift: SE3 | None = None,
    T_forklift_pallet: SE3 | None = None,
    loaded: bool = True,
) -> ExampleWorld:
    """A 20 x 14 m hall: walls, a two-bay rack (pallets on the floor and on the beams), a person, a bin,
    and one pallet ahead of the forklift (default 2.2 m ahead, turned 4 deg, 5 cm to the left)."""
    T_wf = T_world_forklift or SE3.from_xyz_rpy((2.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    T_fp = T_forklift_pallet or SE3.from_xyz_rpy((2.2, 0.05, 0.0), (0.0, 0.0, np.deg2rad(4.0)))
    T_wp = T_wf @ T_fp
    pallet = PalletType.eur()
    rack = Rack()
    T_world_rack = SE2(9.5, -3.8, 0.0)
    parts = [
        floor_mesh(-2.0, -7.0, 18.0, 7.0),
        wall_mesh((-2.0, -7.0), (18.0, -7.0)),
        wall_mesh((18.0, -7.0), (18.0, 7.0)),
        wall_mesh((18.0, 7.0), (-2.0, 7.0)),
        wall_mesh((-2.0, 7.0), (-2.0, -7.0)),
        rack.mesh(T_world_rack),
        pallet_mesh(T_wp, pallet, cargo_size=(1.1, 0.75, 0.8) if loaded else None),
        person_mesh(SE2(7.5, 2.5, np.deg2rad(-150.0))),
        object_box_mesh(SE2(5.0, -1.8, np.deg2rad(20.0))),
    ]
    for bay, level, slot, cargo in ((0, 0, 0, None), (0, 1, 1, (1.2, 0.8, 0.9)), (1, 2, 2, None)):
        T_rack_pallet = rack.slot_pose(bay, level, slot)
        parts.append(pallet_mesh(T_world_rack.to_se3() @ T_rack_pallet, pallet, cargo_size=cargo))
    return ExampleWorld(LabeledMesh.merge(parts), T_wf, T_wp, pallet)

"""Immutable rigid transforms: SE2 (planar) and SE3 (spatial).

Naming follows ARCHITECTURE.md: a variable `T_a_b` maps points from frame b into frame a,
`p_a = T_a_b.apply(p_b)`, and transforms compose with matching inner names:
`T_world_camera = T_world_forklift @ T_forklift_camera`.

Angles are radians. Roll/pitch/yaw are the ROS convention: extrinsic rotations about the fixed
x, y and z axes in that order, so `R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from palletpilot.geometry.angles import wrap_angle
from palletpilot.geometry.errors import GeometryError

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation


def _rotation_class() -> type[Rotation]:
    """scipy's `Rotation`, imported on first use: SE2 alone (maps, plans, the command line) needs no scipy."""
    from scipy.spatial.transform import Rotation

    return Rotation


def _readonly(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


def _points(points: ArrayLike, dim: int, what: str) -> tuple[np.ndarray, bool]:
    """Return points as an (N, dim) float array and whether the input was a single point."""
    arr = np.asarray(points, dtype=float)
    if arr.shape == (dim,):
        return arr[None, :], True
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise GeometryError(f"{what}: expected points of shape (N, {dim}) or ({dim},), got {arr.shape}")
    return arr, False


@dataclass(frozen=True)
class SE2:
    """A planar rigid transform (x, y in m, yaw in rad, wrapped to [-pi, pi)).

    As a pose `T_world_forklift` it is the forklift's position and heading in the world.
    """

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "x", float(self.x))
        object.__setattr__(self, "y", float(self.y))
        # Plain float arithmetic: poses are built in hot loops, numpy per scalar is slow.
        object.__setattr__(self, "yaw", (float(self.yaw) + math.pi) % (2.0 * math.pi) - math.pi)

    @classmethod
    def identity(cls) -> SE2:
        """The identity transform."""
        return cls()

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> SE2:
        """Build from a 3x3 homogeneous matrix (rotation must be orthonormal)."""
        m = np.asarray(matrix, dtype=float)
        if m.shape != (3, 3):
            raise GeometryError(f"SE2 matrix must be 3x3, got {m.shape}")
        r = m[:2, :2]
        if not np.allclose(r.T @ r, np.eye(2), atol=1e-6) or np.linalg.det(r) <= 0:
            raise GeometryError("SE2 matrix: rotation block is not a proper rotation")
        return cls(m[0, 2], m[1, 2], math.atan2(m[1, 0], m[0, 0]))

    @property
    def xy(self) -> np.ndarray:
        """Translation (m) as a length-2 array."""
        return np.array([self.x, self.y])

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 homogeneous matrix."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, self.x], [s, c, self.y], [0.0, 0.0, 1.0]])

    def __matmul__(self, other: SE2) -> SE2:
        if not isinstance(other, SE2):
            return NotImplemented
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return SE2(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            self.yaw + other.yaw,
        )

    def inv(self) -> SE2:
        """The inverse transform: `T_a_b.inv()` is `T_b_a`."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return SE2(-(c * self.x + s * self.y), s * self.x - c * self.y, -self.yaw)

    def apply(self, points: ArrayLike) -> np.ndarray:
        """Map points (N x 2 or a single 2-vector) from the source frame to the target frame."""
        pts, single = _points(points, 2, "SE2.apply")
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        out = pts @ np.array([[c, s], [-s, c]]) + self.xy
        return out[0] if single else out

    def to_se3(self, z: float = 0.0) -> SE3:
        """Lift to SE3: the same x, y, yaw at height z (m), zero roll and pitch."""
        return SE3(_rotation_class().from_euler("z", self.yaw), (self.x, self.y, z))

    def distance_to(self, other: SE2) -> float:
        """Euclidean distance (m) between the two positions."""
        return math.hypot(self.x - other.x, self.y - other.y)

    def isclose(self, other: SE2, atol: float = 1e-9, atol_yaw: float = 1e-9) -> bool:
        """True when positions agree to `atol` (m) and headings to `atol_yaw` (rad)."""
        return (
            abs(self.x - other.x) <= atol
            and abs(self.y - other.y) <= atol
            and abs(wrap_angle(self.yaw - other.yaw)) <= atol_yaw
        )


class SE3:
    """A spatial rigid transform: rotation (scipy `Rotation`) and translation (m). Immutable."""

    __slots__ = ("_rotation", "_translation")

    def __init__(self, rotation: Rotation | None = None, translation: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        t = np.array(translation, dtype=float).reshape(-1)
        if t.shape != (3,):
            raise GeometryError(f"SE3 translation must have 3 elements, got {t.shape[0]}")
        if rotation is None:
            rotation = _rotation_class().identity()
        elif not isinstance(rotation, _rotation_class()) or not rotation.single:
            raise GeometryError("SE3 rotation must be a single scipy Rotation")
        self._rotation = rotation
        self._translation = _readonly(t)

    # -- construction -------------------------------------------------------------------
    @classmethod
    def identity(cls) -> SE3:
        """The identity transform."""
        return cls()

    @classmethod
    def from_translation(cls, x: float, y: float, z: float) -> SE3:
        """A pure translation, the `Trans(x, y, z)` of ARCHITECTURE.md."""
        return cls(None, (x, y, z))

    @classmethod
    def from_matrix(cls, matrix: ArrayLike, atol: float = 1e-6) -> SE3:
        """Build from a 4x4 homogeneous matrix; the rotation block must be orthonormal."""
        m = np.asarray(matrix, dtype=float)
        if m.shape != (4, 4):
            raise GeometryError(f"SE3 matrix must be 4x4, got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise GeometryError("SE3 matrix has non-finite entries")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
            raise GeometryError(f"SE3 matrix: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
        r = m[:3, :3]
        if not np.allclose(r.T @ r, np.eye(3), atol=atol) or np.linalg.det(r) <= 0:
            raise GeometryError("SE3 matrix: rotation block is not a proper rotation")
        return cls(_rotation_class().from_matrix(r), m[:3, 3])

    @classmethod
    def from_xyz_rpy(cls, xyz: ArrayLike, rpy: ArrayLike) -> SE3:
        """Build from a translation (m) and roll, pitch, yaw (rad; R = Rz(yaw) Ry(pitch) Rx(roll))."""
        return cls(_rotation_class().from_euler("xyz", np.asarray(rpy, dtype=float)), xyz)

    # -- access -------------------------------------------------------------------------
    @property
    def rotation(self) -> Rotation:
        """The rotation as a scipy `Rotation`."""
        return self._rotation

    @property
    def R(self) -> np.ndarray:
        """The 3x3 rotation matrix."""
        return _readonly(self._rotation.as_matrix())

    @property
    def t(self) -> np.ndarray:
        """The translation (m), read-only."""
        return self._translation

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix (a fresh, writable copy)."""
        m = np.eye(4)
        m[:3, :3] = self._rotation.as_matrix()
        m[:3, 3] = self._translation
        return m

    def to_xyz_rpy(self) -> tuple[np.ndarray, np.ndarray]:
        """Translation (m) and roll, pitch, yaw (rad), the inverse of `from_xyz_rpy`."""
        return self._translation.copy(), self._rotation.as_euler("xyz")

    def to_se2(self) -> SE2:
        """Project onto the floor: x, y and the heading of the x axis about z."""
        x_axis = self._rotation.apply([1.0, 0.0, 0.0])
        return SE2(self._translation[0], self._translation[1], math.atan2(x_axis[1], x_axis[0]))

    # -- algebra ------------------------------------------------------------------------
    def __matmul__(self, other: SE3) -> SE3:
        if not isinstance(other, SE3):
            return NotImplemented
        return SE3(
            self._rotation * other._rotation, self._rotation.as_matrix() @ other._translation + self._translation
        )

    def inv(self) -> SE3:
        """The inverse transform: `T_a_b.inv()` is `T_b_a`."""
        r_inv = self._rotation.inv()
        return SE3(r_inv, -(r_inv.as_matrix() @ self._translation))

    def apply(self, points: ArrayLike) -> np.ndarray:
        """Map points (N x 3 or a single 3-vector) from the source frame to the target frame."""
        pts, single = _points(points, 3, "SE3.apply")
        out = pts @ self._rotation.as_matrix().T + self._translation
        return out[0] if single else out

    def apply_vectors(self, vectors: ArrayLike) -> np.ndarray:
        """Rotate direction vectors (N x 3 or one 3-vector); translation does not apply."""
        vecs, single = _points(vectors, 3, "SE3.apply_vectors")
        out = vecs @ self._rotation.as_matrix().T
        return out[0] if single else out

    def isclose(self, other: SE3, atol: float = 1e-9, atol_rot: float = 1e-9) -> bool:
        """True when translations agree to `atol` (m) and rotations to `atol_rot` (rad)."""
        dt = np.max(np.abs(self._translation - other._translation))
        dr = (self._rotation.inv() * other._rotation).magnitude()
        return bool(dt <= atol and dr <= atol_rot)

    def __repr__(self) -> str:
        xyz, rpy = self.to_xyz_rpy()
        return (
            f"SE3(xyz=[{xyz[0]:.4f}, {xyz[1]:.4f}, {xyz[2]:.4f}] m, "
            f"rpy=[{math.degrees(rpy[0]):.3f}, {math.degrees(rpy[1]):.3f}, {math.degrees(rpy[2]):.3f}] deg)"
        )

"""Property tests of the pose types: group laws and conversions."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE2, SE3, GeometryError, angle_diff, wrap_angle

coord = st.floats(-50.0, 50.0, allow_nan=False)
angle = st.floats(-10.0, 10.0, allow_nan=False)
se2s = st.builds(SE2, coord, coord, angle)
# Pitch away from +-90 deg, where roll/pitch/yaw are not unique (gimbal lock).
rpys = st.tuples(st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1))
se3s = st.builds(lambda t, rpy: SE3.from_xyz_rpy(t, rpy), st.tuples(coord, coord, coord), rpys)
points3 = st.lists(st.tuples(coord, coord, coord), min_size=1, max_size=5).map(np.array)


@given(se2s)
def test_se2_times_inverse_is_identity(T):
    assert (T @ T.inv()).isclose(SE2.identity(), atol=1e-9, atol_yaw=1e-12)
    assert (T.inv() @ T).isclose(SE2.identity(), atol=1e-9, atol_yaw=1e-12)


@given(se2s, se2s, se2s)
def test_se2_composition_is_associative(a, b, c):
    assert ((a @ b) @ c).isclose(a @ (b @ c), atol=1e-9, atol_yaw=1e-12)


@given(se2s, se2s)
def test_se2_matches_matrix_algebra(a, b):
    assert np.allclose((a @ b).matrix, a.matrix @ b.matrix, atol=1e-9)
    assert SE2.from_matrix(a.matrix).isclose(a, atol=1e-9, atol_yaw=1e-12)


@given(se2s, st.lists(st.tuples(coord, coord), min_size=1, max_size=5).map(np.array))
def test_se2_apply_matches_matrix(T, pts):
    homogeneous = np.c_[pts, np.ones(len(pts))] @ T.matrix.T
    assert np.allclose(T.apply(pts), homogeneous[:, :2], atol=1e-9)


@given(se2s, st.floats(-5, 5))
def test_se2_lift_to_se3_and_back(T, z):
    lifted = T.to_se3(z)
    assert lifted.t[2] == pytest.approx(z)
    assert lifted.to_se2().isclose(T, atol=1e-9, atol_yaw=1e-9)


@given(se3s)
def test_se3_times_inverse_is_identity(T):
    assert (T @ T.inv()).isclose(SE3.identity(), atol=1e-8, atol_rot=1e-9)


@given(se3s, se3s, se3s)
def test_se3_composition_is_associative(a, b, c):
    assert ((a @ b) @ c).isclose(a @ (b @ c), atol=1e-8, atol_rot=1e-9)


@given(se3s, se3s, points3)
def test_se3_composition_maps_points_like_matrices(a, b, pts):
    homogeneous = np.c_[pts, np.ones(len(pts))] @ (a.matrix @ b.matrix).T
    assert np.allclose((a @ b).apply(pts), homogeneous[:, :3], atol=1e-8)
    assert np.allclose(a.apply(b.apply(pts)), (a @ b).apply(pts), atol=1e-8)


@given(se3s)
def test_se3_conversions_round_trip(T):
    assert SE3.from_matrix(T.matrix).isclose(T, atol=1e-9, atol_rot=1e-9)
    xyz, rpy = T.to_xyz_rpy()
    assert SE3.from_xyz_rpy(xyz, rpy).isclose(T, atol=1e-9, atol_rot=1e-9)


@settings(max_examples=50)
@given(st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1))
def test_rpy_is_extrinsic_xyz(roll, pitch, yaw):
    def rx(a):
        return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])

    def ry(a):
        return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])

    def rz(a):
        return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])

    T = SE3.from_xyz_rpy((0, 0, 0), (roll, pitch, yaw))
    assert np.allclose(T.R, rz(yaw) @ ry(pitch) @ rx(roll), atol=1e-12)


def test_frame_naming_composes_like_the_architecture_says():
    # Camera 1 m up on the forklift, forklift at (2, 3) facing +y: a point 1 m ahead of the lens
    # along the forklift's x lies at (2, 4, 1) in the world.
    T_world_forklift = SE2(2.0, 3.0, math.pi / 2).to_se3()
    T_forklift_camera = SE3.from_translation(0.0, 0.0, 1.0)
    T_world_camera = T_world_forklift @ T_forklift_camera
    assert np.allclose(T_world_camera.apply([1.0, 0.0, 0.0]), [2.0, 4.0, 1.0])
    assert np.allclose(T_world_camera.inv().apply([2.0, 4.0, 1.0]), [1.0, 0.0, 0.0])


def test_from_matrix_rejects_non_rigid_and_bad_shapes():
    scaled = np.eye(4)
    scaled[0, 0] = 2.0
    with pytest.raises(GeometryError, match="not a proper rotation"):
        SE3.from_matrix(scaled)
    reflection = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(GeometryError, match="not a proper rotation"):
        SE3.from_matrix(reflection)
    with pytest.raises(GeometryError, match="4x4"):
        SE3.from_matrix(np.eye(3))
    with pytest.raises(GeometryError, match="shape"):
        SE3.identity().apply(np.zeros((4, 2)))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(GeometryError, match="non-finite"):
        SE3.from_matrix(bad)


def test_poses_are_immutable():
    T = SE3.from_translation(1, 2, 3)
    with pytest.raises(ValueError):
        T.t[0] = 5.0
    with pytest.raises(AttributeError):
        SE2(1, 2, 3).x = 4.0  # type: ignore[misc]


def test_angle_helpers():
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)
    assert angle_diff(math.radians(179), math.radians(-179)) == pytest.approx(math.radians(-2))
    assert np.allclose(wrap_angle(np.array([0.0, 2 * math.pi + 0.1])), [0.0, 0.1])
    assert SE2(0, 0, 7.0).yaw == pytest.approx(wrap_angle(7.0))


def test_se3_rotation_argument_is_checked():
    with pytest.raises(GeometryError):
        SE3(Rotation.from_euler("z", [[0.1], [0.2]]))
    with pytest.raises(GeometryError):
        SE3(None, (1.0, 2.0))

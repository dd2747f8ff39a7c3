"""The Pickup view check of a camera mount: entry face and load in the image 1.2-3.0 m ahead of the tips."""

import math

import pytest

from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.specs import PalletType, load_forks
from palletpilot.perception.view import pickup_view
from palletpilot.sim.camera import camera_mount_pose, d435_color_intrinsics

FORKS = load_forks(bundled_path("missions") / "forks.yaml")


def view(tilt_deg: float, z: float = 0.45):
    T = camera_mount_pose([-0.10, 0.0, z], math.radians(tilt_deg))
    return pickup_view(T, d435_color_intrinsics(640, 480), (640, 480), FORKS, PalletType.eur())


def test_the_demo_mount_sees_face_and_load_over_the_whole_range():
    v = view(22.0)
    assert v.face_ok and v.load_ok and v.problems() == []
    assert v.face_m == v.load_m == (1.2, 3.0)


def test_a_steeper_mount_loses_the_far_load_first_then_the_far_face():
    v = view(25.0)
    assert v.face_ok and not v.load_ok
    assert v.load_m is not None and v.load_m[0] == pytest.approx(1.2) and 1.5 < v.load_m[1] < 2.8
    (problem,) = v.problems()
    assert problem.startswith("a load is in the image only 1.20-")
    v = view(27.0)
    assert not v.face_ok and v.load_m is None
    assert v.face_m is not None and v.face_m[1] < 2.5
    assert [p.split(" is ")[0] for p in v.problems()] == ["the entry face", "a load"]


def test_a_higher_camera_sees_farther_at_the_same_tilt():
    assert not view(25.0, z=0.45).load_ok
    assert view(25.0, z=0.60).load_ok


def test_a_very_steep_mount_never_sees_the_pallet():
    v = view(40.0)
    assert v.face_m is None and v.load_m is None
    assert v.to_json()["entry_face_ok"] is False
    assert "is in the image never" in v.problems()[0]

"""The simulated forklift's kinematics, actuator limits and mast."""

import math

import numpy as np
import pytest

from palletpilot.control import load_vehicle
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.sim.forklift import LocalizationNoise, SimForklift

VEHICLE = load_vehicle(bundled_path("missions") / "forklift.yaml")
DT = 0.05


def run(fl: SimForklift, seconds: float) -> None:
    for _ in range(round(seconds / DT)):
        fl.step(DT)


def test_constant_steering_drives_a_circle_of_the_kinematic_radius():
    fl = SimForklift(VEHICLE, SE2(0, 0, 0))
    steering = math.radians(20)
    fl.state.steering = steering
    fl.state.v = 0.5
    fl.command(0.5, steering)
    radius = VEHICLE.wheelbase / math.tan(steering)
    centre = np.array([0.0, radius])  # turning left from the origin heading +x
    for _ in range(200):
        fl.step(DT)
        assert abs(np.hypot(*(fl.state.pose.xy - centre)) - radius) < 1e-9
    # Yaw advanced by the travelled arc length over the radius.
    assert abs(math.remainder(fl.state.pose.yaw - 200 * DT * 0.5 / radius, 2 * math.pi)) < 1e-9


def test_reverse_with_left_steering_turns_right():
    fl = SimForklift(VEHICLE, SE2(0, 0, 0))
    fl.command(-0.5, math.radians(15))
    run(fl, 4.0)
    assert fl.state.pose.x < 0 and fl.state.pose.yaw < 0


def test_acceleration_speed_and_steering_limits():
    fl = SimForklift(VEHICLE, SE2(0, 0, 0))
    fl.command(10.0, math.radians(89))
    fl.step(DT)
    assert fl.state.v <= VEHICLE.max_accel * DT + 1e-12
    assert fl.state.steering <= math.radians(VEHICLE.max_steering_rate_deg_s) * DT + 1e-12
    run(fl, 10.0)
    assert fl.state.v == pytest.approx(VEHICLE.max_speed_forward, abs=1e-6)
    assert fl.state.steering == pytest.approx(VEHICLE.max_steering, abs=1e-6)
    fl.stop()
    speeds = []
    for _ in range(100):
        fl.step(DT)
        speeds.append(fl.state.v)
    assert max(-np.diff(speeds)) <= VEHICLE.max_decel * DT + 1e-9
    assert fl.stopped


def test_mast_is_rate_limited_and_clipped():
    fl = SimForklift(VEHICLE, SE2(0, 0, 0))
    fl.command_fork_height(5.0)
    fl.step(1.0)
    assert fl.state.fork_height == pytest.approx(VEHICLE.mast.lift_speed)
    run(fl, 20.0)
    assert fl.state.fork_height == pytest.approx(VEHICLE.mast.max_height)


def test_slip_and_localization_noise_are_seeded():
    def drive(seed: int) -> SE2:
        fl = SimForklift(VEHICLE, SE2(0, 0, 0), np.random.default_rng(seed), slip_sigma=0.02)
        fl.command(1.0, 0.1)
        run(fl, 5.0)
        return fl.state.pose

    assert drive(1).isclose(drive(1)) and not drive(1).isclose(drive(2), atol=1e-6)
    noise = LocalizationNoise(xy_sigma=0.01, yaw_sigma=0.002)
    rng = np.random.default_rng(0)
    samples = np.array([[p.x, p.y, p.yaw] for p in (noise.measure(SE2(1, 2, 0.3), rng) for _ in range(4000))])
    assert np.std(samples[:, 0]) == pytest.approx(0.01, rel=0.1)
    assert np.mean(samples[:, 2]) == pytest.approx(0.3, abs=2e-4)

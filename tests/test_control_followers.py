"""MPC and pure-pursuit path followers driving the simulated forklift (20 Hz, actuator lag, noise)."""

import math

import numpy as np
import pytest

from palletpilot.bench.mpc import drive
from palletpilot.control import (
    ControlError,
    FollowerConfig,
    FollowerStatus,
    KinematicModel,
    MpcConfig,
    MpcFollower,
    PurePursuitFollower,
    load_vehicle,
)
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.roadmap import Arc, Direction, Edge, Line, Route, reference_path
from palletpilot.sim.forklift import LocalizationNoise

VEHICLE = load_vehicle(bundled_path("missions") / "forklift.yaml")
NOISE = LocalizationNoise(xy_sigma=0.005, yaw_sigma=math.radians(0.2))


@pytest.fixture(scope="module")
def mpc() -> MpcFollower:
    # Simulated time: no wall-clock deadline, so a loaded test machine cannot turn a slow solve into a
    # failure (the deadline has its own test below).
    return MpcFollower(VEHICLE, MpcConfig(solve_deadline_s=None))


def path_of(*edges: Edge):
    nodes = [edges[0].start] + [e.end for e in edges]
    return reference_path(Route(nodes, list(edges)))


def straight(length: float = 5.0, speed: float = 1.0):
    return path_of(Edge("a", "b", Line((0.0, 0.0), (length, 0.0)), speed_limit=speed))


def arc_path():
    # 1 m straight, a quarter circle of radius 2 m turning left, 1 m straight.
    e1 = Edge("a", "b", Line((0.0, 0.0), (1.0, 0.0)), speed_limit=0.8)
    e2 = Edge("b", "c", Arc(SE2(1.0, 0.0, 0.0), (3.0, 2.0)), speed_limit=0.8)
    e3 = Edge("c", "d", Line((3.0, 2.0), (3.0, 3.0)), speed_limit=0.8)
    return path_of(e1, e2, e3)


def pallet_path():
    """Forward along a 1.5 m arc to a pre-pallet node, straight 2.5 m into the pallet node; then reverse out."""
    e1 = Edge("a1", "pre", Arc(SE2(6.0, 15.0, -math.pi / 2), (4.5, 13.5)), speed_limit=0.6)
    e2 = Edge("pre", "pallet", Line((4.5, 13.5), (2.0, 13.5)), speed_limit=0.3)
    return path_of(e1, e2)


def reverse_out_path():
    """Reverse out of a pallet node, reverse arc back onto the aisle, then forward down the aisle."""
    back = Line((4.5, 13.5), (2.0, 13.5)).reversed()
    e1 = Edge("pallet", "pre", back, Direction.REVERSE, speed_limit=0.3)
    arc = Arc(SE2(6.0, 15.0, -math.pi / 2), (4.5, 13.5)).reversed()
    e2 = Edge("pre", "a1", arc, Direction.REVERSE, speed_limit=0.5)
    e3 = Edge("a1", "a2", Line((6.0, 15.0), (6.0, 12.0)), speed_limit=1.0)
    return path_of(e1, e2, e3)


def check_final(result, path, lateral_mm=10.0, heading_deg=0.5):
    assert result.status == "succeeded", result.error
    assert abs(result.final_lateral) * 1e3 <= lateral_mm
    assert abs(math.degrees(result.final_heading)) <= heading_deg
    assert abs(result.final_along) <= 0.02


def test_model_rk4_matches_exact_step_and_steering_sign():
    m = KinematicModel.from_params(VEHICLE)
    z = np.array([1.0, 2.0, 0.3, 0.2])
    u = np.array([0.8, 0.0])
    exact = m.step(z, u, 0.1)
    import casadi as ca

    rk4 = np.asarray(ca.DM(m.rk4(ca.DM(z), ca.DM(u), 0.1))).reshape(-1)
    assert np.allclose(exact, rk4, atol=1e-6)
    assert exact[2] > z[2]  # positive steering turns left going forward
    assert m.step(z, np.array([-0.8, 0.0]), 0.1)[2] < z[2]  # and right in reverse


def test_mpc_follows_a_straight_line(mpc):
    path = straight()
    r = drive(mpc, path, VEHICLE, seed=1, noise=NOISE, slip=0.01, start=SE2(0.0, 0.05, math.radians(2)))
    check_final(r, path)
    assert max(np.abs(r.lateral[len(r.lateral) // 3 :])) <= 0.01  # converged from the 5 cm offset


def test_mpc_follows_an_arc_within_limits(mpc):
    path = arc_path()
    r = drive(mpc, path, VEHICLE, seed=2, noise=NOISE, slip=0.01)
    check_final(r, path)
    lat = np.abs(r.lateral)
    assert float(np.sqrt(np.mean(lat**2))) <= 0.02
    assert float(lat.max()) <= 0.05


def test_mpc_stops_precisely_at_a_pallet_node(mpc):
    path = pallet_path()
    r = drive(mpc, path, VEHICLE, seed=3, noise=NOISE, slip=0.01)
    check_final(r, path)
    assert float(np.abs(r.lateral).max()) <= 0.05


def test_mpc_reverses_out_stops_and_drives_on(mpc):
    path = reverse_out_path()
    assert [seg.direction for seg in path.segments] == [-1, 1]
    r = drive(mpc, path, VEHICLE, seed=4, noise=NOISE, slip=0.01)
    check_final(r, path)
    assert float(np.abs(r.lateral).max()) <= 0.05


def test_mpc_speed_and_steering_commands_respect_the_limits(mpc):
    path = arc_path()
    mpc.start(path)
    from palletpilot.sim.forklift import SimForklift

    sim = SimForklift(VEHICLE, path.segments[0].start_pose)
    prev, t = 0.0, 0.0
    while t < 20.0:
        cmd = mpc.update(t, sim.state.pose, sim.state.v, sim.state.steering)
        if cmd.status is not FollowerStatus.RUNNING:
            break
        assert 0.0 <= cmd.speed <= min(VEHICLE.max_speed_forward, 0.8) + 1e-6
        assert abs(cmd.steering) <= VEHICLE.max_steering + 1e-9
        prev = sim.state.v
        sim.command(cmd.speed, cmd.steering)
        sim.step(0.05)
        assert sim.state.v - prev <= VEHICLE.max_accel * 0.05 + 1e-9
        t += 0.05
    assert cmd.status is FollowerStatus.SUCCEEDED


def test_pure_pursuit_baseline_reaches_the_pallet_node():
    pp = PurePursuitFollower(VEHICLE)
    path = pallet_path()
    r = drive(pp, path, VEHICLE, seed=3, noise=NOISE, slip=0.01)
    assert r.status == "succeeded"
    assert float(np.abs(r.lateral).max()) <= 0.1
    rev = drive(pp, reverse_out_path(), VEHICLE, seed=4, noise=NOISE, slip=0.01)
    assert rev.status == "succeeded"


def _drive_until_error(follower, path, ticks: int = 200):
    """Drive moving at 0.5 m/s; collect the commands until `ControlError`."""
    from palletpilot.sim.forklift import SimForklift

    sim = SimForklift(VEHICLE, path.segments[0].start_pose)
    sim.state.v = 0.5
    sim.speed_cmd = 0.5
    follower.start(path)
    commands = []
    for i in range(ticks):
        try:
            cmd = follower.update(i * 0.05, sim.state.pose, sim.state.v, sim.state.steering)
        except ControlError as exc:
            return commands, exc, sim
        commands.append((sim.state.v, cmd))
        sim.command(cmd.speed, cmd.steering)
        sim.step(0.05)
    return commands, None, sim


def test_infeasible_solve_brakes_then_raises_control_error():
    follower = MpcFollower(VEHICLE, MpcConfig(solve_deadline_s=None), FollowerConfig(max_failures=3))
    path = straight()
    follower.start(path)
    original = follower._start_segment

    def infeasible(track):
        original(track)
        follower._lbg[NZ_ACCEL_ROW] = 1.0  # speed change >= 1 m/s in one step and <= 0.05: infeasible
        follower._ubg[NZ_ACCEL_ROW] = -1.0

    follower._start_segment = infeasible
    commands, exc, sim = _drive_until_error(follower, path)
    assert exc is not None and "3 consecutive failed" in str(exc)
    assert len(commands) == 2  # two braking ticks, the third failure raises
    for v_meas, cmd in commands:
        assert cmd.status is FollowerStatus.RUNNING
        assert cmd.speed < v_meas  # braking ...
        assert v_meas - cmd.speed <= VEHICLE.max_decel * 0.05 + 1e-9  # ... within the deceleration limit
    assert follower.status is FollowerStatus.FAILED
    after = follower.update(1.0, sim.state.pose, sim.state.v, sim.state.steering)
    assert after.status is FollowerStatus.FAILED and abs(after.speed) < abs(sim.state.v) + 1e-9


NZ_ACCEL_ROW = 5 + 5  # first acceleration row of g: after z_0 (5 rows) and the first dynamics rows (5)


def test_late_solve_counts_as_failure():
    follower = MpcFollower(VEHICLE, MpcConfig(solve_deadline_s=0.0), FollowerConfig(max_failures=2))
    commands, exc, _ = _drive_until_error(follower, straight())
    assert exc is not None and "late solve" in str(exc)
    assert len(commands) == 1 and commands[0][1].speed < commands[0][0]


def test_progress_check_raises_when_the_forklift_does_not_move():
    follower = PurePursuitFollower(VEHICLE, follower_config=FollowerConfig(progress_timeout_s=2.0))
    path = straight()
    follower.start(path)
    pose = path.segments[0].start_pose
    with pytest.raises(ControlError, match="no progress"):
        for i in range(100):  # the vehicle never moves (e.g. blocked, or the drive is off)
            cmd = follower.update(i * 0.05, pose, 0.0, 0.0)
            assert cmd.status is FollowerStatus.RUNNING and cmd.speed > 0
    assert follower.status is FollowerStatus.FAILED


def test_stop_and_restart():
    follower = PurePursuitFollower(VEHICLE)
    path = straight(2.0, 0.5)
    follower.start(path)
    follower.update(0.0, path.segments[0].start_pose, 0.0, 0.0)
    follower.stop()
    cmd = follower.update(0.05, path.segments[0].start_pose, 0.2, 0.0)
    assert cmd.status is FollowerStatus.FAILED and cmd.speed < 0.2
    r = drive(follower, path, VEHICLE, seed=5, noise=NOISE)
    assert r.status == "succeeded"


def test_unknown_solver_is_a_control_error():
    with pytest.raises(ControlError, match="unknown solver 'nope'"):
        MpcFollower(VEHICLE, MpcConfig(solver="nope"))

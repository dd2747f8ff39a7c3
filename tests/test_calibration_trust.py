"""Issue 37, point 5: a calibration states its untrusted axes, and the Pickup never enters with one.

Tapered blades with the nominal (box) forks file: the real calibration on simulated frames flags x; the
Pickup refuses without a trusted calibration of the truck, keeps x from one when the mount has not moved,
and refuses when it has.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from palletpilot.executor.apps.app import run_simulated
from palletpilot.executor.core.behaviour import Settings, TaskMemory
from palletpilot.executor.core.calibration_trust import LAST_GOOD_SOURCE, calibration_for_checks
from palletpilot.executor.core.errors import CALIBRATION_FAILED, TaskFailed
from palletpilot.executor.core.jobs import Jobs
from palletpilot.executor.core.pickup import CalibrateCamera
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception import wire
from palletpilot.perception.calibration import calibrate
from palletpilot.perception.calibration_io import (
    Calibration,
    CalibrationAxis,
    MountTolerance,
    keep_axes,
    load_calibration,
    mount_moved,
    save_calibration,
)
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.specs import ForkGeometry, PalletType, load_forks
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")
BOX = load_forks(MISSIONS / "forks.yaml").model_dump(exclude_unset=True, exclude={"taper_length", "tip_thickness"})
NOMINAL = ForkGeometry.model_validate(BOX)  # the nominal box, profile unknown (not measured)
TAPERED = ForkGeometry.model_validate({**BOX, "taper_length": 0.10, "tip_thickness": 0.018})  # the true blades
MOUNT = {"x": -0.05, "y": 0.01, "z": 0.5, "tilt_deg": 30.0, "pan_deg": 1.0, "roll_deg": 0.5}
X = CalibrationAxis.X


def scenario(tmp_path: Path, mount: dict[str, float], start: str = "c_w", seed: int = 0, pallets=()) -> Scenario:
    """The simulated truck with tapered blades (what the camera sees) and this camera mount."""
    path = tmp_path / "true_forks.yaml"
    path.write_text(yaml.safe_dump({k: v for k, v in TAPERED.model_dump().items() if v is not None}))
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": start,
            "seed": seed,
            "forks": str(path),
            "camera": {"mount": mount, "noise": {"label_noise": True}},
            "pallets": list(pallets),
        }
    )
    sc.folder = MISSIONS
    return sc


def pose(xyz: tuple[float, float, float], rpy_deg: tuple[float, float, float]) -> SE3:
    return SE3.from_xyz_rpy(xyz, np.radians(rpy_deg))


LEVEL = (-112.0, 0.3, -89.0)  # rpy_deg of a camera tilted 22 deg down


# -- the statement: axes, JSON, wire ----------------------------------------------------------------


def test_untrusted_tips_make_x_untrusted_and_the_json_keeps_it(tmp_path):
    cal = Calibration(pose((0.0, 0.0, 0.5), LEVEL), "model", {"tip_trusted": False}, ("fork tips cannot ...",))
    assert cal.untrusted_axes == {X} and not cal.trusted
    assert Calibration(cal.T_forklift_camera, "model", {"tip_trusted": True}).trusted
    assert Calibration(cal.T_forklift_camera, "paper", {}).untrusted_axes == {X}  # it never checks the tips
    doc = cal.to_json()
    assert doc["untrusted_axes"] == ["x"]
    assert load_calibration(save_calibration(tmp_path / "cal.json", cal)).untrusted_axes == {X}
    back = wire.calibration_from_json(json.loads(json.dumps(wire.calibration_to_json(cal))), "reply")
    assert back.untrusted_axes == {X}  # over the perception service's wire too
    # A file stating its axes is taken at its word; an old one without the key as its quality says.
    for quality, stated, expected in (({}, None, set()), ({"tip_trusted": False}, None, {X}), ({}, ["x"], {X})):
        old = {k: v for k, v in doc.items() if k != "untrusted_axes"} | {"quality": quality}
        if stated is not None:
            old["untrusted_axes"] = stated
        (tmp_path / "old.json").write_text(json.dumps(old))
        assert load_calibration(tmp_path / "old.json").untrusted_axes == expected, (quality, stated)


def test_an_unknown_axis_in_the_file_is_one_line_naming_the_field(tmp_path):
    doc = Calibration(pose((0.0, 0.0, 0.5), LEVEL), "model").to_json() | {"untrusted_axes": ["x", "depth"]}
    (tmp_path / "cal.json").write_text(json.dumps(doc))
    with pytest.raises(PerceptionError) as info:
        load_calibration(tmp_path / "cal.json")
    lines = str(info.value).splitlines()
    assert len(lines) == 1 and "cal.json" in lines[0] and "untrusted_axes" in lines[0], lines


def test_keep_axes_takes_only_the_untrusted_axes_and_mount_moved_names_the_axes():
    reference = Calibration(pose((-0.05, 0.010, 0.500), LEVEL), "model", {"tip_trusted": True})
    new = Calibration(pose((0.04, 0.012, 0.503), (-112.1, 0.35, -89.05)), "model", {"tip_trusted": False})
    assert mount_moved(new, reference, MountTolerance()) == []
    combined = keep_axes(new, reference, "the file")
    assert combined.trusted and combined.untrusted_axes == frozenset()
    assert combined.T_forklift_camera.t == pytest.approx([-0.05, 0.012, 0.503])  # x kept, y and z measured
    assert combined.T_forklift_camera.rotation.approx_equal(new.T_forklift_camera.rotation, atol=1e-12)
    assert combined.quality["kept_axes"]["x"] == {"source": "the file", "value_m": -0.05, "measured_m": 0.04}
    # Journalled or sent with its quality, it stays trusted (the kept axis is recorded there).
    assert Calibration(combined.T_forklift_camera, "model", combined.quality).trusted
    moved = Calibration(pose((0.04, 0.012, 0.509), (-113.0, 0.3, -89.0)), "model", {"tip_trusted": False})
    problems = mount_moved(moved, reference, MountTolerance())
    assert [p.split()[0] for p in problems] == ["z", "roll"], problems  # x is not compared: untrusted
    with pytest.raises(PerceptionError, match="does not trust x either"):
        keep_axes(new, new, "itself")


# -- the real calibration on simulated frames of tapered blades ---------------------------------------


def test_tapered_blades_with_the_nominal_file_keep_x_from_a_measured_calibration(tmp_path):
    sim = Simulator(scenario(tmp_path, MOUNT))
    truth = sim.T_forklift_camera_true
    measured = calibrate([sim.grab()], TAPERED)  # commissioning: the blades measured (`forks measure`)
    assert measured.trusted and abs(measured.T_forklift_camera.t[0] - truth.t[0]) < 0.005
    # Later, at another place, with a forks file stating only the nominal box:
    other = Simulator(scenario(tmp_path, MOUNT, start="j_drop", seed=7))
    nominal = calibrate([other.grab()], NOMINAL)
    assert nominal.untrusted_axes == {X} and nominal.warnings
    assert nominal.T_forklift_camera.t[0] - truth.t[0] > 0.04  # off by about the taper
    assert mount_moved(nominal, measured, MountTolerance()) == []
    combined = keep_axes(nominal, measured, "commissioning")
    assert np.all(np.abs(combined.T_forklift_camera.t - truth.t) < 0.005)
    # The camera knocked: 1 deg more tilt. Its trusted axes disagree with the measured calibration.
    knocked = Simulator(scenario(tmp_path, MOUNT | {"tilt_deg": 31.0}, start="j_drop", seed=7))
    problems = mount_moved(calibrate([knocked.grab()], NOMINAL), measured, MountTolerance())
    assert any(p.startswith("roll") for p in problems), problems


# -- the Pickup's decision: CalibrateCamera -------------------------------------------------------------


class FakePerception:
    """Returns the calibrations given, in turn; `last_good` as a calibrating service keeps it."""

    def __init__(self, *results: Calibration, last_good: Calibration | None = None) -> None:
        self.results = list(results)
        self.last_good = last_good

    def calibrate(self, frames: Any) -> Calibration:
        self.last_good = self.results.pop(0)
        return self.last_good


@pytest.fixture(scope="module")
def frame_and_truth(tmp_path_factory):
    sim = Simulator(scenario(tmp_path_factory.mktemp("frame"), MOUNT | {"tilt_deg": 22.0}))
    return sim.grab(), sim.T_forklift_camera_true


def calibrate_in_pickup(ctx: SimpleNamespace) -> Calibration:
    """Run `CalibrateCamera` to its end on the fake context; the calibration it uses (or `TaskFailed`)."""
    state = CalibrateCamera()
    state.start(ctx)
    for _ in range(20):
        if state.update(ctx) == "done":
            return ctx.memory.calibration
        ctx.t += 0.05
    raise AssertionError("CalibrateCamera did not finish")


def context(frame, perception: FakePerception) -> SimpleNamespace:
    ctx = SimpleNamespace(t=0.0, events=[], memory=TaskMemory("floor_b2_pre", 0.0, last_motion_s=-1.0))
    ctx.vehicle = SimpleNamespace(speed=0.0, stop=lambda: None)
    ctx.perception, ctx.settings = perception, Settings()
    ctx.forks, ctx.pallet_type = load_forks(MISSIONS / "forks.yaml"), PalletType.eur()
    ctx.clock_now = lambda: ctx.t
    ctx.jobs = Jobs(deterministic=True, now=ctx.clock_now)
    ctx.frame = lambda: frame
    ctx.log = lambda name, **fields: ctx.events.append((name, fields))
    return ctx


def untrusted_like(T: SE3, dx: float = 0.08) -> Calibration:
    """What tapered blades with the nominal file give: x `dx` too far forward, the tips untrusted."""
    warning = "fork tips cannot be trusted: ... Measure the blade profile near the tips ..."
    return Calibration(SE3(T.rotation, T.t + np.array([dx, 0.0, 0.0])), "model", {"tip_trusted": False}, (warning,))


def test_the_pickup_refuses_an_untrusted_x_without_a_trusted_calibration(frame_and_truth):
    frame, truth = frame_and_truth
    ctx = context(frame, FakePerception(untrusted_like(truth), untrusted_like(truth)))
    with pytest.raises(TaskFailed) as info:
        calibrate_in_pickup(ctx)
    assert info.value.reason == CALIBRATION_FAILED
    assert "not trusted in x" in str(info.value) and "no earlier trusted calibration" in str(info.value)
    assert "Measure the blade profile" in str(info.value)  # the warning's text: what to do
    assert ctx.memory.calibration is None and ctx.memory.record["calibration_refused"]["axes"] == ["x"]
    # It looked again first (a few noisy pixels past the tips may trip the check once); a taper trips it again.
    assert [name for name, _ in ctx.events] == ["calibration_untrusted", "calibration_refused"]


def test_the_pickup_takes_another_look_when_the_tips_are_untrusted_once(frame_and_truth):
    frame, truth = frame_and_truth
    trusted = Calibration(truth, "model", {"tip_trusted": True})
    ctx = context(frame, FakePerception(untrusted_like(truth), trusted))
    assert calibrate_in_pickup(ctx) is trusted
    assert [name for name, _ in ctx.events][:2] == ["calibration_untrusted", "calibrated"]
    assert ctx.memory.trusted_calibration is not None and ctx.memory.trusted_calibration[0] is trusted


@pytest.mark.parametrize("from_this_run", [False, True])
def test_the_pickup_keeps_x_from_a_trusted_calibration_of_the_unmoved_mount(frame_and_truth, from_this_run):
    frame, truth = frame_and_truth
    near = SE3(truth.rotation, truth.t + np.array([0.001, -0.001, 0.002]))  # measured with the blades' profile
    trusted = Calibration(near, "model", {"tip_trusted": True})
    new = untrusted_like(truth)
    if from_this_run:  # an earlier pickup of this run calibrated with every axis trusted
        ctx = context(frame, FakePerception(trusted, new))
        assert calibrate_in_pickup(ctx) is trusted and ctx.memory.trusted_calibration[0] is trusted
        source = ctx.memory.trusted_calibration[1]
        assert "this run's calibration" in source
    else:  # the service's last good calibration (as a calibration file loaded at start seeds it)
        ctx = context(frame, FakePerception(new, last_good=trusted))
        source = LAST_GOOD_SOURCE
    ctx.events.clear()
    used = calibrate_in_pickup(ctx)
    assert used.trusted and used.T_forklift_camera.t[0] == pytest.approx(truth.t[0] + 0.001)
    assert used.T_forklift_camera.t[1:] == pytest.approx(new.T_forklift_camera.t[1:])
    kept = dict(ctx.events)["calibration_axis_kept"]
    assert (
        kept["axes"] == ["x"]
        and kept["source"] == source
        and kept["x"]["measured_m"] == pytest.approx(truth.t[0] + 0.08, abs=1e-6)
    )
    assert ctx.memory.record["calibration_axis_kept"] == kept
    assert ctx.memory.record["calibrations"][-1]["untrusted_axes"] == []
    assert ctx.memory.trusted_calibration == (trusted, source)  # a combined calibration never becomes the reference


def test_a_paper_calibration_is_no_reference_for_x(frame_and_truth):
    frame, truth = frame_and_truth
    paper = Calibration(truth, "paper", {})  # e.g. `calibrate --method paper --out cal.json` loaded at start
    ctx = context(frame, FakePerception(untrusted_like(truth), untrusted_like(truth), last_good=paper))
    with pytest.raises(TaskFailed, match="no earlier trusted calibration"):
        calibrate_in_pickup(ctx)


def test_the_pickup_refuses_when_the_mount_moved_since_the_trusted_calibration(frame_and_truth):
    frame, truth = frame_and_truth
    moved = pose(truth.t, np.degrees(truth.to_xyz_rpy()[1]) + np.array([0.0, 0.5, 0.0]))  # pitched 0.5 deg since
    trusted = Calibration(moved, "model", {"tip_trusted": True})
    ctx = context(frame, FakePerception(untrusted_like(truth), last_good=trusted))
    with pytest.raises(TaskFailed) as info:
        calibrate_in_pickup(ctx)
    assert info.value.reason == CALIBRATION_FAILED and "the mount has moved" in str(info.value)
    assert "pitch differs by -0.5 deg (tolerance 0.3 deg)" in str(info.value)
    assert ctx.memory.record["calibration_refused"]["source"] == LAST_GOOD_SOURCE


def test_checks_outside_the_pickup_never_take_an_untrusted_axis_either(frame_and_truth):
    frame, truth = frame_and_truth
    trusted = Calibration(truth, "model", {"tip_trusted": True})
    untrusted = untrusted_like(truth)
    knocked = untrusted_like(pose(truth.t, np.degrees(truth.to_xyz_rpy()[1]) + np.array([0.0, 0.5, 0.0])))
    ctx = context(frame, FakePerception(last_good=untrusted))
    assert calibration_for_checks(ctx) is None  # nothing trusted: no camera check
    ctx.memory.trusted_calibration = (trusted, "commissioning")
    kept = calibration_for_checks(ctx)
    assert kept is not None and kept.trusted and kept.T_forklift_camera.t == pytest.approx(truth.t)
    ctx.perception.last_good = knocked
    assert calibration_for_checks(ctx) is None  # the mount moved since
    ctx.perception.last_good = trusted
    assert calibration_for_checks(ctx) is trusted
    ctx.memory.calibration = kept
    assert calibration_for_checks(ctx) is kept  # the task's own


# -- a whole simulated Pickup: the real calibration, tapered blades, the nominal forks file -----------


def _mission(tmp_path: Path) -> Path:
    path = tmp_path / "mission.yaml"
    tasks = [{"type": "pickup", "node": "floor_b2"}]
    path.write_text(yaml.safe_dump({"name": "taper", "map": str(MISSIONS / "warehouse.yaml"), "tasks": tasks}))
    return path


@pytest.mark.parametrize("seeded", [False, True])
def test_a_simulated_pickup_with_unmeasured_tapered_blades(tmp_path, seeded):
    """Without a trusted calibration the Pickup refuses before lifting anything; with the blades' measured
    calibration of this mount loaded (as `robot --calibration` seeds the service), it keeps x and picks."""
    mount = {"tilt_deg": 22.0, "pan_deg": 0.8, "roll_deg": -0.5}
    sc = scenario(tmp_path, mount, start="floor_b2_pre", seed=3, pallets=[{"node": "floor_b2"}])
    sim = Simulator(sc)
    measured = calibrate([sim.grab()], TAPERED)  # commissioning, the same camera
    assert measured.trusted

    def nominal_forks_file(runner) -> None:
        runner.ctx.perception.calibrator.forks = NOMINAL  # the truck's forks file: the nominal box
        if seeded:
            runner.ctx.perception.calibrator.last_good = measured

    r = run_simulated(
        _mission(tmp_path), scenario=sc, report_dir=tmp_path / "report", on_start=nominal_forks_file, labels="truth"
    )
    task = r.summary["tasks"][0]
    events = [json.loads(x)["event"] for x in (tmp_path / "report" / "events.jsonl").read_text().splitlines()]
    record = json.loads((tmp_path / "report" / "report.json").read_text())["tasks"][0]
    if not seeded:
        assert task["result"] == "failed" and task["reason"] == CALIBRATION_FAILED, task
        assert "calibration_refused" in events and "raise_forks" not in str(events)
        assert not r.sim.pallets[0].carried
        return
    assert r.success and r.sim.pallets[0].carried, task
    assert "calibration_axis_kept" in events and record["calibration_axis_kept"]["source"] == LAST_GOOD_SOURCE
    used = record["calibrations"][0]
    assert abs(used["xyz_m"][0] - r.sim.T_forklift_camera_true.t[0]) < 0.005
    assert used["quality"]["kept_axes"]["x"]["measured_m"] - used["xyz_m"][0] > 0.04
    assert math.isclose(used["xyz_m"][0], measured.T_forklift_camera.t[0], abs_tol=1e-6)

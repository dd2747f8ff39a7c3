"""Tapered fork blades (ISO 2328): the profile in the forks file, the simulator, calibration and `forks measure`."""

import json

import numpy as np
import pytest
import yaml

from palletpilot.cli import main
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration import calibrate
from palletpilot.perception.calibration_io import mount_angles
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import save_bundle
from palletpilot.perception.specs import ForkGeometry, load_forks
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator
from palletpilot.sim.world import forks_mesh

MISSIONS = bundled_path("missions")
NOMINAL = load_forks(MISSIONS / "forks.yaml")
TAPER = {"taper_length": 0.1, "tip_thickness": 0.018}


def blades(**profile) -> ForkGeometry:
    return ForkGeometry.model_validate({**NOMINAL.model_dump(), **profile})


def render(tmp_path, true: ForkGeometry, lift: float = 0.0, seed: int = 0, noise: bool = True, **mount):
    path = tmp_path / f"true_forks_{seed}.yaml"
    path.write_text(yaml.safe_dump({k: v for k, v in true.model_dump().items() if v is not None}))
    mount = {"x": -0.1, "y": 0.01, "z": 0.45, "tilt_deg": 25.0, "pan_deg": 1.0, "roll_deg": 0.5, **mount}
    quiet = {"depth_noise": False, "label_noise": False, "rgb_sigma": 0.0, "lighting_variation": False}
    camera = {"mount": mount, "noise": {"label_noise": True} if noise else quiet}
    sc = Scenario.model_validate(
        {"map": "warehouse.yaml", "start": "c_w", "seed": seed, "forks": str(path), "camera": camera}
    )
    sc.folder = MISSIONS
    sim = Simulator(sc)
    if lift:
        sim.forklift.command_fork_height(lift)
        sim.forklift.state.fork_height = lift
    return sim.grab(), sim.T_forklift_camera_true


def errors(T_est: SE3, T_true: SE3):
    dt = (T_est.t - T_true.t) * 1e3
    return dt, np.degrees(np.array(mount_angles(T_est)) - np.array(mount_angles(T_true)))


def test_profile_fields_default_to_the_box_and_are_checked():
    assert not NOMINAL.tapered and NOMINAL.taper_length == 0.0 and NOMINAL.tip_thickness is None
    assert NOMINAL.tip_top_z == NOMINAL.thickness
    f = blades(**TAPER)
    assert f.tapered and f.tip_top_z == pytest.approx(0.018)
    assert f.top_z(f.tip_x - 0.05) == pytest.approx(0.034)
    assert blades(**TAPER, taper_side="bottom").bottom_z(f.tip_x) == pytest.approx(0.032)
    assert blades(heel_radius=0.02).top_z(NOMINAL.heel_x) == pytest.approx(0.07)
    for bad, words in (
        ({"taper_length": 0.1}, "required with taper_length"),
        ({"tip_thickness": 0.02}, "needs taper_length > 0"),
        ({"taper_length": 0.1, "tip_thickness": 0.08}, "more than the blade thickness"),
        ({"taper_length": 0.9, "tip_thickness": 0.02}, "outside 0..0.5 m"),
        ({"taper_length": 0.1, "tip_thickness": 0.001}, "outside 0.003..0.2 m"),
        ({"heel_radius": 0.3}, "outside 0..0.2 m"),
        ({"taper_length": 0.1, "tip_thickness": 0.02, "taper_side": "left"}, "taper_side"),
    ):
        with pytest.raises(ValueError, match=words):
            blades(**bad)


def test_the_simulator_renders_the_tapered_blade():
    f = blades(**TAPER, heel_radius=0.02)
    mesh = forks_mesh(f, 0.2, SE3.identity())
    near_tip = mesh.vertices[np.abs(mesh.vertices[:, 0] - f.tip_x) < 1e-9]
    assert near_tip[:, 2].max() == pytest.approx(0.2 + 0.018)
    assert mesh.vertices[:, 2].max() == pytest.approx(0.2 + 0.05 + 0.02)  # the heel fillet
    assert mesh.vertices[:, 2].min() == pytest.approx(0.2)


def test_a_tapered_blade_with_its_profile_in_the_file_calibrates_within_goal(tmp_path):
    true = blades(**TAPER)
    frame, truth = render(tmp_path, true)
    calib = calibrate([frame], true)
    dt, da = errors(calib.T_forklift_camera, truth)
    assert np.all(np.abs(dt) < 3.0), dt
    assert np.all(np.abs(da) < 0.2), da
    assert calib.quality["tip_trusted"] and not calib.warnings


def test_a_bottom_taper_with_the_nominal_box_in_the_file_calibrates_within_goal(tmp_path):
    frame, truth = render(tmp_path, blades(**TAPER, taper_side="bottom"))
    calib = calibrate([frame], NOMINAL)  # the top stays flat to the tip: the tips are where the box says
    dt, da = errors(calib.T_forklift_camera, truth)
    assert np.all(np.abs(dt) < 3.0) and np.all(np.abs(da) < 0.2), (dt, da)
    assert calib.quality["tip_trusted"]


def test_a_top_taper_with_the_nominal_box_in_the_file_warns_that_the_tips_cannot_be_trusted(tmp_path, capsys):
    frame, _ = render(tmp_path, blades(**TAPER))
    calib = calibrate([frame], NOMINAL)
    assert calib.quality["tip_trusted"] is False
    assert any("fork tips cannot be trusted" in w and "forks measure" in w for w in calib.warnings)
    assert calib.to_json()["warnings"] == list(calib.warnings)
    # `palletpilot calibrate` prints it on stderr and still writes the calibration.
    save_bundle(tmp_path / "f.npz", frame)
    out = tmp_path / "cal.json"
    code = main(["calibrate", str(tmp_path / "f.npz"), "--forks", str(MISSIONS / "forks.yaml"), "--out", str(out)])
    assert code == 0
    err = capsys.readouterr().err
    assert "warning: calibration: fork tips cannot be trusted" in err and "taper_length" in err
    assert json.loads(out.read_text())["warnings"]


def test_boxes_stay_trusted(tmp_path):
    frame, _ = render(tmp_path, NOMINAL)
    calib = calibrate([frame], NOMINAL)
    assert calib.quality["tip_trusted"] and not calib.warnings


def test_forks_measure_recovers_a_taper(tmp_path, capsys):
    # The camera looks down steeply (38 deg, 0.6 m up): well steeper than the taper's slope, as the
    # procedure asks (README "Camera calibration").
    true = blades(**TAPER)
    paths = []
    for seed, lift in ((0, 0.0), (1, 0.0), (2, 0.3)):
        frame, _ = render(tmp_path, true, lift=lift, seed=seed, tilt_deg=38.0, z=0.6, x=0.0)
        paths.append(tmp_path / f"f{seed}.npz")
        save_bundle(paths[-1], frame)
    out = tmp_path / "measured_forks.yaml"
    args = ["forks", "measure", *map(str, paths), "--forks", str(MISSIONS / "forks.yaml"), "--out", str(out)]
    assert main([*args, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    measured = load_forks(out)  # a valid forks file
    assert measured.taper_side == "top" and doc["taper_side"] == "top"
    assert measured.taper_length == pytest.approx(0.1, abs=0.006)
    assert measured.tip_thickness == pytest.approx(0.018, abs=0.003)
    assert measured.length == NOMINAL.length and measured.tip_x == NOMINAL.tip_x
    # ... and calibrating with it puts the camera within a few mm (no warning).
    frame, truth = render(tmp_path, true, seed=5)
    calib = calibrate([frame], measured)
    dt, _ = errors(calib.T_forklift_camera, truth)
    assert np.all(np.abs(dt) < 5.0) and calib.quality["tip_trusted"], dt


def test_forks_measure_reports_bad_inputs(tmp_path, capsys):
    (tmp_path / "bad.yaml").write_text("length: 1.15\n")
    code = main(
        [
            "forks",
            "measure",
            str(tmp_path / "none.npz"),
            "--forks",
            str(tmp_path / "bad.yaml"),
            "--out",
            str(tmp_path / "o.yaml"),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "none.npz" in err
    assert not (tmp_path / "o.yaml").exists()
    with pytest.raises(PerceptionError):
        load_forks(tmp_path / "bad.yaml")

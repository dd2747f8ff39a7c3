"""Depth tare: the camera's depth scale error measured against a flat wall, and removed before calibrating."""

import dataclasses
import json

import numpy as np
import pytest

from palletpilot.cli import main
from palletpilot.executor.adapters.local_perception import LocalPerception
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration import calibrate
from palletpilot.perception.depth_tare import DepthTare, correct_depth, load_tare, measure_depth_tare, save_tare
from palletpilot.perception.errors import CalibrationError, PerceptionError
from palletpilot.perception.frames import save_bundle
from palletpilot.perception.specs import load_forks
from palletpilot.sim.camera import CameraModel, CameraNoise, RaycastRenderer
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator
from palletpilot.sim.world import LabeledMesh, object_box_mesh, wall_mesh

MISSIONS = bundled_path("missions")
FORKS = load_forks(MISSIONS / "forks.yaml")
CAMERA = CameraModel.d435()
LOOK_X = SE3.from_matrix(np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, 0, 1]], dtype=float))
"""Camera at (0, 0, 1 m), looking along world x (optical z -> world x, optical y -> world -z)."""


def wall_frame(distance_m: float, scale: float, seed: int = 0, turn_deg=(0.0, 0.0, 0.0), extra=()):
    """A D435-noise frame of a wall `distance_m` ahead, with depth scale error `scale`."""
    meshes: list[LabeledMesh] = [wall_mesh((distance_m + 0.1, -5.0), (distance_m + 0.1, 5.0), height=6.0)]
    meshes += list(extra)
    noise = CameraNoise(depth_scale_error=0.0, lighting_variation=False)  # D435 noise, flying pixels, shadow
    rng = np.random.default_rng(seed)
    frame = RaycastRenderer(meshes).render(
        LOOK_X @ SE3.from_xyz_rpy((0, 0, 0), np.radians(turn_deg)), CAMERA, noise, rng
    )
    return scaled(frame, scale)


def scaled(frame, scale: float):
    """The frame as a camera with depth scale error `scale` sees it: every depth times 1 + scale."""
    return dataclasses.replace(frame, depth=(frame.depth * np.float32(1.0 + scale)).astype(np.float32))


@pytest.mark.parametrize(("distance", "scale"), [(1.2, 0.003), (2.5, -0.0025), (3.5, 0.001)])
def test_the_scale_error_of_a_noisy_d435_is_recovered(distance, scale):
    tare = measure_depth_tare([wall_frame(distance, scale, turn_deg=(2.0, -3.0, 1.0))], distance)
    assert tare.depth_scale_error == pytest.approx(scale, abs=2e-4)  # 0.02 %
    assert tare.wall_angle_deg == pytest.approx(np.hypot(2.0, 3.0), abs=0.5)
    assert tare.frames == 1 and tare.points > 0.8 * 320 * 240
    fixed = correct_depth(wall_frame(distance, scale), tare)
    centre = fixed.depth[220:260, 300:340]
    assert float(np.mean(centre[centre > 0])) == pytest.approx(distance, abs=0.002)


def test_a_bad_target_is_refused_with_the_reason():
    with pytest.raises(CalibrationError, match=r"turned 30\.0 deg"):
        measure_depth_tare([wall_frame(2.0, 0.0, turn_deg=(0.0, 30.0, 0.0))], 2.0 / np.cos(np.radians(30.0)))
    box = object_box_mesh(SE3.from_translation(1.5, 0.0, 0.0), (0.2, 0.3, 1.4))  # something in front of the wall
    with pytest.raises(CalibrationError, match=r"lies on one plane|is not flat"):
        measure_depth_tare([wall_frame(2.0, 0.0, extra=[box])], 2.0)
    with pytest.raises(CalibrationError, match=r"off the measured 2\.1000 m"):
        measure_depth_tare([wall_frame(2.0, 0.0)], 2.1)  # a wrong distance, not a camera
    with pytest.raises(CalibrationError, match="outside"):
        measure_depth_tare([wall_frame(2.0, 0.0)], 9.0)
    empty = RaycastRenderer([wall_mesh((30.0, -5.0), (30.0, 5.0))]).render(LOOK_X, CAMERA)  # beyond the range
    with pytest.raises(CalibrationError, match="has depth"):
        measure_depth_tare([empty], 2.0)


def fork_frame(scale: float):
    mount = {"x": -0.1, "y": 0.01, "z": 0.45, "tilt_deg": 25.0, "pan_deg": 1.0, "roll_deg": 0.5}
    noise = {"depth_noise": False, "label_noise": False, "rgb_sigma": 0.0, "lighting_variation": False}
    sc = Scenario.model_validate({"map": "warehouse.yaml", "start": "c_w", "camera": {"mount": mount, "noise": noise}})
    sc.folder = MISSIONS
    sim = Simulator(sc)
    frame = sim.grab()
    return scaled(frame, scale), sim.T_forklift_camera_true


def test_the_tare_removes_the_camera_offset_a_scale_error_causes(tmp_path, capsys):
    frame, truth = fork_frame(0.004)
    off = calibrate([frame], FORKS).T_forklift_camera.t[0] - truth.t[0]
    assert off < -0.003  # the camera put ~0.4 % of the tip distance too far back
    tare = measure_depth_tare([wall_frame(2.0, 0.004)], 2.0)
    fixed = calibrate([correct_depth(frame, tare)], FORKS).T_forklift_camera.t[0] - truth.t[0]
    assert abs(fixed) < 0.001
    # the same through LocalPerception, which every truck path uses
    local = LocalPerception(FORKS, depth_tare=tare)
    assert abs(local.calibrate([frame]).T_forklift_camera.t[0] - truth.t[0]) < 0.001

    # and through the command line: camera tare writes the file, calibrate --depth-tare applies it
    wall = save_bundle(tmp_path / "wall.npz", wall_frame(2.0, 0.004))
    forks = save_bundle(tmp_path / "forks.npz", frame)
    out = tmp_path / "tare.json"
    assert (
        main(["camera", "tare", str(wall), "--distance-m", "1.997", "--origin-offset-mm", "3", "--out", str(out)]) == 0
    )
    assert "depth scale error +0.39" in capsys.readouterr().out
    assert load_tare(out).depth_scale_error == pytest.approx(0.004, abs=2e-4)
    assert (
        main(["calibrate", str(forks), "--forks", str(MISSIONS / "forks.yaml"), "--json", "--depth-tare", str(out)])
        == 0
    )
    x = json.loads(capsys.readouterr().out)["xyz_m"][0]
    assert abs(x - truth.t[0]) < 0.001


def test_bad_tare_inputs_get_one_line_each(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(
        '{"depth_scale_error": 0.5, "distance_m": 2, "plane_distance_m": 3, "residual_rms_m": 0,'
        ' "points": 1, "frames": 1, "wall_angle_deg": 0, "extra": 1}'
    )
    with pytest.raises(PerceptionError) as info:
        load_tare(bad)
    lines = info.value.problems
    assert len(lines) == 2 and all(line.startswith(str(bad)) for line in lines)
    assert any("depth_scale_error" in line for line in lines) and any("extra" in line for line in lines)
    frame = save_bundle(tmp_path / "f.npz", fork_frame(0.0)[0])
    assert main(["calibrate", str(frame), "--forks", str(MISSIONS / "forks.yaml"), "--depth-tare", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.json" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as exit_info:
        main(["camera", "tare", str(frame), "--distance-m", "0"])
    assert exit_info.value.code == 2 and "--distance-m: must be in 0.3..20 m" in capsys.readouterr().err
    assert main(["camera", "tare", str(tmp_path / "missing.npz"), "--distance-m", "2"]) == 2
    assert "missing.npz" in capsys.readouterr().err
    good = save_tare(tmp_path / "good.json", DepthTare(0.001, 2.0, 2.002, 0.01, 100, 1, 1.0))
    assert load_tare(good) == DepthTare(0.001, 2.0, 2.002, 0.01, 100, 1, 1.0)

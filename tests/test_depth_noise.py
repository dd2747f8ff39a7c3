"""Correlated depth noise (issue 37): the simulator's correlated mode, `camera noise` measuring the correlation
area from still frames into the camera file, and the pallet spread widened by it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from palletpilot.bench.pallet import FrameSpec, render
from palletpilot.cli import main
from palletpilot.geometry import SE3
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.depth_noise import measure_depth_correlation
from palletpilot.perception.depth_tare import DepthTare, load_tare, save_tare
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, save_bundle
from palletpilot.perception.pallet import estimate_pallet, estimator_config
from palletpilot.sim.camera import CameraModel, CameraNoise, RaycastRenderer
from palletpilot.sim.world import wall_mesh

CAMERA = CameraModel.d435(320, 240)
LOOK_X = SE3.from_matrix(np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, 0, 1]], dtype=float))


def _stills(area_px: float, n: int = 3, camera: CameraModel = CAMERA) -> list[FrameBundle]:
    """`n` frames of a wall 2 m ahead from a still camera whose depth noise is correlated over `area_px`."""
    renderer = RaycastRenderer([wall_mesh((2.1, -5.0), (2.1, 5.0), height=6.0)])
    noise = CameraNoise(depth_scale_error=0.0, lighting_variation=False, depth_correlation_px=area_px)
    rng = np.random.default_rng(1)
    return [renderer.render(LOOK_X, camera, noise, rng) for _ in range(n)]


@pytest.mark.parametrize("area", [1.0, 4.0, 16.0])
def test_the_measured_correlation_area_is_the_simulated_one(area):
    noise = measure_depth_correlation(_stills(area))
    assert noise.depth_correlation_px == pytest.approx(area, rel=0.15)
    assert noise.frames == 3 and noise.pixels > 0.9 * CAMERA.width * CAMERA.height
    # The per-pixel noise is the D435's whatever the correlation: 0.08 px of disparity at f B.
    assert noise.inverse_depth_sigma == pytest.approx(0.08 / (CAMERA.depth_focal_px * 0.05), rel=0.1)


def test_camera_noise_writes_the_area_into_the_camera_file(tmp_path, capsys):
    paths = []
    for k, frame in enumerate(_stills(9.0)):
        paths.append(str(save_bundle(tmp_path / f"still{k}.npz", frame)))
    tare = tmp_path / "tare.json"
    save_tare(tare, DepthTare(0.001, 1.5, 1.5015, 0.002, 1000, 2, 1.0))
    assert main(["camera", "noise", *paths, "--into", str(tare), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)["depth_correlation_px"]
    kept = load_tare(tare)
    assert kept.depth_correlation_px == pytest.approx(printed, abs=0.01) and 7.5 < printed < 10.5
    assert kept.depth_scale_error == 0.001  # the tare itself is kept
    assert main(["camera", "noise", paths[0]]) == 2
    assert "needs two or more frames" in capsys.readouterr().err
    assert main(["camera", "noise", *paths, "--into", str(tmp_path / "none.json")]) == 2
    with pytest.raises(PerceptionError, match="differ in size"):
        measure_depth_correlation(_stills(1.0, 1) + _stills(1.0, 1, CameraModel.d435(160, 120)))


def test_the_spread_widens_by_the_root_of_the_correlation_area():
    spec = FrameSpec("floor_b2", loaded=True, dx=0.02, dy=0.05, dyaw_deg=3.0, ahead=2.0, seed=7)
    frame, _ = render(spec)
    cal = Calibration(SE3.from_matrix(frame.truth["T_forklift_camera_true"]), "true")
    one = estimate_pallet(frame, cal, config=estimator_config(False, 1.0))
    nine = estimate_pallet(frame, cal, config=estimator_config(False, 9.0))
    assert nine.T_forklift_pallet.t == pytest.approx(one.T_forklift_pallet.t)  # the pose is the same
    assert nine.spread.yaw_own_rad == pytest.approx(3.0 * one.spread.yaw_own_rad, rel=1e-6)
    assert nine.spread.x_own_m > 2.0 * one.spread.x_own_m  # the face distance is the plane fit's
    assert nine.spread.yaw_common_rad == one.spread.yaw_common_rad  # what frames share is not the pixels'
    assert math.isclose(estimator_config(True, 0.5).depth_correlation_px, 1.0)  # never below independent

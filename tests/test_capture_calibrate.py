"""From a RealSense recording to a calibration: extract bundles (no labels), segment, calibrate."""

import json

import numpy as np

from palletpilot.cli import main
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration_io import mount_angles
from palletpilot.perception.frames import load_bundle
from palletpilot.perception.realsense_synthetic import write_software_recording
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")


def test_calibrate_runs_on_bundles_extracted_from_a_recording(tmp_path, capsys):
    sc = Scenario.model_validate(
        {"map": "warehouse.yaml", "start": "c_w", "seed": 5, "camera": {"mount": {"tilt_deg": 24.0, "pan_deg": 1.2}}}
    )
    sc.folder = MISSIONS
    sim = Simulator(sc)
    frames = [sim.grab() for _ in range(3)]
    recording = write_software_recording(
        tmp_path / "forks.db3",
        [f.depth for f in frames],
        [f.rgb for f in frames],
        K_depth=frames[0].K,
        K_colour=frames[0].K,
    )
    out = tmp_path / "bundles"
    assert main(["capture", "--recording", str(recording), "--out", str(out)]) == 0
    bundles = sorted(out.glob("frame_*.npz"))
    assert len(bundles) == 3
    assert load_bundle(bundles[0]).labels is None  # a camera gives no labels: the shipped model segments
    capsys.readouterr()
    assert main(["calibrate", *map(str, bundles), "--forks", str(MISSIONS / "forks.yaml"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    truth = sim.T_forklift_camera_true
    assert np.allclose(doc["xyz_m"], truth.t, atol=0.005)
    tilt, pan, roll = (np.degrees(a) for a in mount_angles(truth))
    assert abs(doc["tilt_deg"] - tilt) < 0.2 and abs(doc["pan_deg"] - pan) < 0.2
    assert abs(doc["roll_about_optical_deg"] - roll) < 0.2
    assert doc["quality"]["frames_used"] == 3

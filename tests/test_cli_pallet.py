"""`palletpilot estimate-pallet` (executor.cli_pallet), driven through its own sub-parser."""

import argparse
import dataclasses
import json

import numpy as np
import pytest

from palletpilot.bench.pallet import FrameSpec, render
from palletpilot.executor.apps.cli_pallet import add_parsers
from palletpilot.geometry import SE3
from palletpilot.perception.calibration_io import Calibration, save_calibration
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import SemanticClass, save_bundle
from palletpilot.perception.pallet import PalletNotFound


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="palletpilot")
    add_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def frame():
    spec = FrameSpec("floor_b2", loaded=False, dx=0.0, dy=0.08, dyaw_deg=4.0, ahead=1.5, seed=3)
    return render(spec, noise=False)[0]


@pytest.fixture
def calib(tmp_path, frame):
    cal = Calibration(SE3.from_matrix(frame.truth["T_forklift_camera_true"]), "true")
    return str(save_calibration(tmp_path / "calib.json", cal))


def test_json_output(tmp_path, frame, calib, capsys):
    path = str(save_bundle(tmp_path / "frame.npz", frame))
    assert run(["estimate-pallet", path, "--calibration", calib, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert {"T_forklift_pallet", "x_m", "y_m", "z_m", "yaw_deg", "spread"} <= set(doc)
    T = np.array(doc["T_forklift_pallet"])
    truth = frame.truth["T_forklift_pallet_true"]
    assert T.shape == (4, 4) and np.allclose(T[:3, 3], truth[:3, 3], atol=2e-3)
    assert doc["x_m"] == pytest.approx(truth[0, 3], abs=1e-3) and doc["y_m"] == pytest.approx(truth[1, 3], abs=1e-3)
    assert doc["yaw_deg"] == pytest.approx(4.0, abs=0.05)
    assert set(doc["spread"]) == {"x_m", "y_m", "yaw_deg", "x_common_m", "y_common_m", "yaw_common_deg"}


def test_text_output(tmp_path, frame, calib, capsys):
    path = str(save_bundle(tmp_path / "frame.npz", frame))
    assert run(["estimate-pallet", path, "--calibration", calib]) == 0
    assert capsys.readouterr().out.startswith("pallet at x ")


def test_not_found_propagates_as_pallet_not_found(tmp_path, frame, calib):
    labels = np.where(np.isin(frame.labels, (7, 8)), SemanticClass.DRIVABLE, frame.labels).astype(np.uint8)
    path = str(save_bundle(tmp_path / "empty.npz", dataclasses.replace(frame, labels=labels)))
    with pytest.raises(PalletNotFound, match="too few points") as info:
        run(["estimate-pallet", path, "--calibration", calib, "--labels", "model"])
    assert str(info.value).startswith(f"{path}: pallet not found") and "\n" not in str(info.value)
    assert info.value.reason == "too_few_points"


def test_without_labels_or_rgb_the_model_mode_says_labels_are_needed(tmp_path, frame, calib):
    path = str(save_bundle(tmp_path / "bare.npz", dataclasses.replace(frame, labels=None, rgb=None)))
    with pytest.raises(PerceptionError, match="labels"):
        run(["estimate-pallet", path, "--calibration", calib, "--labels", "model"])


@pytest.mark.parametrize("mode", ["geometry", "fused"])
def test_without_labels_or_rgb_geometry_finds_the_pallet(tmp_path, frame, calib, mode, capsys):
    # Depth alone: the default (fused) and geometry modes need no labels and no RGB.
    path = str(save_bundle(tmp_path / "bare.npz", dataclasses.replace(frame, labels=None, rgb=None)))
    run(["estimate-pallet", path, "--calibration", calib, "--labels", mode, "--json"])
    doc = json.loads(capsys.readouterr().out)
    truth = frame.truth["T_forklift_pallet_true"]
    assert doc["x_m"] == pytest.approx(truth[0, 3], abs=0.01) and doc["y_m"] == pytest.approx(truth[1, 3], abs=0.005)


def test_bad_calibration_file_is_a_perception_error(tmp_path, frame):
    path = str(save_bundle(tmp_path / "frame.npz", frame))
    bad = tmp_path / "calib.json"
    bad.write_text("{}")
    with pytest.raises(PerceptionError, match="not a calibration file"):
        run(["estimate-pallet", path, "--calibration", str(bad)])


def test_every_input_is_checked_before_any_work(tmp_path, frame, monkeypatch):
    import palletpilot.perception.pallet as pallet_module

    monkeypatch.setattr(pallet_module, "estimate_pallet", lambda *a, **k: pytest.fail("work started"))
    with np.load(save_bundle(tmp_path / "good.npz", frame)) as data:
        arrays = {key: data[key] for key in data.files}
    arrays["K"][0, 0] = 1e-3  # the tiny focal length that once asked for 387 TiB
    path = str(tmp_path / "frame.npz")
    np.savez_compressed(path, **arrays)
    cal = tmp_path / "calib.json"
    cal.write_text('{"T_forklift_camera": [[1, 0, 0, 1e6], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}')
    pallet = tmp_path / "pallet.yaml"
    pallet.write_text("width: 50\n")
    vehicle = tmp_path / "vehicle.yaml"
    vehicle.write_text("wheelbase: [\n")
    argv = ["estimate-pallet", path, "--calibration", str(cal), "--pallet", str(pallet), "--vehicle", str(vehicle)]
    with pytest.raises(PerceptionError) as info:
        run(argv)
    problems = info.value.problems
    assert [p.split(": ")[0] for p in problems] == [str(vehicle), path, path, str(cal), str(pallet)]
    assert "K: fx 0.001 px is implausible" in problems[1] and "1e+06 m from the forklift origin" in problems[3]
    assert all("\n" not in p for p in problems) and str(info.value).startswith(f"{vehicle}: ")


def test_vehicle_mast_range_checks_the_fork_height(tmp_path, frame, calib):
    from palletpilot.geometry.fileio import bundled_path

    vehicle = str(bundled_path("missions", "forklift.yaml"))
    high = str(save_bundle(tmp_path / "high.npz", dataclasses.replace(frame, fork_height=3.0)))
    with pytest.raises(PerceptionError, match=r"high\.npz: fork_height: 3 m is outside the mast's range 0\.\.2 m"):
        run(["estimate-pallet", high, "--calibration", calib, "--vehicle", vehicle])
    path = str(save_bundle(tmp_path / "frame.npz", frame))
    assert run(["estimate-pallet", path, "--calibration", calib, "--vehicle", vehicle]) == 0

"""The `palletpilot` CLI: map, plan and bench commands; exit codes and one-line errors."""

import json

import pytest

from palletpilot.cli import main
from palletpilot.geometry.fileio import bundled_path

MISSIONS = bundled_path("missions")
MAP = str(MISSIONS / "warehouse.yaml")


def test_map_check_ok(capsys):
    assert main(["map", "check", MAP]) == 0
    assert "ok (44 nodes" in capsys.readouterr().out


def test_map_check_lists_problems_and_exits_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "nodes:\n"
        "  - {id: a, type: waypoint, x: 0, y: 0, yaw_deg: 0}\n"
        "  - {id: a, type: waypoint, x: 1, y: 0, yaw_deg: 0}\n"
        "edges:\n"
        "  - {from: a, to: b}\n"
    )
    assert main(["map", "check", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"{bad}: duplicate node id 'a'", f"{bad}: edge 'a->b': unknown node 'b'"]


def test_map_check_uses_the_given_vehicle(tmp_path, capsys):
    vehicle = tmp_path / "tight.yaml"
    text = (MISSIONS / "forklift.yaml").read_text().replace("max_steering_deg: 60", "max_steering_deg: 20")
    vehicle.write_text(text)
    assert main(["map", "check", MAP, "--vehicle", str(vehicle)]) == 2
    assert "above the vehicle's limit" in capsys.readouterr().err


def test_bad_vehicle_file_is_one_line(tmp_path, capsys):
    vehicle = tmp_path / "v.yaml"
    vehicle.write_text("wheelbase: -1\n")
    assert main(["map", "check", MAP, "--vehicle", str(vehicle)]) == 2
    err = capsys.readouterr().err
    assert "wheelbase: Input should be greater than 0" in err
    assert "Traceback" not in err


def test_plan_json(capsys):
    assert main(["plan", MAP, "charger", "rack_b3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"nodes", "edges", "length_m"}
    assert out["nodes"][0] == "charger" and out["nodes"][-1] == "rack_b3"
    assert len(out["edges"]) == len(out["nodes"]) - 1
    assert out["edges"][0]["direction"] == "reverse"
    assert out["length_m"] == pytest.approx(sum(e["length_m"] for e in out["edges"]), abs=1e-3)


def test_plan_unknown_node_is_one_line(capsys):
    assert main(["plan", MAP, "charger", "nowhere"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"{MAP}: unknown node 'nowhere'"]


def test_map_show_writes_a_png(tmp_path, capsys):
    out = tmp_path / "route.png"
    assert main(["map", "show", MAP, "--route", "charger", "rack_b3", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_roadmap_prints_its_figures(capsys):
    assert main(["bench", "roadmap", "--json", "--rows", "20", "--cols", "20", "--queries", "5"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["nodes"] == 400
    assert out["queries"] == 5 and out["plan_ms_median"] > 0


def test_bench_faults_prints_its_safety_figures(capsys):
    assert main(["bench", "faults", "--json", "--runs", "2", "--seed", "4", "--kill-rate", "0"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["runs"] == 2 and out["kill_runs"] == 0 and sum(out["faults_fired"].values()) >= 1
    assert out["collisions"] == 0 and out["unstopped_failures"] == 0 and out["invalid_reports"] == 0
    assert sum(out["reasons"].values()) == out["outcomes"]["failed"]
    assert {"p50", "p99", "max", "n"} <= set(out["fault_to_standstill_s"])


def test_unknown_bench(capsys):
    assert main(["bench", "nope"]) == 2
    assert "unknown benchmark 'nope'" in capsys.readouterr().err


def test_bench_pallet_reports_frames_and_fused_estimates(capsys):
    assert main(["bench", "pallet", "--json", "--frames", "2", "--seed", "5", "--frames-per-estimate", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    case = out["cases"]["labels=gt,calibration=true"]
    assert out["standpoints"] == 2 and case["frames"] == 4
    assert case["detection_rate"] == 1.0 and case["per_estimate"]["estimates"] == 2
    # Small errors, both per frame and fused: the figures come from real estimates against the truth.
    assert 0 < case["lateral_mm"]["max"] < 10 and 0 < case["per_estimate"]["yaw_deg"]["max"] < 1.0


@pytest.mark.parametrize(
    "option, message",
    [
        (["--labels", "foo"], "argument --labels: unknown 'foo' (known: gt,onnx,model,geometry,fused)"),
        (["--frames-per-estimate", "0"], "argument --frames-per-estimate: must be an integer in 1..100, got '0'"),
    ],
)
def test_bench_pallet_bad_option_is_one_line(option, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["bench", "pallet", *option])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and err[0].startswith("palletpilot bench pallet: ")

"""The campaign report of `palletpilot test` (`executor.apps.suite_campaign`): per family the coverage of
what it drew against the outcome, the failing and slowest runs with their paths; on a tiny suite."""

import json
from pathlib import Path

import yaml

from palletpilot.cli import main
from palletpilot.executor.apps.suite import load_suite
from palletpilot.executor.apps.suite_campaign import Parameter, Unit, campaign_json
from palletpilot.executor.apps.suite_run import RunResult
from palletpilot.geometry.fileio import bundled_path

SUITE = bundled_path("missions", "suite")
PERSON = {"kind": "person", "x": 20.0, "y": 11.0, "yaw_deg": 0}  # on aisle B's route: the truck stops
BOX = {"kind": "box", "x": 23.0, "y": 9.0, "yaw_deg": 15, "size": [0.6, 0.4, 0.5]}  # beside it


def _tiny(folder: Path) -> Path:
    """Aisle B driven 4 times with a person or a box drawn (seed 4: box, person, box, none) and tilts,
    plus a refusal; every file beside the example suite's."""
    (folder / "aisle.yaml").write_text(
        yaml.safe_dump({"map": str(SUITE.parent / "warehouse.yaml"), "forks": str(SUITE.parent / "forks.yaml")})
        + "seed: 5\nstart: b1\n"
    )
    family = {
        "base": "aisle.yaml",
        "runs": 4,
        "seed": 4,
        "mount": {"tilt_deg": [18, 26]},
        "clutter": {"count": [0, 1], "choose": [PERSON, BOX]},
    }
    cases = [
        {"name": "aisle_b", "mission": str(SUITE / "move_b_top.yaml"), "family": family},
        {"name": "unknown_node", "mission": str(SUITE / "bad_unknown_node.yaml"), "expect": "rejected"},
    ]
    path = folder / "tiny.yaml"
    path.write_text(yaml.safe_dump({"name": "tiny", "cases": cases}))
    return path


def test_a_tiny_campaign_reports_coverage_failures_and_the_slowest_runs(tmp_path, capsys):
    report = tmp_path / "report"
    assert main(["test", str(_tiny(tmp_path)), "--report", str(report)]) == 1
    assert "(suite.json, campaign.json, CASE/K/report.json)" in capsys.readouterr().out
    doc = json.loads((report / "campaign.json").read_text())
    assert (doc["suite"], doc["runs"], doc["met"], doc["failing_total"]) == ("tiny", 5, 4, 1)
    assert list(doc["families"]) == ["aisle_b"]  # a plain case is no family
    fam = doc["families"]["aisle_b"]
    assert (fam["runs"], fam["met"], fam["outcomes"], fam["seed"]) == (4, 3, {"failure": 1, "success": 3}, 4)
    assert list(fam["parameters"]) == ["tilt_deg", "clutter.count", "clutter.box", "clutter.person"]
    people = fam["parameters"]["clutter.person"]
    assert (people["unit"], people["span"], people["bins_covered"], people["coverage"]) == ("count", [0, 1], 2, 1.0)
    assert people["bins"] == [
        {"low": 0.0, "high": 0.0, "runs": 3, "met": 3, "outcomes": {"success": 3}},
        {"low": 1.0, "high": 1.0, "runs": 1, "met": 0, "outcomes": {"failure": 1}},  # the person stops the truck
    ]
    assert [b["runs"] for b in fam["parameters"]["clutter.count"]["bins"]] == [1, 3]
    tilt = fam["parameters"]["tilt_deg"]
    assert tilt["unit"] == "deg" and tilt["span"] == [18.0, 26.0] and len(tilt["bins"]) == 5
    assert [b["low"] for b in tilt["bins"]] == [18.0, 19.6, 21.2, 22.8, 24.4] and tilt["bins"][-1]["high"] == 26.0
    assert sum(b["runs"] for b in tilt["bins"]) == 4 and tilt["bins_covered"] == sum(
        b["runs"] > 0 for b in tilt["bins"]
    )
    assert 18.0 <= tilt["drawn_min"] <= tilt["drawn_max"] <= 26.0
    assert [(d["label"], d["met"], d["values"]["clutter.person"]) for d in fam["drawn"]] == [
        ("aisle_b#0", True, 0.0),
        ("aisle_b#1", False, 1.0),
        ("aisle_b#2", True, 0.0),
        ("aisle_b#3", True, 0.0),
    ]
    png = report / fam["plot"]
    assert fam["plot"] == "campaign/aisle_b.png" and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    (failing,) = doc["failing"]
    assert (failing["label"], failing["outcome"], failing["reason"]) == ("aisle_b#1", "failure", "path_blocked")
    assert failing["problems"] == ["expected success, got failure (path_blocked)"]
    folder = report / "aisle_b" / "1"
    assert (failing["report"], failing["mcap"]) == (str(folder / "report.json"), str(folder / "run.mcap"))
    assert Path(failing["mcap"]).is_file() and failing["drawn"] == {
        "tilt_deg": failing["drawn"]["tilt_deg"],
        "clutter": [0],
    }
    walls = [r["wall_s"] for r in doc["slowest"]]
    assert len(walls) == 5 and walls == sorted(walls, reverse=True)
    refused = next(r for r in doc["slowest"] if r["label"] == "unknown_node#0")
    assert refused["report"] is None and refused["mcap"] is None  # refused before anything ran


def test_pallet_draws_bin_per_node_and_the_lists_are_capped(monkeypatch):
    from palletpilot.executor.apps import suite_campaign

    suite = load_suite(SUITE / "suite.yaml")
    runs = [
        RunResult(f"floor_envelope#{k}", "floor_envelope", k, "success", k != 1, wall_s=float(k), drawn=drawn)
        for k, drawn in enumerate(
            [
                {"floor_b2": {"dx": -0.1, "dy": 0.3, "dyaw_deg": 0.0}, "tilt_deg": 18.0, "clutter": []},
                {"floor_b2": {"dx": 0.1, "dy": -0.3, "dyaw_deg": 9.9}, "tilt_deg": 26.0, "clutter": [0, 1]},
            ]
        )
    ]
    monkeypatch.setattr(suite_campaign, "SLOWEST", 1)
    doc = campaign_json(suite, runs)
    params = doc["families"]["floor_envelope"]["parameters"]
    assert list(params)[:3] == ["floor_b2.dx", "floor_b2.dy", "floor_b2.dyaw_deg"]
    dx = params["floor_b2.dx"]
    assert dx["unit"] == "m" and [b["runs"] for b in dx["bins"]] == [1, 0, 0, 0, 1]  # both ends of the span
    assert [b["met"] for b in dx["bins"]] == [1, 0, 0, 0, 0] and dx["coverage"] == 0.4
    assert [b["runs"] for b in params["clutter.count"]["bins"]] == [1, 0, 1]
    assert params["clutter.person"]["span"] == [0, 1] and params["clutter.box"]["bins"][1]["runs"] == 1
    assert [r["label"] for r in doc["slowest"]] == ["floor_envelope#1"]
    assert doc["failing"][0]["report"] is None  # no report folder: no paths


def test_a_count_bins_whole_numbers_and_a_point_span_one_bin():
    assert Parameter("n", Unit.COUNT, (0, 2), lambda d: None).bins() == [(0.0, 0.0), (1.0, 1.0), (2.0, 2.0)]
    assert Parameter("x", Unit.M, (0.5, 0.5), lambda d: None).bins() == [(0.5, 0.5)]


# -- `palletpilot bench campaign` -------------------------------------------------------------------


def test_bench_campaign_draws_its_runs_from_the_example_suite():
    from palletpilot.bench.campaign import campaign_specs

    family = campaign_specs("floor_envelope", 5, 9)
    assert [s.label for s in family] == [f"floor_envelope#{k}" for k in range(5)]
    assert family[:3] != campaign_specs("floor_envelope", 3, 1)  # --seed moves the draws
    assert [s.drawn for s in family[:2]] == [s.drawn for s in campaign_specs("floor_envelope", 2, 9)]
    plain = campaign_specs("person_on_the_route", 3, 2)
    assert [s.seed for s in plain] == [21000, 21001, 21002] and plain[0].scenario_path is not None


def test_bench_campaign_prints_its_figures_and_refuses_an_unknown_case(capsys):
    assert main(["bench", "--json", "campaign", "--runs", "3", "--case", "unknown_node", "--jobs", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["runs"], out["executor"], out["jobs"], out["met"], out["outcomes"]) == (
        3,
        "local",
        1,
        3,
        {"rejected": 3},
    )
    assert out["runs_per_minute"] > 0 and len(out["verdicts_sha256"]) == 64 and out["ray_start_s"] is None
    assert main(["bench", "campaign", "--case", "nope"]) == 2
    assert capsys.readouterr().err.startswith("--case: no case 'nope' in ")

"""Pallet families (issue 37, point 2): ranges in a pallet type, the estimator measuring the pockets within
them, the entry check on the measured pockets, and `palletpilot pallet measure`."""

import argparse
import dataclasses
import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from palletpilot.bench.pallet import FrameSpec, render, render_frames
from palletpilot.executor.apps.cli_pallet_measure import add_parsers
from palletpilot.executor.core.behaviour import TaskMemory
from palletpilot.executor.core.entry import CheckVolume, entry_pocket_fit, pocket_fit_problems
from palletpilot.executor.core.errors import TaskFailed
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration_io import Calibration, save_calibration
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, save_bundle
from palletpilot.perception.pallet import PalletEstimate, PalletNotFound, PalletSpread, estimate_pallet
from palletpilot.perception.specs import ForkGeometry, PalletType, load_forks, load_pallet_type, pallet_type

MISSIONS = bundled_path("missions")
ONEWAY = str(MISSIONS / "pallet_oneway.yaml")  # blocks 91 / 108 / 91 mm, pockets 255 mm: not an EPAL
FAMILY = "block_2pocket_800"


def calibration(frame: FrameBundle) -> Calibration:
    return Calibration(SE3.from_matrix(frame.truth["T_forklift_camera_true"]), "true")


def frame_of(seen: str, node: str = "floor_b2", ahead: float = 2.2, seed: int = 11, loaded: bool = False):
    spec = FrameSpec(node, loaded, 0.02, 0.08, 4.0, ahead, seed=seed, pallet=(("type", seen),))
    return render(spec)[0]


# -- the family in a pallet type file ------------------------------------------------------------------


def test_the_builtin_family_and_its_file() -> None:
    family = pallet_type(FAMILY)
    assert family.family == "block_2pocket"
    assert load_pallet_type(MISSIONS / "pallet_block_2pocket_800.yaml") == family
    assert family.bounds("pocket_width") == (0.2, 0.28) and family.bounds("block_columns") == (0.08, 0.16)
    eur = PalletType.eur()
    assert eur.family is None and eur.bounds("pocket_width") == (eur.pocket_width, eur.pocket_width)


@pytest.mark.parametrize(
    ("doc", "words"),
    [
        ({"family": "block_2pocket"}, "ranges: needed with a family"),
        ({"ranges": {"pocket_width": [0.2, 0.28]}}, "ranges: only with a family"),
        ({"family": "block_2pocket", "ranges": {"pocket_width": [0.25, 0.28]}}, "the type's own pocket width"),
        ({"family": "block_2pocket", "ranges": {"pocket_width": [0.28, 0.2]}}, "ranges.pocket_width: [0.28, 0.2]"),
        ({"family": "block_2pocket", "ranges": {"block_columns": [0.01, 0.2]}}, "0.01 m is outside 0.02..1 m"),
        ({"family": "block_2pocket", "ranges": {"pocket_widht": [0.2, 0.3]}}, "ranges.pocket_widht: Extra inputs"),
        ({"family": "stringer", "ranges": {"pocket_width": [0.2, 0.3]}}, "family: Input should be 'block_2pocket'"),
        (
            {"family": "block_2pocket", "bottom_boards": "perimeter", "ranges": {"pocket_width": [0.2, 0.3]}},
            "family: block_2pocket: its pockets are open to the floor",
        ),
        ({"family": "block_2pocket", "ranges": {"pocket_height": [0.09, "0.1"]}}, "pocket_height[1]: Input should"),
    ],
)
def test_bad_family_files_name_the_file_and_field(tmp_path: Path, doc: dict, words: str) -> None:
    path = tmp_path / "family.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(PerceptionError) as info:
        load_pallet_type(path)
    assert words in str(info.value) and str(path) in str(info.value)
    assert len(info.value.problems) == 1


# -- the estimator measures within the family -----------------------------------------------------------


def test_a_family_finds_a_block_pallet_that_eur_refuses() -> None:
    f = frame_of(ONEWAY)
    with pytest.raises(PalletNotFound) as info:
        estimate_pallet(f, calibration(f), PalletType.eur())
    assert info.value.reason == "pockets_inconsistent"
    est = estimate_pallet(f, calibration(f), pallet_type(FAMILY))
    err = (SE3.from_matrix(f.truth["T_forklift_pallet_true"]).inv() @ est.T_forklift_pallet).to_se2()
    assert abs(err.y) < 0.006 and abs(err.x) < 0.015 and abs(math.degrees(err.yaw)) < 0.5
    assert all(abs(w - 0.255) < 0.01 for w in est.pocket_widths_m)
    assert est.pocket_centres_y_m[0] == pytest.approx(0.1815, abs=0.006)
    assert est.pocket_centres_y_m[1] == pytest.approx(-0.1815, abs=0.006)
    assert est.extras["pocket_height_m"] == pytest.approx(0.100, abs=0.006)
    assert [round(c, 2) for c in est.extras["block_columns_m"]] == pytest.approx([0.09, 0.11, 0.09], abs=0.011)


def test_a_family_on_a_rack_reports_no_pocket_height_but_the_pocket_top() -> None:
    f = frame_of(ONEWAY, node="rack_a2")
    est = estimate_pallet(f, calibration(f), pallet_type(FAMILY))
    assert est.extras["pocket_height_m"] is None
    true_z = float(f.truth["T_forklift_pallet_true"][2, 3])
    assert est.extras["pocket_top_z_m"] == pytest.approx(true_z + 0.1, abs=0.006)


def test_a_family_on_a_low_support_is_not_measured_from_the_floor() -> None:
    # A pallet on a beam or platform 3 cm up (a real rack's lowest beam stood 6 cm up in a ToF camera's
    # frames): its pocket top, 3 cm higher than on the floor, must not be taken for a pocket height measured
    # from the floor (refused as outside the family). The support height the caller gives says where the
    # pallet stands; off the floor, the pocket height is not measured.
    from palletpilot.perception.pallet_model import _family_face, _Model

    model = _Model.of(pallet_type(FAMILY))
    sides = [float(v) for v in model.columns.reshape(-1)]
    _, z0, measured = _family_face(model, sides, 0.0, 0.03, 0.004, support_m=0.03)
    assert measured["pocket_height_m"] is None
    assert measured["pocket_top_z_m"] == pytest.approx(0.03 + model.block_top) and z0 == pytest.approx(0.03)
    _, z0, measured = _family_face(model, sides, 0.0, 0.003, 0.004)  # on the floor: measured from it
    assert measured["pocket_height_m"] == pytest.approx(0.003 + model.block_top) and z0 == 0.0


def test_pallets_outside_the_family_are_refused(tmp_path: Path) -> None:
    wide = tmp_path / "wide_pockets.yaml"  # columns 60 / 80 / 60 mm: pockets 300 mm, past the 280 mm range
    wide.write_text(yaml.safe_dump({"name": "wide pockets", "block_columns": [0.06, 0.08, 0.06]}))
    family = pallet_type(FAMILY)
    for seen, reason, words in (
        (str(wide), "pockets_inconsistent", "family's are"),
        ("half", "pockets_inconsistent", ""),
        ("industrial", "type_mismatch", "continues past"),
    ):
        f = frame_of(seen)
        with pytest.raises(PalletNotFound) as info:
            estimate_pallet(f, calibration(f), family)
        assert info.value.reason == reason and words in str(info.value), str(info.value)


# -- the entry check on the measured pockets -------------------------------------------------------------


def measured(widths: tuple[float, float], centres: tuple[float, float], height: float | None) -> PalletEstimate:
    return PalletEstimate(
        T_forklift_pallet=SE3.from_translation(3.0, 0.0, 0.0),
        spread=PalletSpread(0.003, 0.003, 0.002),
        n_points=1000,
        n_face_points=500,
        pocket_widths_m=widths,
        pocket_centres_y_m=centres,
        residual_rms_w=1e-4,
        extras={"pocket_height_m": height},
    )


def test_the_forks_must_fit_the_measured_pockets() -> None:
    forks, family = load_forks(MISSIONS / "forks.yaml"), pallet_type(FAMILY)  # forks 160 mm wide at +-186 mm
    ahead = SE2(-3.0, 0.0, 0.0)  # the truck 3 m before the entry face, square to it
    oneway = measured((0.255, 0.255), (0.1815, -0.1815), 0.100)
    assert pocket_fit_problems(forks, family, oneway, ahead, 0.025) == []
    narrow = measured((0.200, 0.200), (0.1725, -0.1725), 0.100)  # columns 100 / 145 / 100, pockets 200 mm
    problems = pocket_fit_problems(forks, family, narrow, ahead, 0.025)
    assert len(problems) == 2 and "left fork (160 mm wide) would keep 6 mm inside" in problems[0]
    assert "(200 mm wide at y = +172 mm), less than the 10 mm margin" in problems[0]
    low = measured((0.255, 0.255), (0.1815, -0.1815), 0.080)
    (problem,) = pocket_fit_problems(forks, family, low, ahead, 0.025)
    assert "need 85 mm, the pockets are 80 mm high (measured)" in problem
    # Not measured (a rack pallet): the family's lowest pocket, 95 mm, still takes these forks.
    assert pocket_fit_problems(forks, family, measured((0.255, 0.255), (0.1815, -0.1815), None), ahead, 0.025) == []
    # Turned 3 deg: square at the face, the tips swing 60 mm sideways at 1.15 m.
    turned = pocket_fit_problems(forks, family, oneway, SE2(-3.0, 0.0, math.radians(3.0)), 0.025)
    assert len(turned) == 2 and "mm beside its measured pocket (255 mm wide" in turned[0]


def test_the_entry_check_refuses_before_entering_with_the_figures() -> None:
    forks: ForkGeometry = load_forks(MISSIONS / "forks.yaml")
    events: list[tuple[str, dict]] = []
    vehicle = SimpleNamespace(speed=0.0, stop=lambda: None, localization=lambda: SE2(0.0, 0.0, 0.0))
    ctx = SimpleNamespace(
        vehicle=vehicle,
        forks=forks,
        pallet_type=pallet_type(FAMILY),
        memory=TaskMemory(
            "",
            0.0,
            estimate=measured((0.200, 0.200), (0.1725, -0.1725), 0.100),
            estimated_pallet=SE3.from_translation(3.0, 0.0, 0.0),
        ),
        settings=SimpleNamespace(fork_clearance=0.025, blocked_wait_s=5.0),
        now=lambda: 0.0,
        log=lambda name, **kw: events.append((name, kw)),
    )
    check = CheckVolume(lambda c: None, "path_blocked", "the pallet's entry volume", fit=entry_pocket_fit)
    check.start(ctx)  # type: ignore[arg-type]
    with pytest.raises(TaskFailed) as info:
        check.update(ctx)  # type: ignore[arg-type]
    assert info.value.reason == "safety_check_failed" and "200 mm wide" in str(info.value)
    assert events[0][0] == "pocket_fit"
    ctx.pallet_type = PalletType.eur()  # an exact type: its pockets are SafetyCheck's (nominal) business
    assert check.update(ctx) == "done"  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("columns", "result", "words"),
    [((0.091, 0.108, 0.091), "succeeded", ""), ((0.13, 0.13, 0.13), "failed", "fork (160 mm wide) would ")],
    ids=["one-way-255", "pockets-205"],
)
def test_a_family_pickup_enters_only_pockets_the_forks_fit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, columns: tuple, result: str, words: str
) -> None:
    import palletpilot.executor.core.tasks as tasks
    from palletpilot.executor.apps.app import run_simulated
    from palletpilot.sim.scenario import load_scenario

    # The entry check as `executor.tasks` wires it: the pickup's entry volume checks the pocket fit first.
    class Entry(CheckVolume):
        def __init__(self, volume, reason, what, fit=None) -> None:  # type: ignore[no-untyped-def]
            super().__init__(volume, reason, what, fit=fit or (entry_pocket_fit if "entry" in what else None))

    monkeypatch.setattr(tasks, "CheckVolume", Entry)
    (tmp_path / "seen.yaml").write_text(yaml.safe_dump({"name": "seen", "block_columns": list(columns)}))
    mission = {"name": "family", "map": str(MISSIONS / "warehouse.yaml"), "pallet_type": FAMILY}
    mission["tasks"] = [{"type": "pickup", "node": "floor_b2"}]
    (tmp_path / "mission.yaml").write_text(yaml.safe_dump(mission))
    sc = yaml.safe_load((MISSIONS / "scenario_floor.yaml").read_text())
    sc.update(map=str(MISSIONS / "warehouse.yaml"), forks=str(MISSIONS / "forks.yaml"), clutter=[])
    sc["pallets"] = [{"node": "floor_b2", "dx": 0.10, "dy": -0.15, "dyaw_deg": 5, "type": str(tmp_path / "seen.yaml")}]
    (tmp_path / "scenario.yaml").write_text(yaml.safe_dump(sc))
    r = run_simulated(
        tmp_path / "mission.yaml",
        scenario=load_scenario(tmp_path / "scenario.yaml"),
        report_dir=tmp_path / "report",
        labels="truth",
    )
    task = json.loads((tmp_path / "report" / "report.json").read_text())["tasks"][0]
    assert task["result"] == result and r.sim.collisions == [], task
    if words:  # refused before entering, with the figures: the forks never reached the pallet
        assert task["reason"] == "safety_check_failed" and words in task["message"], task
        figures = r"its measured pocket \(20\d mm wide at y = [+-]1[67]\d mm\), less than the 10 mm margin"
        assert re.search(figures, task["message"]), task["message"]
        assert not r.sim.pallets[0].carried and not r.sim.pallets[0].lifted


# -- palletpilot pallet measure -------------------------------------------------------------------------


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="palletpilot")
    add_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def oneway_frames(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[str], str, list[FrameBundle]]:
    folder = tmp_path_factory.mktemp("oneway")
    spec = FrameSpec("floor_b2", False, 0.02, 0.05, 3.0, 1.8, seed=5, pallet=(("type", ONEWAY),))
    frames, _ = render_frames(spec, 3)
    paths = [str(save_bundle(folder / f"f{i}.npz", f)) for i, f in enumerate(frames)]
    cal = str(save_calibration(folder / "cal.json", calibration(frames[0])))
    return paths, cal, frames


def test_pallet_measure_recovers_the_pockets_and_the_type_finds_the_pallet(
    oneway_frames: tuple[list[str], str, list[FrameBundle]], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    paths, cal, frames = oneway_frames
    out = tmp_path / "oneway.yaml"
    assert run(["pallet", "measure", *paths, "--calibration", cal, "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["frames_used"] == 3 and doc["out"] == str(out)
    assert all(abs(w - 255.0) <= 4.0 for w in doc["pocket_widths_mm"]), doc
    assert all(abs(c - t) <= 4.0 for c, t in zip(doc["block_columns_mm"], (91, 108, 91), strict=True)), doc
    assert abs(doc["pocket_height_mm"] - 100.0) <= 4.0 and abs(doc["face_width_mm"] - 800.0) <= 5.0
    written = pallet_type(str(out))
    assert written.family is None and written.pocket_height == pytest.approx(0.1, abs=0.004)
    est = estimate_pallet(frames[0], calibration(frames[0]), written)
    err = (SE3.from_matrix(frames[0].truth["T_forklift_pallet_true"]).inv() @ est.T_forklift_pallet).to_se2()
    assert abs(err.y) < 0.006 and abs(math.degrees(err.yaw)) < 0.5
    assert "Measured by `palletpilot pallet measure`" in out.read_text()


def test_pallet_measure_by_depth_alone(
    oneway_frames: tuple[list[str], str, list[FrameBundle]], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    _, cal, frames = oneway_frames  # the same frames without labels or colour: geometry alone selects the pallet
    bare = [
        str(save_bundle(tmp_path / f"bare{i}.npz", dataclasses.replace(f, labels=None, rgb=None)))
        for i, f in enumerate(frames)
    ]
    out = tmp_path / "oneway.yaml"
    assert (
        run(["pallet", "measure", *bare, "--calibration", cal, "--labels", "geometry", "--out", str(out), "--json"])
        == 0
    )
    doc = json.loads(capsys.readouterr().out)
    assert doc["frames_used"] == 3 and all(abs(w - 255.0) <= 5.0 for w in doc["pocket_widths_mm"]), doc
    with pytest.raises(PerceptionError, match="labels"):
        run(["pallet", "measure", *bare, "--calibration", cal, "--labels", "model", "--out", str(tmp_path / "m.yaml")])


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--family", "eur"], "--family eur: not a family pallet type"),
        (["--family", "crate"], "crate: not a known pallet type"),
        (["--calibration", "missing.json"], "missing.json: cannot read"),
    ],
)
def test_pallet_measure_bad_inputs_are_one_line(
    oneway_frames: tuple[list[str], str, list[FrameBundle]], tmp_path: Path, extra: list[str], words: str
) -> None:
    paths, cal, _ = oneway_frames
    argv = ["pallet", "measure", paths[0], "--calibration", cal, "--out", str(tmp_path / "t.yaml"), *extra]
    with pytest.raises(PerceptionError) as info:
        run(argv)
    assert words in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "t.yaml").exists()


def test_pallet_measure_through_the_command_line_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from palletpilot.executor.apps.cli import main

    assert main(["pallet", "measure", str(tmp_path / "none.npz"), "--calibration", "x.json", "--out", "t.yaml"]) == 2
    err = capsys.readouterr().err.strip().splitlines()  # one line per problem, every input checked first
    assert len(err) == 2 and "none.npz: no such file" in err[0] and "x.json: cannot read" in err[1]
    with pytest.raises(SystemExit) as info:
        main(["pallet", "measure", "f.npz", "--calibration", "x.json", "--out", str(tmp_path / "t.txt")])
    assert info.value.code == 2

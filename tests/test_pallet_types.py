"""Real pallets (issue 17): pallet types, build tolerance, damage, overhanging and filmed loads, mismatches."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from palletpilot.bench.pallet import FrameSpec, render, standpoint
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.pallet import PalletNotFound, estimate_pallet
from palletpilot.perception.pallet_steps import _chipped_edge
from palletpilot.perception.specs import (
    BUILTIN_PALLETS,
    PalletType,
    builtin_pallet,
    load_pallet_type,
    pallet_type,
)
from palletpilot.sim.scenario import Scenario, SimError, load_scenario
from palletpilot.sim.simulator import Simulator
from palletpilot.sim.world import PalletCondition, pallet_parts

MISSIONS = bundled_path("missions")


def frame(pallet: dict, loaded: bool = False, node: str = "floor_b2", ahead: float = 2.2) -> FrameBundle:
    spec = FrameSpec(node, loaded, 0.02, 0.08, 4.0, ahead, seed=11, pallet=tuple(pallet.items()))
    return render(spec)[0]


def errors(f: FrameBundle, told: str | PalletType = "eur") -> tuple[float, float, float]:
    """Lateral and longitudinal (mm) and yaw (deg) errors of the estimate in the true pallet frame."""
    cal = Calibration(SE3.from_matrix(f.truth["T_forklift_camera_true"]), "true")
    pallet = told if isinstance(told, PalletType) else pallet_type(told)
    est = estimate_pallet(f, cal, pallet)
    err = (SE3.from_matrix(f.truth["T_forklift_pallet_true"]).inv() @ est.T_forklift_pallet).to_se2()
    return 1e3 * err.y, 1e3 * err.x, math.degrees(err.yaw)


# -- the pallet types ---------------------------------------------------------------------------------


def test_builtin_types_match_the_bundled_files_and_eur_is_the_default() -> None:
    for name in BUILTIN_PALLETS:
        if name != "eur":
            assert load_pallet_type(MISSIONS / f"pallet_{name}.yaml") == builtin_pallet(name)
    assert pallet_type("EPAL") == PalletType() == PalletType.eur()
    legs = load_pallet_type(MISSIONS / "pallet_plastic_legs.yaml")
    assert legs.bottom_boards == "none" and not [p for p in legs.parts() if p.kind == "bottom_board"]
    assert pallet_type("industrial_long").pocket_floor == pytest.approx(0.022)
    assert len([p for p in pallet_type("plastic").parts() if p.kind == "top_board"]) == 1


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        ({"deck": "closed", "top_board_widths": [0.3]}, "top_board_widths: a closed deck"),
        ({"bottom_boards": "none"}, "bottom_board_thickness: 0.022 m, but bottom_boards is none"),
        ({"deck": "across", "top_board_widths": [0.5, 0.5, 0.5]}, "more than the pallet's length (1.2 m)"),
        ({"deck": "slats"}, "deck: Input should be 'boards', 'across' or 'closed'"),
        ({"bottom_boards": "perimeter", "bottom_board_thickness": 0.0}, "bottom_board_thickness: 0 m is outside"),
        ({"material": "steel"}, "material: Input should be 'wood' or 'plastic'"),
        ({"min_fork_engagement": 0.3}, "min_fork_engagement: 0.3 is outside 0.5..1 (the share of the pallet's"),
        ({"min_fork_engagement": "two thirds"}, "min_fork_engagement: "),
        ({"balance_margin": -0.1}, "balance_margin: -0.1 m is outside 0..0.5 m"),
    ],
)
def test_bad_pallet_type_files(tmp_path: Path, changes: dict, words: str) -> None:
    path = tmp_path / "pallet.yaml"
    path.write_text(yaml.safe_dump(changes))
    with pytest.raises(PerceptionError) as info:
        load_pallet_type(path)
    assert words in str(info.value) and str(path) in str(info.value)


def test_unknown_type_name_lists_the_known_ones() -> None:
    with pytest.raises(PerceptionError, match=r"not a known pallet type .*industrial_long"):
        pallet_type("crate")


# -- the simulated pallet ------------------------------------------------------------------------------


def test_condition_changes_the_parts_within_the_tolerance() -> None:
    eur = PalletType.eur()
    nominal = eur.parts()
    assert [p.name for p in pallet_parts(eur, None)] == [p.name for p in nominal]
    built = pallet_parts(eur, PalletCondition(tolerance_m=0.005, seed=3))
    for a, b in zip(nominal, built, strict=True):
        assert np.all(np.abs(a.lo - b.lo) <= 0.0025 + 1e-12) and np.all(np.abs(a.hi - b.hi) <= 0.0025 + 1e-12)
        assert a.lo[2] > 0 or b.lo[2] == 0.0  # what stands on the floor stays on it
    damaged = pallet_parts(eur, PalletCondition(chipped_blocks=3, chip_m=0.03, missing_bottom_boards=(1,), seed=5))
    assert "bottom_board_1" not in {p.name for p in damaged}

    def volume(parts: list) -> float:
        return float(sum(np.prod(p.hi - p.lo) for p in parts if p.kind == "block"))

    assert volume(nominal) - volume(damaged) >= 3 * 0.03**3 - 1e-9  # three chunks gone, nothing else


def test_scenario_pallet_fields_reach_the_simulator() -> None:
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": "floor_b2_pre",
            "pallets": [
                {
                    "node": "floor_b2",
                    "type": "pallet_half.yaml",
                    "loaded": True,
                    "overhang_m": 0.04,
                    "film": True,
                    "damage": {"missing_bottom_boards": [0]},
                },
                {"node": "floor_b1", "type": "industrial"},
            ],
        }
    )
    sc.folder = MISSIONS
    sim = Simulator(sc)
    half, industrial = sim.pallets
    assert half.type == pallet_type("half") and industrial.type.width == pytest.approx(1.0)
    assert half.condition is not None and half.condition.overhang_m == 0.04 and half.condition.film
    assert "bottom_board_0" not in {p.name for p in half.parts}
    load = [s for s in sim._pallet_solids(half) if s.kind == "load"]
    assert load and len(sim.pallet_records()) == 2


@pytest.mark.parametrize(
    ("fields", "words"),
    [
        ({"tolerance_m": 0.05}, "pallets[0].tolerance_m: Input should be less than or equal to 0.01"),
        ({"overhang_m": 0.04}, "overhang_m: only with a load (loaded: true)"),
        ({"film": True}, "film: only with a load (loaded: true)"),
        ({"loaded": True, "overhang_m": -0.01}, "pallets[0].overhang_m: Input should be greater than or equal to 0"),
        (
            {"damage": {"chipped_blocks": 7}},
            "pallets[0].damage.chipped_blocks: Input should be less than or equal to 3",
        ),
        (
            {"damage": {"missing_bottom_boards": [4]}},
            "pallets[0].damage.missing_bottom_boards[0]: Input should be 0, 1 or 2",
        ),
        ({"damage": {"dents": 2}}, "pallets[0].damage.dents: Extra inputs are not permitted"),
        ({"tolerance_seed": -1}, "pallets[0].tolerance_seed: Input should be greater than or equal to 0"),
    ],
)
def test_bad_pallet_fields_are_one_line_naming_the_field(tmp_path: Path, fields: dict, words: str) -> None:
    doc = yaml.safe_load((MISSIONS / "scenario_floor.yaml").read_text())
    doc["map"] = str(MISSIONS / doc["map"])
    doc["forks"] = str(MISSIONS / doc.get("forks", "forks.yaml"))
    doc["pallets"] = [{"node": "floor_b2", **fields}]
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(SimError) as info:
        load_scenario(path)
    assert words in str(info.value)
    assert all("\n" not in line for line in info.value.problems)


@pytest.mark.parametrize(
    ("type_", "words"),
    [
        ("crate", "pallets[0].type: crate: not a known pallet type"),
        ("missing.yaml", "pallets[0].type: "),
        ("bad_pallet.yaml", "pallets[0].type: "),
    ],
)
def test_bad_pallet_type_in_a_scenario(tmp_path: Path, type_: str, words: str) -> None:
    (tmp_path / "bad_pallet.yaml").write_text("width: 9.0\n")
    sc = Scenario.model_validate(
        {
            "map": str(MISSIONS / "warehouse.yaml"),
            "forks": str(MISSIONS / "forks.yaml"),
            "start": "floor_b2_pre",
            "pallets": [{"node": "floor_b2", "type": type_}],
        }
    )
    sc.folder = tmp_path
    with pytest.raises(SimError) as info:
        Simulator(sc)
    assert words in str(info.value)
    if type_ == "bad_pallet.yaml":
        assert "width: 9 m is outside 0.3..3 m" in str(info.value)


# -- the estimator on each family ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("pallet", "loaded", "told"),
    [
        ({"type": "industrial"}, False, "industrial"),
        ({"type": "industrial_long"}, True, "industrial_long"),
        ({"type": "half"}, False, "half"),
        ({"type": "plastic"}, True, "plastic"),
        ({"type": "pallet_plastic_legs.yaml"}, False, str(MISSIONS / "pallet_plastic_legs.yaml")),
        ({"tolerance_m": 0.005, "tolerance_seed": 4}, False, "eur"),
        (
            {"tolerance_m": 0.005, "tolerance_seed": 2, "damage": {"chipped_blocks": 3, "missing_bottom_boards": [2]}},
            True,
            "eur",
        ),
        ({"overhang_m": 0.05}, True, "eur"),
        ({"overhang_m": 0.03, "film": True}, True, "eur"),
    ],
    ids=["industrial", "industrial_long", "half", "plastic", "plastic_legs", "tolerance", "damage", "overhang", "film"],
)
def test_each_family_is_estimated_within_the_goals(pallet: dict, loaded: bool, told: str) -> None:
    lat, lon, yaw = errors(frame(pallet, loaded), told)
    assert abs(lat) < 10.0 and abs(lon) < 15.0 and abs(yaw) < 0.5, (lat, lon, yaw)


def test_a_badly_damaged_face_still_loses_its_clearest_missing_parts() -> None:
    # Three chipped blocks (4 cm chunks) and the middle bottom board gone: with margins around each hole,
    # more than `MAX_GONE` of the face tests as missing. The clearest holes must still go out of the fit;
    # left in, they turned the face by -0.56 to -0.77 deg on each of these frames.
    damage = {"chipped_blocks": 3, "chip_m": 0.04, "missing_bottom_boards": [1]}
    pallet = (("tolerance_m", 0.005), ("tolerance_seed", 2078115594), ("damage", damage))
    spec = FrameSpec("floor_a1", True, 0.038, 0.042, 6.4, 1.55, seed=2078115594, pallet=pallet)
    yaws = [errors(f)[2] for f in standpoint(spec)(3)]
    assert abs(float(np.mean(yaws))) < 0.3, yaws


def test_a_damaged_pallet_seen_sharply_is_still_the_type() -> None:
    # A noise-free camera sees the damage exactly. Three chipped blocks: a part built 2 mm proud lies off
    # the face by more than the noise (before: "the block column ... is missing: 0 % on the face").
    pallet = (("tolerance_m", 0.005), ("tolerance_seed", 5), ("damage", {"chipped_blocks": 3, "chip_m": 0.04}))
    lat, _, yaw = errors(standpoint(FrameSpec("floor_b2", False, 0.02, 0.05, 3.0, 1.2, 5, pallet), noise=False)(1)[0])
    assert abs(lat) < 10.0 and abs(yaw) < 0.5, (lat, yaw)
    # And the middle bottom board gone: one inner block edge lies 20 mm and more into its block, the
    # pocket wider at the face (before: "the block edge at y = +0.072 m ... is -20 mm off").
    damage = {"chipped_blocks": 3, "chip_m": 0.03984374676167893, "missing_bottom_boards": [1]}
    pallet = (("tolerance_m", 0.005), ("tolerance_seed", 2078115594), ("damage", damage))
    spec = FrameSpec(
        "floor_a1",
        True,
        0.038269265284270035,
        0.04156403128141356,
        6.409170928763917,
        1.546670955682236,
        2078115594,
        pallet,
    )
    lat, _, yaw = errors(standpoint(spec, noise=False)(1)[0])
    assert abs(lat) < 10.0 and abs(yaw) < 0.5, (lat, yaw)


def test_only_one_edge_off_into_its_block_is_a_chip() -> None:
    limit = 0.017
    assert _chipped_edge([0.0, 0.002, -0.02, 0.001], limit) == 2  # the left pocket's right edge, into column 1
    assert _chipped_edge([0.0, 0.002, 0.02, 0.001], limit) is None  # into the pocket: narrower, not a chip
    assert _chipped_edge([-0.02, 0.002, -0.02, 0.001], limit) is None  # two edges off: another type
    assert _chipped_edge([0.0, 0.002, 0.003, 0.001], limit) is None  # none off


@pytest.mark.parametrize(
    ("seen", "told", "reasons"),
    [
        ("industrial_long", "eur", ("type_mismatch",)),
        ("industrial", "eur", ("type_mismatch", "pockets_inconsistent")),
        ("eur", "industrial", ("pockets_inconsistent", "type_mismatch")),
        ("eur", "half", ("pockets_inconsistent", "type_mismatch")),
        ("plastic", "eur", ("pockets_inconsistent",)),
    ],
)
def test_a_pallet_of_another_type_is_not_found_with_the_reason(seen: str, told: str, reasons: tuple) -> None:
    f = frame({"type": seen})
    with pytest.raises(PalletNotFound) as info:
        errors(f, told)
    assert info.value.reason in reasons
    assert pallet_type(told).name in str(info.value)


# -- missions name the pallet type --------------------------------------------------------------------


def _mission(tmp_path: Path, tasks: list[dict], **fields: object) -> Path:
    path = tmp_path / "mission.yaml"
    path.write_text(yaml.safe_dump({"name": "t", "map": str(MISSIONS / "warehouse.yaml"), "tasks": tasks, **fields}))
    return path


def _industrial_scenario() -> Scenario:
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": "b1",
            "seed": 5,
            "pallets": [{"node": "floor_b2", "type": "industrial", "dy": 0.08, "dyaw_deg": 3}],
        }
    )
    sc.folder = MISSIONS
    return sc


def test_a_mission_picks_the_pallet_type_it_names(tmp_path: Path) -> None:
    from palletpilot.executor.apps.app import run_simulated

    mission = _mission(tmp_path, [{"type": "pickup", "node": "floor_b2", "pallet_type": "industrial"}])
    r = run_simulated(mission, scenario=_industrial_scenario(), report_dir=tmp_path / "report")
    assert r.success and r.sim.pallets[0].carried and r.sim.collisions == []


def test_a_pallet_of_another_type_than_the_mission_names_is_not_lifted(tmp_path: Path) -> None:
    from palletpilot.executor.apps.app import run_simulated

    mission = _mission(tmp_path, [{"type": "pickup", "node": "floor_b2"}])  # the mission's default: eur
    r = run_simulated(mission, scenario=_industrial_scenario(), report_dir=tmp_path / "report")
    task = r.summary["tasks"][0]
    assert not r.success and task["reason"] == "pallet_not_found"
    assert not r.sim.pallets[0].lifted and r.sim.collisions == []


def test_pallet_types_per_task_follow_the_load(tmp_path: Path) -> None:
    from palletpilot.executor.core.mission import load_mission

    (tmp_path / "mine.yaml").write_text(yaml.safe_dump({"name": "mine", "width": 1.0, "length": 1.2}))
    tasks = [
        {"type": "pickup", "node": "floor_b2", "pallet_type": "mine.yaml"},
        {"type": "delivery", "node": "drop"},
        {"type": "pickup", "node": "floor_b3"},
        {"type": "move", "node": "b1"},
    ]
    types = load_mission(_mission(tmp_path, tasks, pallet_type="half")).pallet_types()
    assert [t.name for t in types] == ["mine", "mine", pallet_type("half").name, pallet_type("half").name]


def test_a_bad_pallet_type_in_a_mission_is_one_line_per_problem(tmp_path: Path, capsys) -> None:
    from palletpilot.cli import main

    tasks = [{"type": "pickup", "node": "floor_b2", "pallet_type": "crate"}]
    path = _mission(tmp_path, tasks, pallet_type="nowhere.yaml")
    code = main(["run", str(path), "--report", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert f"{path}: tasks[0].pallet_type: crate: not a known pallet type" in err
    assert any(line.startswith(f"{path}: pallet_type: ") and "nowhere.yaml" in line for line in err.splitlines())

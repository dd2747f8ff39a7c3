"""`bench missions` judges each rack pallet from the simulator's truth before the run: take it, refuse it
(deeper than the forks can carry it) or either (within the estimate's error of that limit)."""

import pytest

from palletpilot.bench.missions import NARROW_MAP, VERDICT_BAND_M, _rack_verdict, _scenarios, load_narrow_aisle
from palletpilot.geometry.fileio import bundled_path
from palletpilot.roadmap import load_map

WAREHOUSE = load_map(bundled_path("missions") / "warehouse.yaml")


def _target(dx: float, dy: float = 0.0, dyaw_deg: float = 0.0) -> dict:
    return {"dx": dx, "dy": dy, "dyaw_deg": dyaw_deg}


def test_rack_pallets_deeper_than_the_forks_carry_must_be_refused():
    narrow = load_narrow_aisle()
    assert _rack_verdict(narrow, NARROW_MAP, "rack_n2", _target(0.0)) == "take"
    # the pallet: 200 mm deeper, 0.28 m to the side, 8 deg; taken with the forks held back
    assert _rack_verdict(narrow, NARROW_MAP, "rack_n2", _target(0.20, 0.28, 8.0)) == "take"
    assert _rack_verdict(narrow, NARROW_MAP, "rack_n2", _target(0.40)) == "refuse"
    verdicts = [_rack_verdict(narrow, NARROW_MAP, "rack_n2", _target(d / 1000)) for d in range(200, 420, 5)]
    first_refuse = verdicts.index("refuse")
    assert verdicts[: verdicts.index("either")] == ["take"] * verdicts.index("either")  # take, either, refuse
    assert set(verdicts[first_refuse:]) == {"refuse"}
    band = sum(v == "either" for v in verdicts) * 0.005
    assert band == pytest.approx(VERDICT_BAND_M + 0.01, abs=0.011)  # the band and the longitudinal margin


def test_floor_pallets_are_always_taken_and_the_draws_carry_their_verdict():
    floor = next(n.id for n in WAREHOUSE.nodes() if n.type.name == "PALLET" and n.height == 0.0)
    assert _rack_verdict(WAREHOUSE, "warehouse.yaml", floor, _target(0.4, 0.4, 15.0)) == "take"
    specs = _scenarios(30, 0, ["floor", "rack", "narrow"])
    assert {s["verdict"] for s in specs} <= {"take", "refuse", "either"}
    assert all(s["verdict"] == "take" for s in specs if s["family"] == "floor")

"""`bench safety`: every family once, judged on what the simulator's truth says happened."""

import json

import numpy as np
import pytest

from palletpilot.bench import safety
from palletpilot.cli import main


@pytest.mark.parametrize("family", safety.FAMILIES)
def test_each_family_ends_as_documented_and_touches_nothing(family):
    spec = safety._spec(family, 0, np.random.default_rng(11)) | {"seed": 11}
    outcome = safety._one(spec)
    assert outcome["outcomes"] == spec["expected"], outcome["message"]
    assert outcome["collision"] == [] and outcome["wrong_pallet"] == []
    assert outcome["placed"] and not outcome["travel_height_violation"]
    assert outcome["max_travel_fork_height_m"] <= 0.10 + 0.05
    assert outcome["correct"]


def test_lane_placements_never_reach_into_a_neighbour():
    rng = np.random.default_rng(0)
    for _ in range(200):
        dx, dy, dyaw = safety._lane_placement(rng)
        assert abs(dx) <= 0.05 and abs(dy) <= 0.15 and abs(dyaw) <= 5.0


def test_the_cli_prints_figures_per_family(capsys):
    assert main(["bench", "safety", "--json", "--runs", "1", "--seed", "3", "--families", "box_in_aisle"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["families"]) == {"box_in_aisle"}
    fig = doc["families"]["box_in_aisle"]
    assert fig["runs"] == 1 and fig["collisions"] == 0 and fig["correct_outcome_rate"] == 1.0
    assert doc["travel_height_limit_m"] == pytest.approx(0.15)

"""`palletpilot bench mpc` on one route: the figures it promises, for both controllers."""

import argparse

from palletpilot.bench import BENCHMARKS
from palletpilot.bench.mpc import add_arguments, run

KEYS = {
    "solve_ms_median",
    "solve_ms_p99",
    "lateral_rms_m",
    "lateral_max_m",
    "heading_max_deg",
    "final_lateral_mm",
    "final_heading_deg",
}


def test_bench_mpc_reports_both_controllers_on_a_pallet_approach():
    assert BENCHMARKS["mpc"] == "palletpilot.bench.mpc"
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    result = run(parser.parse_args(["--routes", "a3->floor_a3", "--seed", "3"]))
    assert result["routes"] == 1
    for ctrl in ("mpc", "pure_pursuit"):
        figures = result[ctrl]
        assert KEYS <= set(figures)
        assert figures["succeeded"] == "1/1"
        assert figures["final_lateral_mm"] <= 10.0 and figures["final_heading_deg"] <= 0.5
    assert result["mpc"]["lateral_max_m"] <= 0.05

"""Benchmarks behind `palletpilot bench NAME`: each measures and prints figures, seeded.

A benchmark module has `add_arguments(parser)` and `run(args) -> dict` (the JSON it prints).
Public API: `BENCHMARKS`, the registry of name -> module path. Shared by the pickup benchmarks
(`bench.missions`): `example_pallet_nodes`, `draw_pickup` and `start_node` (a run's pallet node and where
its truck starts on the example map). `bench.pallet_families` runs `bench pallet --families`, and
`bench.pallet_coverage` measures whether the stated spreads cover the errors.
"""

BENCHMARKS: dict[str, str] = {
    "roadmap": "palletpilot.bench.roadmap",
    "mapload": "palletpilot.bench.mapload",
    "sim": "palletpilot.bench.sim",
    "calibration": "palletpilot.bench.calibration",
    "pallet": "palletpilot.bench.pallet",
    "mpc": "palletpilot.bench.mpc",
    "missions": "palletpilot.bench.missions",
    "faults": "palletpilot.bench.faults",
    "safety": "palletpilot.bench.safety",
    "perception_service": "palletpilot.bench.perception_service",
    "robot": "palletpilot.bench.robot",
    "recording": "palletpilot.bench.recording",
    "fleet": "palletpilot.bench.fleet",
    "realdata": "palletpilot.bench.realdata",
    "campaign": "palletpilot.bench.campaign",
}

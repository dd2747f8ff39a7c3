"""Benchmarks behind `palletpilot bench NAME`: each measures and prints figures, seeded.

A benchmark module has `add_arguments(parser)` and `run(args) -> dict` (the JSON it prints).
Public API: `BENCHMARKS`, the registry of name -> module path.
"""

BENCHMARKS: dict[str, str] = {
    "roadmap": "bench.roadmap",
    "sim": "bench.sim",
    "calibration": "bench.calibration",
    "pallet": "bench.pallet",
    "mpc": "bench.mpc",
    "missions": "bench.missions",
}

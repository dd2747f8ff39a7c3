"""palletpilot: a mission executor for automated forklifts with camera-calibrated adaptive pallet pickup.

The project's top-level folders install and import under this one namespace (see README, "One
namespace"); each subpackage's docstring lists its public API:

- `palletpilot.geometry`: SE2/SE3 poses (`T_a_b`), angles, the base error, file loading and writing.
- `palletpilot.roadmap`: the roadmap graph, curves, map files, planner, reference paths, overlays.
- `palletpilot.control`: vehicle parameters, kinematic model, MPC and pure-pursuit path followers.
- `palletpilot.perception`: frame bundles, calibration, pallet pose, segmentation, camera sources.
- `palletpilot.sim`: the simulated warehouse.
- `palletpilot.executor`: missions, task state machines, the runner and its ports, reports, the CLI.
- `palletpilot.bench`: the benchmarks behind `palletpilot bench NAME`.
- `palletpilot.cli`: the `palletpilot` command (the executor's commands plus `bench`).
- `missions/` (package data, `geometry.fileio.bundled_path("missions", NAME)`): the example files.
"""

__version__ = "0.1.0"

"""The `palletpilot` command line.

Commands (exit 0 on success, 2 on bad input with one line per problem on stderr, never a traceback):
- `palletpilot map check MAP [--vehicle VEHICLE.yaml]`
- `palletpilot map show MAP --out PNG [--route FROM TO]`
- `palletpilot plan MAP FROM TO [--json]`
- `palletpilot run MISSION.yaml [--scenario S.yaml] [--seed N] [--report DIR] [--no-adapt] [--json]`
  (exit 0 success, 1 mission failed, 2 bad input); `palletpilot mission diagram TASK [--out FILE]`
- `palletpilot calibrate FRAME.npz [FRAME.npz ...] --forks FORKS.yaml [--method model|paper] [--json] [--out F]
  [--pallet eur|FILE.yaml]`; it also checks that the calibrated mount shows a pallet's entry face and
  load at the Pickup's distances (`perception.view`), with a warning on stderr when it does not
- `palletpilot capture --out DIR [--count N] [--serial S]`, `palletpilot capture --recording FILE --out DIR`
- `palletpilot sim render SCENARIO --out FRAME.npz [--fork-height H] [--at NODE] [--seed N]`
- `palletpilot bench NAME [--json] [bench options]` (see `bench/`)
"""

from __future__ import annotations

import os

# Our matrices are small (poses, point sets of thousands): a multi-threaded BLAS only oversubscribes
# the cores (measured: 11 ms SVDs of 3500 x 6 matrices under load). Set before numpy loads.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from pathlib import Path  # noqa: E402

from geometry import PalletpilotError  # noqa: E402

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2


def _max_curvature(map_path: str, vehicle: str | None) -> tuple[float | None, str | None]:
    """The curvature limit (1/m) from --vehicle or the map's own `vehicle` file, and that file's name."""
    from control import load_vehicle
    from roadmap import map_vehicle_file

    path = Path(vehicle) if vehicle else map_vehicle_file(map_path)
    if path is None:
        return None, None
    return load_vehicle(path).max_curvature, str(path)


def cmd_map_check(args: argparse.Namespace) -> int:
    """Validate a map file, including curvature against the vehicle."""
    from roadmap import check_map

    kappa, vehicle = _max_curvature(args.map, args.vehicle)
    roadmap, problems = check_map(args.map, kappa)
    if problems:
        for line in problems:
            print(line, file=sys.stderr)
        return EXIT_BAD_INPUT
    assert roadmap is not None
    limit = f", curvature limit {kappa:.3f} 1/m from {vehicle}" if kappa else ", no vehicle file: curvature unchecked"
    print(f"{args.map}: ok ({len(roadmap.nodes())} nodes, {len(roadmap.edges())} edges{limit})")
    return EXIT_OK


def cmd_map_show(args: argparse.Namespace) -> int:
    """Draw the map (and optionally a planned route) to a PNG."""
    from roadmap import Planner, load_map
    from roadmap.draw import save_roadmap_png

    roadmap = load_map(args.map)
    route = Planner(roadmap).plan(*args.route) if args.route else None
    out = save_roadmap_png(roadmap, args.out, route)
    print(f"wrote {out}")
    return EXIT_OK


def cmd_plan(args: argparse.Namespace) -> int:
    """Plan the shortest route between two nodes."""
    from roadmap import Planner, load_map

    route = Planner(load_map(args.map)).plan(args.start, args.goal)
    if args.json:
        print(json.dumps(route.to_json(), indent=2))
    else:
        print(" -> ".join(route.nodes))
        print(f"{route.length:.2f} m over {len(route.edges)} edges")
    return EXIT_OK


def cmd_sim_render(args: argparse.Namespace) -> int:
    """Render one frame bundle of a scenario from its start node (or --at NODE)."""
    from perception.frames import save_bundle
    from sim.scenario import load_scenario
    from sim.simulator import Simulator

    sim = Simulator(load_scenario(args.scenario), seed=args.seed, start=args.at)
    if args.fork_height is not None:
        sim.forklift.command_fork_height(args.fork_height)
        sim.forklift.state.fork_height = sim.forklift.fork_height_cmd
    out = save_bundle(args.out, sim.grab())
    print(f"wrote {out} ({sim.camera.width}x{sim.camera.height}, fork height {sim.fork_height:.3f} m)")
    return EXIT_OK


def _labelled(frames: list, model: str | None) -> list:
    """Frames with labels: those without are segmented by the ONNX model (the shipped one by default)."""
    if all(f.labels is not None for f in frames):
        return frames
    from perception.segmentation import DEFAULT_MODEL, OnnxSegmenter, ensure_labels

    segmenter = OnnxSegmenter(model or DEFAULT_MODEL)
    return [ensure_labels(f, segmenter) for f in frames]


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate T_forklift_camera from frame bundles of the forks and the floor."""
    from perception.calibration import calibrate
    from perception.frames import load_bundle
    from perception.specs import load_forks, pallet_type
    from perception.view import pickup_view

    forks = load_forks(args.forks)
    pallet = pallet_type(args.pallet)
    frames = _labelled([load_bundle(p) for p in args.frames], args.model)
    calibration = calibrate(frames, forks, args.method, names=[str(p) for p in args.frames])
    h, w = frames[0].depth.shape
    view = pickup_view(calibration.T_forklift_camera, frames[0].K, (w, h), forks, pallet)
    problems = view.problems()
    doc = {**calibration.to_json(), "pickup_view": view.to_json()}
    if args.out:
        Path(args.out).write_text(json.dumps(doc, indent=2) + "\n")
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        x, y, z = doc["xyz_m"]
        print(f"T_forklift_camera ({calibration.method}, lift height 0):")
        print(f"  position  x {x * 1e3:8.1f} mm   y {y * 1e3:8.1f} mm   z {z * 1e3:8.1f} mm")
        print(
            f"  mount     tilt {doc['tilt_deg']:7.3f} deg   pan {doc['pan_deg']:7.3f} deg   "
            f"roll {doc['roll_about_optical_deg']:7.3f} deg"
        )
        print("  quality   " + ", ".join(f"{k} {v}" for k, v in calibration.quality.items()))
        if not problems:
            lo, hi = view.ahead_m
            print(f"  pickup    the entry face and a load are in view {lo:.2f}-{hi:.2f} m ahead of the fork tips")
    for problem in problems:  # the calibration is good; the mount may still not suit the Pickup
        print(f"warning: camera mount: {problem}", file=sys.stderr)
    return EXIT_OK


def cmd_run(args: argparse.Namespace) -> int:
    """Run a mission in the simulated warehouse; exit 0 on success, 1 when the mission failed."""
    import signal

    from executor.app import run_simulated

    progress = None if args.json or args.quiet else sys.stderr
    report = args.report or "out/run"

    def attach(runner: object) -> None:
        """SIGUSR1 pauses the running mission, SIGUSR2 resumes it."""
        signal.signal(signal.SIGUSR1, lambda _sig, _frame: runner.pause())  # type: ignore[attr-defined]
        signal.signal(signal.SIGUSR2, lambda _sig, _frame: runner.resume())  # type: ignore[attr-defined]

    try:
        result = run_simulated(
            args.mission,
            args.scenario,
            seed=args.seed,
            report_dir=report,
            adapt=not args.no_adapt,
            progress=progress,
            on_start=attach,
        )
    except KeyboardInterrupt:
        print("cancelled: the vehicle is stopped", file=sys.stderr)
        return EXIT_FAILED
    if args.json:
        print(json.dumps(result.summary, indent=2))
    else:
        for task in result.summary["tasks"]:
            why = f" ({task['reason']})" if task["reason"] else ""
            print(f"{task['type']:9s} {task['node'] or '':14s} {task['result']}{why}, {task['attempts']} estimate(s)")
        print(f"mission {'succeeded' if result.success else 'FAILED'}; report in {report}/")
    if not result.success:
        failed = next(t for t in result.runner.results if t.result != "succeeded")
        print(
            f"mission failed: task {failed.index} ({failed.type}): {failed.message}; vehicle stopped", file=sys.stderr
        )
    return EXIT_OK if result.success else EXIT_FAILED


def cmd_mission_diagram(args: argparse.Namespace) -> int:
    """Write a task type's state machine as a mermaid diagram."""
    from executor.tasks import TASK_SPECS, mermaid

    if args.task not in TASK_SPECS:
        print(f"mission diagram: unknown task '{args.task}' (known: {', '.join(TASK_SPECS)})", file=sys.stderr)
        return EXIT_BAD_INPUT
    text = mermaid(args.task)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
    else:
        print(text)
    return EXIT_OK


def cmd_bench(args: argparse.Namespace, extra: list[str]) -> int:
    """Run one benchmark by name and print its figures."""
    from bench import BENCHMARKS

    if args.name not in BENCHMARKS:
        print(f"bench: unknown benchmark '{args.name}' (known: {', '.join(sorted(BENCHMARKS))})", file=sys.stderr)
        return EXIT_BAD_INPUT
    module = importlib.import_module(BENCHMARKS[args.name])
    parser = argparse.ArgumentParser(prog=f"palletpilot bench {args.name}")
    module.add_arguments(parser)
    result = module.run(parser.parse_args(extra))
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        width = max(len(k) for k in result)
        for key, value in result.items():
            print(f"{key:<{width}}  {value}")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of `palletpilot`."""
    parser = argparse.ArgumentParser(prog="palletpilot", description="Mission executor for automated forklifts.")
    sub = parser.add_subparsers(dest="command", required=True)

    map_p = sub.add_parser("map", help="check or draw a map file")
    map_sub = map_p.add_subparsers(dest="map_command", required=True)
    check = map_sub.add_parser("check", help="validate a map file (exit 2 listing every problem)")
    check.add_argument("map")
    check.add_argument("--vehicle", help="vehicle file for the curvature limit (default: the map's own)")
    check.set_defaults(func=cmd_map_check)
    show = map_sub.add_parser("show", help="draw a map to a PNG")
    show.add_argument("map")
    show.add_argument("--out", required=True, help="PNG file to write")
    show.add_argument("--route", nargs=2, metavar=("FROM", "TO"), help="also draw the planned route")
    show.set_defaults(func=cmd_map_show)

    plan = sub.add_parser("plan", help="plan the shortest route between two nodes")
    plan.add_argument("map")
    plan.add_argument("start", metavar="FROM")
    plan.add_argument("goal", metavar="TO")
    plan.add_argument("--json", action="store_true", help="print nodes, edges and length_m as JSON")
    plan.set_defaults(func=cmd_plan)

    run = sub.add_parser("run", help="run a mission (in the simulated warehouse)")
    run.add_argument("mission")
    run.add_argument("--scenario", help="scenario file (default: the default simulated warehouse)")
    run.add_argument("--seed", type=int, help="override the scenario's seed")
    run.add_argument("--report", help="report folder (default out/run)")
    run.add_argument("--no-adapt", action="store_true", help="the paper's original Pickup: no camera")
    run.add_argument("--json", action="store_true", help="print the summary as JSON")
    run.add_argument("--quiet", action="store_true", help="no live progress")
    run.set_defaults(func=cmd_run)

    mission = sub.add_parser("mission", help="mission tools")
    mission_sub = mission.add_subparsers(dest="mission_command", required=True)
    diagram = mission_sub.add_parser("diagram", help="draw a task type's state machine (mermaid)")
    diagram.add_argument("task", help="pickup, pickup_no_adapt, delivery, move, charge, wait")
    diagram.add_argument("--out", help="file to write (default: stdout)")
    diagram.set_defaults(func=cmd_mission_diagram)

    cal = sub.add_parser("calibrate", help="calibrate the camera pose from the forks and the floor")
    cal.add_argument("frames", nargs="+", metavar="FRAME.npz", help="frame bundles with labels")
    cal.add_argument("--forks", required=True, help="fork geometry file (YAML)")
    cal.add_argument("--method", choices=("model", "paper"), default="model")
    cal.add_argument("--json", action="store_true", help="print the calibration as JSON")
    cal.add_argument("--out", help="also write the JSON to this file (for estimate-pallet --calibration)")
    cal.add_argument("--model", help="segmentation model for frames without labels (default: the shipped one)")
    cal.add_argument("--pallet", default="eur", help="pallet type for the pickup view check: eur or a YAML file")
    cal.set_defaults(func=cmd_calibrate)

    sim = sub.add_parser("sim", help="the simulated warehouse")
    sim_sub = sim.add_subparsers(dest="sim_command", required=True)
    render = sim_sub.add_parser("render", help="render one RGB-D frame bundle (.npz) of a scenario")
    render.add_argument("scenario")
    render.add_argument("--out", required=True, help="frame bundle to write (.npz)")
    render.add_argument("--fork-height", type=float, help="fork height (m) for the frame")
    render.add_argument("--at", help="node to stand at (default: the scenario's start)")
    render.add_argument("--seed", type=int, help="override the scenario's seed")
    render.set_defaults(func=cmd_sim_render)

    bench = sub.add_parser("bench", help="run a benchmark (options after NAME go to the benchmark)")
    bench.add_argument("name")
    bench.add_argument("--json", action="store_true")
    bench.set_defaults(func=cmd_bench)

    # Commands defined next to the code they drive.
    for module in ("executor.cli_capture", "executor.cli_pallet", "executor.cli_segmentation"):
        importlib.import_module(module).add_parsers(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `palletpilot` console script; returns the exit code."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    try:
        if args.command == "bench":
            return cmd_bench(args, extra)
        if extra:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        return args.func(args)
    except PalletpilotError as exc:
        for line in exc.problems:
            print(line, file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

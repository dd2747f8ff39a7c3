"""The `palletpilot` command line.

Exit codes: 0 success; 1 the mission failed (the vehicle is stopped, the reason printed); 2 bad input,
one line per problem on stderr, never a traceback; 3 an output could not be written (for `run`: the
mission succeeded but its report did not land; the line says which file); 128 + N a run cancelled by
signal N (130 Ctrl-C / SIGINT, 143 SIGTERM), with the vehicle stopped and the report written; 70 an
internal error (a bug), one line naming it (`PALLETPILOT_DEBUG=1` shows the traceback).

Commands:
- `palletpilot map check MAP [--vehicle VEHICLE.yaml]`
- `palletpilot map show MAP --out PNG [--route FROM TO]`
- `palletpilot plan MAP FROM TO [--json]`
- `palletpilot run MISSION.yaml [--scenario S.yaml] [--seed N] [--report DIR] [--no-adapt] [--json]
  [--clock sim|wall] [--journal FILE] [--perception local|remote|serve-local] [--perception-connect ENDPOINT]
  [--foxglove [PORT]] [--foxglove-host HOST]` (the report folder gets `run.mcap`, `executor.recording`),
  `palletpilot run --demo`, `palletpilot run --resume JOURNAL`;
  `palletpilot mission diagram TASK [--out FILE]`; `palletpilot examples [--out DIR]`
- `palletpilot calibrate FRAME.npz [FRAME.npz ...] --forks FORKS.yaml [--method model|paper] [--json] [--out F]
  [--pallet eur|FILE.yaml]`; it also checks that the calibrated mount shows a pallet's entry face and
  load at the Pickup's distances (`perception.view`), with a warning on stderr when it does not
- `palletpilot forks measure FRAME.npz [...] --forks FORKS.yaml --out NEW_FORKS.yaml` (the blade's taper)
- `palletpilot capture --out DIR [--count N] [--serial S]`, `palletpilot capture --recording FILE --out DIR`
- `palletpilot perception serve [--camera realsense|none] [--model M.onnx] [--forks F] [--pallet P]
  [--listen ENDPOINT] [--connect ENDPOINT] [--prefix KEY]` (`executor.cli_perception`)
- `palletpilot sim render SCENARIO --out FRAME.npz [--fork-height H] [--at NODE] [--seed N]`
- `palletpilot robot MISSION --robot robot.yaml [...]`, `palletpilot sim serve SCENARIO --ros [--robot robot.yaml]`
  (`executor.ros.cli_robot`)
- `palletpilot replay RUN.mcap --report DIR [--json]`: report.json and trajectory.png from a recording
  (`executor.cli_replay`)
- `palletpilot bench NAME [--json] [bench options]` is added by `palletpilot.cli` (see `bench/`)
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import sys
import traceback
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import palletpilot
from palletpilot.executor.apps.cli_args import Parser, add_labels_argument, number, out_file, out_folder, seed
from palletpilot.executor.apps.cli_outcome import (
    EXIT_BAD_INPUT,
    EXIT_INTERNAL,
    EXIT_OK,
    EXIT_WRITE_FAILED,
    mission_outcome,
)
from palletpilot.geometry import OutputError, PalletpilotError
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.geometry.fileio import bundled_path, write_atomic, write_json

"""An internal error (a bug): one line naming it, never a traceback unless PALLETPILOT_DEBUG is set."""

DEMO_MISSION = "pickup_delivery.yaml"
DEMO_SCENARIO = "scenario_demo.yaml"

# A function that adds sub-commands to the `palletpilot` parser (`palletpilot.bench.cli.add_parsers`).
Extension = Callable[[Any], None]


def _max_curvature(map_path: str, vehicle: str | None) -> tuple[float | None, str | None]:
    """The curvature limit (1/m) from --vehicle or the map's own `vehicle` file, and that file's name."""
    from palletpilot.control import load_vehicle
    from palletpilot.roadmap import map_vehicle_file

    path = Path(vehicle) if vehicle else map_vehicle_file(map_path)
    if path is None:
        return None, None
    return load_vehicle(path).max_curvature, str(path)


def cmd_map_check(args: argparse.Namespace) -> int:
    """Validate a map file, including curvature against the vehicle."""
    from palletpilot.roadmap import check_map

    vehicle_problems: list[str] = []  # a bad vehicle file and the map's own problems, all at once
    kappa, vehicle = collect(vehicle_problems, lambda: _max_curvature(args.map, args.vehicle)) or (None, None)
    roadmap, problems = check_map(args.map, kappa)
    problems = vehicle_problems + [p for p in problems if p not in vehicle_problems]
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
    from palletpilot.roadmap import Planner, load_map
    from palletpilot.roadmap.draw import save_roadmap_png

    roadmap = load_map(args.map)
    route = Planner(roadmap).plan(*args.route) if args.route else None
    out = save_roadmap_png(roadmap, args.out, route)
    print(f"wrote {out}")
    return EXIT_OK


def cmd_plan(args: argparse.Namespace) -> int:
    """Plan the shortest route between two nodes."""
    from palletpilot.roadmap import Planner, load_map

    route = Planner(load_map(args.map)).plan(args.start, args.goal)
    if args.json:
        print(json.dumps(route.to_json(), indent=2))
    else:
        print(" -> ".join(route.nodes))
        print(f"{route.length:.2f} m over {len(route.edges)} edges")
    return EXIT_OK


def cmd_sim_render(args: argparse.Namespace) -> int:
    """Render one frame bundle of a scenario from its start node (or --at NODE)."""
    from palletpilot.perception.frames import save_bundle
    from palletpilot.sim.scenario import load_scenario
    from palletpilot.sim.simulator import Simulator

    sim = Simulator(load_scenario(args.scenario), seed=args.seed, start=args.at)
    mast = sim.vehicle.mast
    if args.fork_height is not None and not mast.min_height <= args.fork_height <= mast.max_height:
        raise PalletpilotError(
            f"sim render: --fork-height: {args.fork_height:g} m is outside the mast's range "
            f"{mast.min_height:g}..{mast.max_height:g} m"
        )
    if args.fork_height is not None:
        sim.forklift.command_fork_height(args.fork_height)
        sim.forklift.state.fork_height = sim.forklift.fork_height_cmd
    out = save_bundle(args.out, sim.grab())
    print(f"wrote {out} ({sim.camera.width}x{sim.camera.height}, fork height {sim.fork_height:.3f} m)")
    return EXIT_OK


def _labelled(frames: list, model: str | None) -> list:
    """The frames, those without labels but with RGB segmented by the ONNX model (the shipped one by default)."""
    if all(f.labels is not None or f.rgb is None for f in frames):
        return frames
    from palletpilot.perception.segmentation import DEFAULT_MODEL, OnnxSegmenter, ensure_labels

    segmenter = OnnxSegmenter(model or DEFAULT_MODEL)
    return [ensure_labels(f, segmenter) if f.labels is None and f.rgb is not None else f for f in frames]


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate T_forklift_camera from frame bundles of the forks and the floor."""
    from palletpilot.perception.calibration import calibrate
    from palletpilot.perception.depth_tare import correct_depth, load_tare
    from palletpilot.perception.frames import load_bundles
    from palletpilot.perception.labels_mode import LabelsMode
    from palletpilot.perception.specs import load_forks, pallet_type
    from palletpilot.perception.view import pickup_view

    problems: list[str] = []  # every problem of every input, before any work
    forks = collect(problems, lambda: load_forks(args.forks))
    pallet = collect(problems, lambda: pallet_type(args.pallet))
    mode = LabelsMode(args.labels)
    loaded = collect(problems, lambda: load_bundles(args.frames, need_labels=mode == LabelsMode.MODEL))
    tare = collect(problems, lambda: load_tare(args.depth_tare)) if args.depth_tare else None
    raise_problems(problems)
    assert forks is not None and pallet is not None and loaded is not None
    frames = [correct_depth(f, tare) for f in loaded]
    if mode != LabelsMode.GEOMETRY:
        frames = _labelled(frames, args.model)
    calibration = calibrate(frames, forks, args.method, names=[str(p) for p in args.frames], labels=mode)
    h, w = frames[0].depth.shape
    view = pickup_view(calibration.T_forklift_camera, frames[0].K, (w, h), forks, pallet)
    problems = view.problems()
    doc = {**calibration.to_json(), "pickup_view": view.to_json()}
    if args.out:
        write_json(args.out, doc)
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
    for warning in calibration.warnings:  # e.g. fork tips that cannot be trusted (`perception.calibration`)
        print(f"warning: calibration: {warning}", file=sys.stderr)
    if args.ros_static_tf is not None:  # base_link -> camera_color_optical_frame for ROS users
        from palletpilot.executor.apps.cli_robot import emit_static_tf

        emit_static_tf(calibration, args.ros_static_tf, json_out=args.json)
    return EXIT_OK


def cmd_run(args: argparse.Namespace) -> int:
    """Run (or resume) a mission in the simulated warehouse; the exit codes are in the module docstring."""
    from palletpilot.executor.core.controls import CONTROLS

    progress = None if args.json or args.quiet else sys.stderr
    if args.perception_connect and args.perception != "remote":
        print("run: --perception-connect names the service of --perception remote; give both", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.resume and args.foxglove is not None:
        print("run: --foxglove shows a new run; give no --resume with it", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.resume and args.perception != "local":
        print("run: --resume continues with perception in process; give no --perception with it", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.resume:
        if args.mission or args.scenario or args.demo or args.journal or args.seed is not None or args.report:
            print(
                "run: --resume continues the journal's own run; give it alone (with --json, --quiet)", file=sys.stderr
            )
            return EXIT_BAD_INPUT
        from palletpilot.executor.apps.app import resume_simulated

        result = resume_simulated(args.resume, progress=progress, controls=CONTROLS)
    else:
        if args.demo:
            if args.mission or args.scenario:
                print("run: --demo runs the bundled demo; give no MISSION or --scenario with it", file=sys.stderr)
                return EXIT_BAD_INPUT
            args.mission = str(bundled_path("missions", DEMO_MISSION))
            args.scenario = str(bundled_path("missions", DEMO_SCENARIO))
        elif not args.mission:
            print("run: give a MISSION file (or --demo for the bundled demo)", file=sys.stderr)
            return EXIT_BAD_INPUT
        from palletpilot.executor.core.mission import load_mission

        load_mission(
            args.mission
        )  # a bad mission file (the first check of a run) is refused before the simulator loads
        from palletpilot.executor.apps.app import run_simulated

        result = run_simulated(
            args.mission,
            args.scenario,
            seed=args.seed,
            report_dir=args.report or "out/run",
            adapt=not args.no_adapt,
            progress=progress,
            clock=args.clock,
            journal=args.journal,
            controls=CONTROLS,
            labels=args.labels,
            perception=args.perception,
            perception_connect=args.perception_connect or [],
            foxglove=args.foxglove,
            foxglove_host=args.foxglove_host,
        )
    report = result.report.parent if result.report is not None else None
    return mission_outcome(result, report, args.json, CONTROLS, "vehicle")


def cmd_examples(args: argparse.Namespace) -> int:
    """List the bundled example files (map, vehicle, forks, scenarios, missions), or copy them to --out."""
    folder = bundled_path("missions")
    # the example files, the example test suite (`suite/`, whose files refer to `../`) and the Foxglove layout
    found = [*folder.glob("*.yaml"), *folder.glob("suite/*.yaml"), *folder.glob("foxglove/*.json")]
    names = sorted(str(p.relative_to(folder)) for p in found)
    if not args.out:
        print(f"{folder}:")
        for name in names:
            print(f"  {name}")
        return EXIT_OK
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        copied = 0
        for name in names:
            target = out / name
            if target.exists():
                print(f"examples: {target}: exists, left alone", file=sys.stderr)
                continue
            target.parent.mkdir(exist_ok=True)
            write_atomic(target, (folder / name).read_bytes())
            copied += 1
    except OSError as exc:
        print(f"examples: {out}: cannot write: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(
        f"copied {copied} example file(s) to {out}/ (run: palletpilot run {out}/{DEMO_MISSION} "
        f"--scenario {out}/{DEMO_SCENARIO})"
    )
    return EXIT_OK


DIAGRAM_SUFFIXES = (".mmd", ".md", ".txt")
"""What `mission diagram --out` writes: Mermaid text; image suffixes are refused rather than filled with text."""


def cmd_mission_diagram(args: argparse.Namespace) -> int:
    """Write a task type's state machine as a mermaid diagram."""
    from palletpilot.executor.core.tasks import TASK_SPECS, mermaid

    if args.task not in TASK_SPECS:
        print(f"mission diagram: unknown task '{args.task}' (known: {', '.join(TASK_SPECS)})", file=sys.stderr)
        return EXIT_BAD_INPUT
    text = mermaid(args.task)
    if args.out and Path(args.out).suffix.lower() not in DIAGRAM_SUFFIXES:
        print(
            f"mission diagram: --out {args.out}: writes Mermaid text ({', '.join(DIAGRAM_SUFFIXES)}); render it with "
            "mermaid-cli (mmdc -i FILE.mmd -o FILE.png) or any Mermaid viewer",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    if args.out:
        write_atomic(args.out, text)
        print(f"wrote {args.out}")
    else:
        print(text)
    return EXIT_OK


def _add_map(sub: Any) -> None:
    """The `map check` and `map show` commands."""
    map_p = sub.add_parser("map", help=_HELP["map"])
    map_sub = map_p.add_subparsers(dest="map_command", required=True)
    check = map_sub.add_parser("check", help="validate a map file (exit 2 listing every problem)")
    check.add_argument("map")
    check.add_argument("--vehicle", help="vehicle file for the curvature limit (default: the map's own)")
    check.set_defaults(func=cmd_map_check)
    show = map_sub.add_parser("show", help="draw a map to a PNG")
    show.add_argument("map")
    show.add_argument("--out", required=True, type=out_file(".png"), help="PNG file to write")
    show.add_argument("--route", nargs=2, metavar=("FROM", "TO"), help="also draw the planned route")
    show.set_defaults(func=cmd_map_show)


def _add_plan(sub: Any) -> None:
    """The `plan` command."""
    plan = sub.add_parser("plan", help=_HELP["plan"])
    plan.add_argument("map")
    plan.add_argument("start", metavar="FROM")
    plan.add_argument("goal", metavar="TO")
    plan.add_argument("--json", action="store_true", help="print nodes, edges and length_m as JSON")
    plan.set_defaults(func=cmd_plan)


def _add_run(sub: Any) -> None:
    """The `run` command."""
    from palletpilot.executor.adapters.mcap.recording_channels import add_foxglove_argument
    from palletpilot.executor.apps.cli_perception import endpoint

    run = sub.add_parser("run", help=_HELP["run"])
    run.add_argument("mission", nargs="?", help="mission file (YAML)")
    run.add_argument("--demo", action="store_true", help=f"the bundled demo: {DEMO_MISSION} in {DEMO_SCENARIO}")
    run.add_argument("--scenario", help="scenario file (default: the default simulated warehouse)")
    run.add_argument("--seed", type=seed, help="override the scenario's seed (0 .. 2**64 - 1)")
    run.add_argument("--report", type=out_folder, help="report folder (default out/run)")
    run.add_argument(
        "--no-adapt",
        action="store_true",
        help="no re-plan; the camera still checks the entry (a pallet the forks do not fit is refused)",
    )
    add_labels_argument(run, sim=True)
    run.add_argument(
        "--perception",
        choices=("local", "remote", "serve-local"),
        default="local",
        help="perception in process (default), the service at --perception-connect (`perception serve`), "
        "or a service started for the run",
    )
    run.add_argument(
        "--perception-connect",
        action="append",
        type=endpoint,
        metavar="ENDPOINT",
        help="the perception service for --perception remote (default tcp/127.0.0.1:7447)",
    )
    run.add_argument("--json", action="store_true", help="print the summary as JSON")
    run.add_argument("--quiet", action="store_true", help="no live progress")
    run.add_argument("--clock", choices=("sim", "wall"), default="sim", help="simulated time (default) or real time")
    run.add_argument(
        "--journal", metavar="FILE", type=out_file(), help="record the progress in this SQLite file (for --resume)"
    )
    run.add_argument("--resume", metavar="FILE", help="continue the interrupted run of this journal")
    add_foxglove_argument(run)
    run.set_defaults(func=cmd_run)


def _add_examples(sub: Any) -> None:
    """The `examples` command."""
    examples = sub.add_parser("examples", help=_HELP["examples"])
    examples.add_argument("--out", type=out_folder, help="copy them into this folder (existing files are left alone)")
    examples.set_defaults(func=cmd_examples)


def _add_mission(sub: Any) -> None:
    """The `mission diagram` command."""
    mission = sub.add_parser("mission", help=_HELP["mission"])
    mission_sub = mission.add_subparsers(dest="mission_command", required=True)
    diagram = mission_sub.add_parser("diagram", help="draw a task type's state machine (mermaid)")
    diagram.add_argument("task", help="pickup, pickup_no_adapt, pickup_paper, delivery, move, charge, wait")
    diagram.add_argument("--out", type=out_file(), help="file to write (default: stdout)")
    diagram.set_defaults(func=cmd_mission_diagram)


def _add_calibrate(sub: Any) -> None:
    """The `calibrate` command."""
    from palletpilot.executor.apps.cli_robot import static_tf_dest

    cal = sub.add_parser("calibrate", help=_HELP["calibrate"])
    cal.add_argument("frames", nargs="+", metavar="FRAME.npz", help="frame bundles with labels")
    cal.add_argument("--forks", required=True, help="fork geometry file (YAML)")
    cal.add_argument("--method", choices=("model", "paper"), default="model")
    cal.add_argument("--json", action="store_true", help="print the calibration as JSON")
    cal.add_argument(
        "--out", type=out_file(".json"), help="also write the JSON to this file (for estimate-pallet --calibration)"
    )
    cal.add_argument("--model", help="segmentation model for frames without labels (default: the shipped one)")
    add_labels_argument(cal)
    cal.add_argument("--pallet", default="eur", help="pallet type for the pickup view check: eur or a YAML file")
    cal.add_argument(
        "--depth-tare", metavar="TARE.json", help="the camera's depth tare (`palletpilot camera tare`), applied first"
    )
    cal.add_argument(
        "--ros-static-tf",
        nargs="?",
        const="-",
        type=static_tf_dest,
        metavar="FILE.yaml",
        help="also print (or write to FILE.yaml) the base_link -> camera_color_optical_frame static transform",
    )
    cal.set_defaults(func=cmd_calibrate)


def _add_sim(sub: Any) -> None:
    """The `sim render` command, and `sim serve --ros` (`executor.apps.cli_robot`)."""
    sim = sub.add_parser("sim", help=_HELP["sim"])
    sim_sub = sim.add_subparsers(dest="sim_command", required=True)
    render = sim_sub.add_parser("render", help="render one RGB-D frame bundle (.npz) of a scenario")
    render.add_argument("scenario")
    render.add_argument("--out", required=True, type=out_file(".npz"), help="frame bundle to write (.npz)")
    render.add_argument(
        "--fork-height", type=number(0.0, 20.0, "m"), help="fork height (m) for the frame, within the mast's range"
    )
    render.add_argument("--at", help="node to stand at (default: the scenario's start)")
    render.add_argument("--seed", type=seed, help="override the scenario's seed (0 .. 2**64 - 1)")
    render.set_defaults(func=cmd_sim_render)
    from palletpilot.executor.apps import cli_robot

    cli_robot.add_sim_serve(sim_sub)  # sim serve --ros


# Every command: name, help, and where it is defined (a function here, or the module next to the code it
# drives, which has an `add_parsers`). Only the given command is built; the others appear in `--help` from
# this table, so `--help`, `--version`, `map check`, `plan` and a refused command line load no module (nor
# open3d, scipy.optimize, casadi, OpenCV) of a command they do not run. tests/test_cli_startup.py checks
# that each module's help matches this table.
_COMMANDS: tuple[tuple[str, str, Callable[[Any], None] | str], ...] = (
    ("map", "check or draw a map file", _add_map),
    ("plan", "plan the shortest route between two nodes", _add_plan),
    ("run", "run a mission (in the simulated warehouse)", _add_run),
    ("examples", "the bundled example files: list them, or copy them to edit", _add_examples),
    ("mission", "mission tools", _add_mission),
    ("calibrate", "calibrate the camera pose from the forks and the floor", _add_calibrate),
    ("sim", "the simulated warehouse", _add_sim),
    ("camera", "depth camera tools", "cli_camera"),
    ("capture", "save RGB-D frame bundles from a RealSense camera or recording", "cli_capture"),
    ("forks", "fork geometry tools", "cli_forks"),
    ("estimate-pallet", "estimate the pallet pose in a frame bundle (.npz)", "cli_pallet"),
    ("pallet", "pallet type tools", "cli_pallet_measure"),
    ("perception", "perception as a service (Zenoh)", "cli_perception"),
    ("replay", "a run's report (report.json, trajectory.png) from its run.mcap", "cli_replay"),
    ("robot", "run a mission on a real truck over ROS 2 (robot.yaml)", "cli_robot"),
    ("segment", "segmentation datasets, training, evaluation and timing", "cli_segmentation"),
    ("test", "run a mission test suite (SUITE.yaml) in the simulator", "cli_test"),
    ("agv", "run as a VDA 5050 AGV: orders from a fleet manager over MQTT", "vda5050.cli_agv"),
)
_HELP = {name: text for name, text, _ in _COMMANDS}
ALL_COMMANDS = "*"
"""`build_parser(command=ALL_COMMANDS)` builds every command in full (tests, documentation)."""


def command_of(argv: Sequence[str]) -> str | None:
    """The sub-command named in `argv` (the first word that is not an option), None when there is none."""
    return next((arg for arg in argv if not arg.startswith("-")), None)


def build_parser(extensions: Sequence[Extension] = (), command: str | None = ALL_COMMANDS) -> argparse.ArgumentParser:
    """The argument parser of `palletpilot`; each extension adds its sub-commands (`palletpilot.cli`).

    Only `command` is built in full (all of them with `ALL_COMMANDS`); the others are stand-ins with their help.
    """
    parser = Parser(prog="palletpilot", description="Mission executor for automated forklifts.")
    parser.add_argument("--version", action="version", version=f"palletpilot {palletpilot.__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, text, where in _COMMANDS:
        if command not in (name, ALL_COMMANDS):
            sub.add_parser(name, help=text)  # never run: the command given is built in full
        elif isinstance(where, str):
            importlib.import_module(f"palletpilot.executor.apps.{where}").add_parsers(sub)
        else:
            where(sub)
    for extend in extensions:
        extend(sub)
    return parser


def main(argv: Sequence[str] | None = None, extensions: Sequence[Extension] = ()) -> int:
    """Run the command line; returns the exit code. `palletpilot.cli.main` adds the `bench` extension."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(extensions, command_of(argv))
    args, extra = parser.parse_known_args(argv)
    try:
        with warnings.catch_warnings():
            if not sys.warnoptions:  # library warnings (numpy, matplotlib) are not the operator's; -W shows them
                warnings.simplefilter("ignore")
            if getattr(args, "takes_extra", False):
                return int(args.func(args, extra))
            if extra:
                parser.error(f"unrecognized arguments: {' '.join(extra)}")
            return int(args.func(args))
    except OutputError as exc:
        for line in exc.problems:
            print(f"error: {line}", file=sys.stderr)
        return EXIT_WRITE_FAILED
    except PalletpilotError as exc:
        for line in exc.problems:
            print(line, file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `palletpilot ... | head`: the reader has gone; nothing more to say
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except MemoryError:
        print("palletpilot: out of memory (an input too large for this machine?)", file=sys.stderr)
        return EXIT_INTERNAL
    except Exception as exc:  # a bug, not an input problem: one line, the traceback only when asked
        if os.environ.get("PALLETPILOT_DEBUG"):
            raise
        where = traceback.extract_tb(exc.__traceback__)[-1]
        print(
            f"palletpilot: internal error: {type(exc).__name__}: {exc} (at {Path(where.filename).name}:{where.lineno}; "
            "a bug: please report it with the command line; PALLETPILOT_DEBUG=1 shows the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())

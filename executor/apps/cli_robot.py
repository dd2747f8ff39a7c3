"""The ROS 2 commands (wired in by `executor.cli`): `palletpilot robot`, `palletpilot sim serve --ros`, and the
`palletpilot calibrate --ros-static-tf` output.

- `palletpilot robot MISSION --robot robot.yaml [--perception local|remote|serve-local] [--perception-connect EP]
  [--calibration CAL.json] [--journal FILE] [--report DIR] [--start NODE] [--wait S] [--no-adapt] [--json]
  [--quiet]`: runs a mission on the truck (`executor.ros.robot`). Before anything moves it refuses, one
  line per reason and exit 2, when a required topic is silent for its timeout, tf gives no fix, the
  safety state has a fault, the camera gives no frame, the calibration is stale, or the truck stands on
  no node. Exit codes as `palletpilot run`: 0 success, 1 the mission failed (the truck stopped), 3 the
  report could not be written, 128 + N cancelled by signal N (SIGINT, SIGTERM: the truck stops first).
- `palletpilot sim serve SCENARIO --ros [--robot robot.yaml] [--seed N] [--camera-hz HZ] [--foxglove [PORT]]
  [--foxglove-host HOST]`: the simulator as a stand-in truck on the robot file's topics
  (`executor.ros.standin`; its camera renders in a child process, `executor.ros.standin_camera`); prints
  one ready line on stdout, serves until SIGINT or SIGTERM, then prints its statistics (JSON) on stderr
  and exits 0. `--foxglove` also serves the simulated truth live over Foxglove WebSocket
  (`executor.ros.standin_foxglove`: the channels of `run --foxglove` that the truth feeds) and says where
  in one line on stderr (`foxglove: live on ws://HOST:PORT`); a port that cannot be served: exit 2.
- `static_tf_text(calibration)`: the `base_link -> camera_color_optical_frame` transform for ROS users, as
  a `static_transform_publisher` line and a tf2 YAML snippet (`calibrate --ros-static-tf [FILE]`).

Heavy modules (Cyclone DDS, the simulator, the runner) load only when a command runs.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from types import FrameType
from typing import TYPE_CHECKING

from palletpilot.executor.adapters.mcap.recording_channels import add_foxglove_argument
from palletpilot.executor.apps.cli_args import add_labels_argument, number, out_file, out_folder, seed
from palletpilot.executor.apps.cli_outcome import EXIT_BAD_INPUT, EXIT_OK, mission_outcome
from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.fileio import bundled_path, write_atomic

if TYPE_CHECKING:
    from palletpilot.perception.calibration_io import Calibration


# -- calibrate --ros-static-tf ------------------------------------------------------------------------------
def static_tf_text(
    calibration: Calibration, parent: str = "base_link", child: str = "camera_color_optical_frame"
) -> str:
    """`T_base_link_camera` (lift height 0; base_link = the forklift frame) as a `static_transform_publisher`
    argument line and a tf2 YAML snippet (a `geometry_msgs/TransformStamped` for `/tf_static`)."""
    T = calibration.T_forklift_camera
    x, y, z = (float(v) for v in T.t)
    qx, qy, qz, qw = (float(v) for v in T.rotation.as_quat())
    line = (
        f"ros2 run tf2_ros static_transform_publisher --x {x:.6f} --y {y:.6f} --z {z:.6f} "
        f"--qx {qx:.9f} --qy {qy:.9f} --qz {qz:.9f} --qw {qw:.9f} --frame-id {parent} --child-frame-id {child}"
    )
    return (
        f"# {parent} -> {child} from palletpilot calibrate ({calibration.method}), lift height 0 (REP 103 / 105).\n"
        f"# {parent} here is the forklift frame: on the floor midway between the forks, at the fork heels, x towards\n"
        "# the tips. The camera rides on the fork carriage: at lift height h add h to z (a moving frame on a real\n"
        "# truck: publish it from the lift joint instead of statically).\n"
        f"# {line}\n"
        "header:\n"
        f"  frame_id: {parent}\n"
        f"child_frame_id: {child}\n"
        "transform:\n"
        f"  translation: {{x: {x:.6f}, y: {y:.6f}, z: {z:.6f}}}\n"
        f"  rotation: {{x: {qx:.9f}, y: {qy:.9f}, z: {qz:.9f}, w: {qw:.9f}}}\n"
    )


def static_tf_dest(text: str) -> str:
    """An argparse type for `calibrate --ros-static-tf [FILE.yaml]`: `-` (print) or a writable `.yaml` file."""
    return text if text == "-" else out_file(".yaml")(text)


def emit_static_tf(calibration: Calibration, dest: str, json_out: bool = False) -> None:
    """Print the static transform (`dest` `-`; on stderr when stdout carries JSON) or write it to the file
    `dest` (YAML, atomically)."""
    text = static_tf_text(calibration)
    if dest == "-":
        print(text, end="", file=sys.stderr if json_out else sys.stdout)
    else:
        write_atomic(dest, text)
        print(f"wrote {dest} (base_link -> camera_color_optical_frame)", file=sys.stderr)


def require_cyclonedds() -> None:
    """Raise `PalletpilotError` (one line, how to install it) when the `cyclonedds` package is missing: the
    adapter's message types are Cyclone DDS IDL classes, whichever transport carries them."""
    try:
        import cyclonedds.idl  # noqa: F401
    except ImportError as exc:
        raise PalletpilotError(
            f"the ROS 2 adapter needs the cyclonedds package ({exc}): `pip install cyclonedds` (wheels for x86_64); "
            "on aarch64 build Cyclone DDS 11 from source, then `CYCLONEDDS_HOME=/its/install/prefix pip install "
            "cyclonedds`"
        ) from None


# -- robot ----------------------------------------------------------------------------------------------------
def cmd_robot(args: argparse.Namespace) -> int:
    """Run a mission on the truck over ROS 2; exit codes in the module docstring."""
    require_cyclonedds()
    from palletpilot.executor.apps.robot import run_robot
    from palletpilot.executor.core.controls import CONTROLS, install_signal_handlers
    from palletpilot.perception.labels_mode import LabelsMode

    install_signal_handlers(CONTROLS, cancel=True)  # SIGINT / SIGTERM: stop the truck, then exit
    if args.perception_connect and args.perception != "remote":
        print("robot: --perception-connect names the service of --perception remote; give both", file=sys.stderr)
        return EXIT_BAD_INPUT
    progress = None if args.json or args.quiet else sys.stderr

    def ready(node: str) -> None:
        if progress is not None:
            print(f"robot: truck ready at node '{node}'; running {args.mission}", file=progress, flush=True)

    result = run_robot(
        args.mission,
        args.robot,
        report_dir=args.report or "out/robot",
        journal=args.journal,
        calibration_path=args.calibration,
        perception_mode=args.perception,
        perception_connect=args.perception_connect or [],
        adapt=not args.no_adapt,
        start=args.start,
        wait_s=args.wait,
        progress=progress,
        controls=CONTROLS,
        on_ready=ready,
        foxglove=args.foxglove,
        foxglove_host=args.foxglove_host,
        labels=LabelsMode(args.labels),
    )
    report = result.report.parent if result.report is not None else None
    return mission_outcome(result, report, args.json, CONTROLS, "truck")


def _endpoint(text: str) -> str:
    from palletpilot.executor.apps.cli_perception import endpoint

    return endpoint(text)


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `robot` on the `palletpilot` sub-command parser."""
    p = subparsers.add_parser("robot", help="run a mission on a real truck over ROS 2 (robot.yaml)")
    p.add_argument("mission", help="mission file (YAML)")
    p.add_argument("--robot", required=True, help="robot file: topics, frames, QoS, rates, timeouts (YAML)")
    p.add_argument(
        "--perception",
        choices=("local", "remote", "serve-local"),
        default="local",
        help="perception in this process (default), the service at --perception-connect, or one started for the run",
    )
    p.add_argument("--perception-connect", action="append", type=_endpoint, metavar="ENDPOINT")
    p.add_argument("--calibration", metavar="CAL.json", help="camera calibration (palletpilot calibrate --out)")
    p.add_argument("--journal", metavar="FILE", type=out_file(), help="record the progress in this SQLite file")
    p.add_argument("--report", type=out_folder, help="report folder (default out/robot)")
    p.add_argument("--start", metavar="NODE", help="the node the truck stands on (default: the nearest)")
    p.add_argument(
        "--wait", type=number(0.0, 600.0, "s"), default=5.0, help="wait this long for the truck's topics (s)"
    )
    p.add_argument(
        "--no-adapt",
        action="store_true",
        help="no re-plan; the camera still checks the entry (a pallet the forks do not fit is refused)",
    )
    add_labels_argument(p)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no live progress")
    add_foxglove_argument(p)
    p.set_defaults(func=cmd_robot)


# -- sim serve --ros --------------------------------------------------------------------------------------------
def cmd_sim_serve(args: argparse.Namespace) -> int:
    """The simulator as a stand-in truck on ROS 2 until SIGINT / SIGTERM."""
    if not args.ros:
        print("sim serve: give --ros (the simulator as a stand-in truck on ROS 2 topics)", file=sys.stderr)
        return EXIT_BAD_INPUT
    require_cyclonedds()
    from palletpilot.executor.adapters.ros.config import load_robot
    from palletpilot.executor.adapters.ros.transport import open_transport
    from palletpilot.executor.apps.standin.truck import StandIn
    from palletpilot.geometry.errors import collect, raise_problems
    from palletpilot.sim.scenario import load_scenario
    from palletpilot.sim.simulator import Simulator

    stop = threading.Event()

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        problems: list[str] = []
        robot_path = args.robot or str(bundled_path("missions", "robot.yaml"))
        config = collect(problems, lambda: load_robot(robot_path))
        scenario = collect(problems, lambda: load_scenario(args.scenario))
        raise_problems(problems)
        assert config is not None and scenario is not None
        sim = Simulator(scenario, seed=args.seed)
        view = None
        if args.foxglove is not None:
            from palletpilot.executor.apps.standin.foxglove import StandInView

            view = StandInView(sim, args.foxglove, args.foxglove_host)  # a port it cannot serve: exit 2
        transport = None
        standin = None
        try:
            transport = open_transport(config.transport, config.domain_id)
            standin = StandIn(sim, config, transport, camera_hz=args.camera_hz)
            domain = getattr(transport, "domain_id", "ROS_DOMAIN_ID")
            print(
                f"stand-in truck ready: {args.scenario} at '{scenario.start}', domain {domain}, "
                f"{len(standin.topics())} topics out, command timeout {config.command_timeout_s:g} s",
                flush=True,
            )
            if view is not None:
                print(f"foxglove: live on ws://{args.foxglove_host}:{view.port}", file=sys.stderr, flush=True)
            standin.run(stop, on_tick=None if view is None else view.tick)
            print(json.dumps({"stand_in": standin.stats()}), file=sys.stderr, flush=True)
        finally:
            if standin is not None:
                standin.close()
            if view is not None:
                view.close()
                for line in view.errors:
                    print(f"error: {line}", file=sys.stderr)
            if transport is not None:
                transport.close()
        return EXIT_OK
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def add_sim_serve(sim_subparsers: argparse._SubParsersAction) -> None:
    """Register `sim serve` on the `palletpilot sim` sub-command parser."""
    s = sim_subparsers.add_parser("serve", help="the simulator as a stand-in truck on ROS 2 (--ros)")
    s.add_argument("scenario")
    s.add_argument("--ros", action="store_true", help="serve the robot file's ROS 2 topics (required)")
    s.add_argument("--robot", help="robot file (default: the bundled missions/robot.yaml)")
    s.add_argument("--seed", type=seed, help="override the scenario's seed (0 .. 2**64 - 1)")
    s.add_argument(
        "--camera-hz", type=number(0.0, 30.0, "Hz"), help="camera frames per second (default: the robot file's)"
    )
    add_foxglove_argument(s)
    s.set_defaults(func=cmd_sim_serve)

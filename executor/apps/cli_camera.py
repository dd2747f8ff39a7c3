"""`palletpilot camera tare FRAME.npz... --distance-m D [--origin-offset-mm MM] [--out TARE.json] [--json]`.

Measures the depth camera's scale error against a flat wall at a measured distance
(`perception.depth_tare`) and writes the tare file that `calibrate`, `estimate-pallet`, `perception
serve` and the robot's camera take with `--depth-tare` (or `depth_tare:` in robot.yaml). Exit 0 with the
result; 2 for bad input or frames that do not allow a trustworthy measurement (one line each).
"""

from __future__ import annotations

import argparse
import json

from palletpilot.executor.apps.cli_args import number, out_file


def cmd_camera_tare(args: argparse.Namespace) -> int:
    """Measure the depth scale error from frames of a flat wall and print (and write) it."""
    from palletpilot.perception.depth_tare import measure_depth_tare, save_tare
    from palletpilot.perception.frames import load_bundles

    frames = load_bundles(args.frames)
    distance = args.distance_m + args.origin_offset_mm * 1e-3
    tare = measure_depth_tare(frames, distance)
    if args.out:
        save_tare(args.out, tare)
    if args.json:
        print(json.dumps(tare.to_json(), indent=2))
    else:
        print(
            f"depth scale error {tare.depth_scale_error * 100:+.3f} % (measured z = true z x "
            f"{1 + tare.depth_scale_error:.5f}): the wall at {tare.plane_distance_m:.4f} m by depth, "
            f"{tare.distance_m:.4f} m measured; {tare.points} points of {tare.frames} frame(s), "
            f"{tare.residual_rms_m * 1e3:.1f} mm RMS off the plane, wall turned {tare.wall_angle_deg:.1f} deg"
        )
        if args.out:
            print(f"written to {args.out}: pass it with --depth-tare")
    return 0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `camera tare` on the `palletpilot` sub-command parser."""
    camera = subparsers.add_parser("camera", help="depth camera tools")
    sub = camera.add_subparsers(dest="camera_command", required=True)
    p = sub.add_parser("tare", help="measure the depth scale error against a flat wall at a measured distance")
    p.add_argument("frames", nargs="+", metavar="FRAME.npz", help="frame bundles of the wall (`palletpilot capture`)")
    p.add_argument(
        "--distance-m",
        type=number(0.3, 20.0, "m"),
        required=True,
        help="the wall's perpendicular distance from the camera (laser distance meter), m",
    )
    p.add_argument(
        "--origin-offset-mm",
        type=number(-50.0, 50.0, "mm"),
        default=0.0,
        help="add this to the distance: how far the depth origin lies behind the point measured from "
        "(the datasheet's depth start point behind the front glass), mm",
    )
    p.add_argument("--out", type=out_file(".json"), help="write the tare file (JSON) here")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=cmd_camera_tare)

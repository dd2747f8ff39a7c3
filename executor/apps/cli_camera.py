"""`palletpilot camera tare FRAME.npz... --distance-m D [--origin-offset-mm MM] [--out TARE.json] [--json]` and
`palletpilot camera noise FRAME.npz... [--into TARE.json] [--json]`.

`camera noise` measures over how many pixels the depth noise is correlated (`perception.depth_noise`) from
two or more frames of a still scene and, with `--into`, writes it into the camera's tare file
(`depth_correlation_px`), where the pallet estimate's spread takes it from.

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


def cmd_camera_noise(args: argparse.Namespace) -> int:
    """Measure the depth noise's correlation area from still frames, print it and (`--into`) write it into
    the camera's tare file."""
    import dataclasses

    from palletpilot.perception.depth_noise import measure_depth_correlation
    from palletpilot.perception.depth_tare import load_tare, save_tare
    from palletpilot.perception.frames import load_bundles

    tare = load_tare(args.into) if args.into else None  # a bad camera file: one line, before the work
    noise = measure_depth_correlation(load_bundles(args.frames))
    if tare is not None:
        save_tare(args.into, dataclasses.replace(tare, depth_correlation_px=round(noise.depth_correlation_px, 2)))
    if args.json:
        print(json.dumps(noise.to_json(), indent=2))
    else:
        print(
            f"depth noise correlated over {noise.depth_correlation_px:.1f} px (effective pixel count: a fit over "
            f"N pixels carries N / {noise.depth_correlation_px:.1f}); inverse-depth noise "
            f"{noise.inverse_depth_sigma:.2e} 1/m per pixel; {noise.pixels} pixels of {noise.frames} frames"
        )
        if args.into:
            print(f"written into {args.into} (depth_correlation_px): pass it with --depth-tare")
    return 0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `camera tare` and `camera noise` on the `palletpilot` sub-command parser."""
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
    p = sub.add_parser("noise", help="measure over how many pixels the depth noise is correlated (still frames)")
    p.add_argument(
        "frames", nargs="+", metavar="FRAME.npz", help="two or more frames of one still scene, the camera still"
    )
    p.add_argument(
        "--into",
        type=out_file(".json"),
        help="the camera's tare file (`camera tare --out`): its depth_correlation_px is set to the result",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=cmd_camera_noise)

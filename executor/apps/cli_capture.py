"""`palletpilot capture`: frame bundles from a live RealSense camera or from a RealSense recording.

- `palletpilot capture --out DIR [--count N] [--serial S] [--width 640|848] [--fps 15|30]
  [--filters spatial,temporal,hole_filling] [--warmup W]`: N bundles (default 10) from a live camera,
  after W dropped frames (default 30, auto exposure settling).
- `palletpilot capture --recording FILE --out DIR [--count N] [--filters ...]`: the bundles of a
  recording (all of them, or the first N).

Bundles are written as `DIR/frame_0000.npz`, ... (ARCHITECTURE.md: depth in metres aligned to colour,
K of the colour image, rgb). Problems raise `PerceptionError`, which the main CLI prints as one line
(exit 2). pyrealsense2 is imported only when the command runs.
"""

from __future__ import annotations

import argparse
from typing import Any

from palletpilot.executor.apps.cli_args import count, names, out_folder
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.realsense import FILTER_NAMES

DEFAULT_COUNT = 10


def cmd_capture(args: argparse.Namespace) -> int:
    """Save frame bundles from a live camera or a recording into `--out`; return the exit code."""
    from palletpilot.perception.realsense import capture_from_camera, extract_recording

    filters = args.filters or []
    if args.recording is not None:
        live_only = [f"--{name}" for name in ("serial", "width", "fps", "warmup") if getattr(args, name) is not None]
        if live_only:
            raise PerceptionError(f"capture: {', '.join(live_only)} apply to a live camera, not to --recording")
        paths = extract_recording(args.recording, args.out, count=args.count, filters=filters)
        source = args.recording
    else:
        paths = capture_from_camera(
            args.out,
            count=args.count if args.count is not None else DEFAULT_COUNT,
            serial=args.serial,
            width=args.width if args.width is not None else 640,
            fps=args.fps if args.fps is not None else 30,
            filters=filters,
            warmup=args.warmup if args.warmup is not None else 30,
        )
        source = f"camera {args.serial}" if args.serial else "camera"
    print(f"wrote {len(paths)} bundles from {source} to {args.out}")
    return 0


def add_parsers(subparsers: Any) -> None:
    """Register `capture` on the `palletpilot` sub-command parsers (`parser.add_subparsers()`)."""
    p = subparsers.add_parser("capture", help="save RGB-D frame bundles from a RealSense camera or recording")
    p.add_argument(
        "--out", required=True, type=out_folder, help="folder for frame_0000.npz, ... (must not hold bundles yet)"
    )
    p.add_argument("--recording", metavar="FILE", help="extract from this recording (.db3; .bag if the SDK reads it)")
    p.add_argument("--count", type=count(1), help=f"number of bundles (live default {DEFAULT_COUNT}; recording: all)")
    p.add_argument("--serial", help="camera serial number (default: the first camera found)")
    p.add_argument("--width", type=int, choices=(640, 848), help="stream width, height 480 (default 640)")
    p.add_argument("--fps", type=int, choices=(15, 30), help="frame rate (default 30)")
    p.add_argument(
        "--filters", type=names(FILTER_NAMES), help="depth filters, comma separated: spatial,temporal,hole_filling"
    )
    p.add_argument("--warmup", type=count(0, 10_000), help="live frames dropped before saving (default 30)")
    p.set_defaults(func=cmd_capture)

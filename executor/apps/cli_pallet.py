"""`palletpilot estimate-pallet FRAME.npz --calibration CALIB.json [--pallet P] [--vehicle V.yaml] [--json]`.

Estimates the pose of the pallet in front of the forks from one frame bundle (`perception.pallet`).
Without labels in the bundle the shipped segmentation model labels its RGB
(`perception.segmentation`); without that module, labels are required.

Every input is checked before any work starts, and every problem of every input is reported at once,
one line each naming the file (and field), exit code 2: the frame bundle (`perception.frames.load_bundle`:
a damaged or oversized archive, bad arrays, an implausible K, depth or fork height, no labels and no
rgb), the calibration (`perception.calibration_io.load_calibration`), the pallet type
(`perception.specs.pallet_type`) and the vehicle file. The fork height is checked against any mast's
range (`perception.frames.FORK_HEIGHT_RANGE_M`); with `--vehicle` against that truck's mast
(`mast.min_height` .. `mast.max_height`), since perception cannot read vehicle files itself.
Estimation failures are `PerceptionError`s (`PalletNotFound` when there is no pallet, naming the
frame): the main CLI prints them as one line and exits 2.

Registered by `executor.cli` through `add_parsers(subparsers)`.
"""

from __future__ import annotations

import argparse
import json
import math

from palletpilot.executor.apps.cli_args import add_labels_argument, number
from palletpilot.geometry import SE2
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.specs import pallet_type


def _with_labels(frame: FrameBundle, where: str, mode: str) -> FrameBundle:
    """The frame itself when it has labels (or the mode needs none), else labelled by the shipped segmentation
    model; `fused` without RGB goes on with geometry alone."""
    if frame.labels is not None or mode == "geometry" or (mode == "fused" and frame.rgb is None):
        return frame
    try:
        from palletpilot.perception import segmentation as seg
    except ImportError:
        raise PerceptionError(
            f"{where}: labels: missing, and no segmentation model is available (labels are required)"
        ) from None
    if frame.rgb is None:
        raise PerceptionError(f"{where}: labels: missing, and there is no rgb to segment them from")
    return seg.ensure_labels(frame, seg.OnnxSegmenter(seg.DEFAULT_MODEL))


def cmd_estimate_pallet(args: argparse.Namespace) -> int:
    """Check every input, then estimate the pallet pose in one frame bundle and print it."""
    from palletpilot.perception.calibration_io import load_calibration
    from palletpilot.perception.depth_tare import correct_depth, load_tare
    from palletpilot.perception.frames import load_bundle
    from palletpilot.perception.labels_mode import LabelsMode
    from palletpilot.perception.pallet import PalletNotFound, estimate_pallet, estimator_config

    problems: list[str] = []
    mast_range_m: tuple[float, float] | None = None
    if args.vehicle is not None:
        from palletpilot.control.vehicle import load_vehicle

        vehicle = collect(problems, lambda: load_vehicle(args.vehicle))
        if vehicle is not None:
            mast_range_m = (vehicle.mast.min_height, vehicle.mast.max_height)
    frame = collect(problems, lambda: load_bundle(args.frame, mast_range_m, need_labels=args.labels == "model"))
    calibration = collect(problems, lambda: load_calibration(args.calibration))
    pallet = collect(problems, lambda: pallet_type(args.pallet))
    tare = collect(problems, lambda: load_tare(args.depth_tare)) if args.depth_tare else None
    raise_problems(problems, PerceptionError)
    assert frame is not None and calibration is not None and pallet is not None

    frame = _with_labels(correct_depth(frame, tare), args.frame, args.labels)
    x, y, yaw_deg = args.expected if args.expected is not None else (0.0, 0.0, 0.0)
    expected = None if args.expected is None else SE2(x, y, math.radians(yaw_deg))
    try:
        estimate = estimate_pallet(
            frame,
            calibration,
            pallet,
            config=estimator_config(tare is not None, tare.depth_correlation_px if tare else 1.0),
            expected=expected,
            labels=LabelsMode(args.labels),
            support_height_m=args.support_height,
        )
    except PalletNotFound as exc:  # name the frame in the one-line message
        raise PalletNotFound(exc.reason, exc.detail, where=args.frame) from None
    doc = estimate.to_json()
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        s = estimate.spread
        print(
            f"pallet at x {doc['x_m']:.3f} m, y {doc['y_m']:+.3f} m, z {doc['z_m']:.3f} m, "
            f"yaw {doc['yaw_deg']:+.2f} deg "
            f"(1-sigma {s.x_m * 1e3:.1f} mm, {s.y_m * 1e3:.1f} mm, {math.degrees(s.yaw_rad):.2f} deg; "
            f"{estimate.n_face_points} face pixels)"
        )
    return 0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `estimate-pallet` on the `palletpilot` sub-command parser."""
    p = subparsers.add_parser("estimate-pallet", help="estimate the pallet pose in a frame bundle (.npz)")
    p.add_argument("frame", metavar="FRAME.npz")
    p.add_argument("--calibration", required=True, metavar="CALIB.json", help="output of `palletpilot calibrate --out`")
    p.add_argument("--pallet", default="eur", help="pallet type: eur (default) or a pallet type YAML file")
    p.add_argument(
        "--vehicle",
        metavar="V.yaml",
        help="vehicle file: the frame's fork height must lie within its mast's range (default: any mast's, 0..20 m)",
    )
    p.add_argument("--json", action="store_true", help="print T_forklift_pallet, x_m, y_m, z_m, yaw_deg, spread")
    add_labels_argument(p)
    p.add_argument(
        "--expected",
        nargs=3,
        type=number(-50.0, 50.0, "m or deg"),
        metavar=("X_M", "Y_M", "YAW_DEG"),
        help="where the pallet should stand (T_forklift_pallet on the floor): only the pallet there, within "
        "the misplacement envelope, is taken (default: anywhere ahead of the forks)",
    )
    p.add_argument(
        "--support-height",
        type=number(-1.0, 20.0, "m"),
        default=0.0,
        help="height of what the pallet stands on, m above the floor (default 0; a rack's beam height)",
    )
    p.add_argument("--depth-tare", metavar="TARE.json", help="the camera's depth tare (`palletpilot camera tare`)")
    p.set_defaults(func=cmd_estimate_pallet)

"""`palletpilot forks measure FRAME.npz [FRAME.npz ...] --forks FORKS.yaml [--calibration CAL.json] --out NEW.yaml`.

Measures the blade profile near the fork tips (taper length, tip thickness, which face slopes;
`perception.fork_profile`) from labelled frame bundles of the forks over open floor, best a few at
different fork heights (`fork_height` in the bundles: raised forks show the blades' bottom edges),
and writes the forks file with that profile (atomically; validated before it is written). The camera
pose comes from `--calibration` or, without it, from calibrating the same frames with `--forks`
(lengths are measured from the end of the blades' full-thickness top, so a calibration made with the
nominal box serves). Every input is checked first; every problem is one line, exit code 2.

Registered by `executor.cli` through `add_parsers(subparsers)`.
"""

from __future__ import annotations

import argparse
import json
import sys

from pydantic import ValidationError

from palletpilot.executor.apps.cli_args import out_file
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.geometry.fileio import write_atomic
from palletpilot.perception.errors import PerceptionError


def cmd_forks_measure(args: argparse.Namespace) -> int:
    """Check every input, measure the profile, write the new forks file."""
    from palletpilot.perception.calibration import calibrate
    from palletpilot.perception.calibration_io import load_calibration
    from palletpilot.perception.fork_profile import forks_yaml, measure_profile
    from palletpilot.perception.frames import load_bundles
    from palletpilot.perception.specs import load_forks

    problems: list[str] = []
    forks = collect(problems, lambda: load_forks(args.forks))
    frames = collect(problems, lambda: load_bundles(args.frames, need_labels=True))
    calibration = collect(problems, lambda: load_calibration(args.calibration)) if args.calibration else None
    raise_problems(problems, PerceptionError)
    assert forks is not None and frames is not None
    if calibration is None:
        calibration = calibrate(frames, forks, names=[str(p) for p in args.frames])
    measured = measure_profile(frames, forks, calibration.T_forklift_camera)
    try:
        new = measured.apply(forks)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise PerceptionError(f"{args.out}: the measured profile is not plausible: {first['msg']}") from None
    write_atomic(args.out, forks_yaml(new, ", ".join(str(p) for p in args.frames)))
    doc = {**measured.to_json(), "out": str(args.out)}
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        if measured.tapered:
            print(
                f"blade profile: thins over the last {doc['taper_length_mm']:.0f} mm to "
                f"{doc['tip_thickness_mm']:.1f} mm at the tip ({measured.taper_side} face slopes); "
                f"written to {args.out}"
            )
        else:
            print(f"blade profile: full thickness to the tips; written to {args.out}")
    for note in measured.notes:
        print(f"note: {note}", file=sys.stderr)
    return 0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `forks measure` on the `palletpilot` sub-command parser."""
    p = subparsers.add_parser("forks", help="fork geometry tools")
    sub = p.add_subparsers(dest="forks_command", required=True)
    m = sub.add_parser("measure", help="measure the blades' profile near the tips and write a forks file")
    m.add_argument("frames", nargs="+", metavar="FRAME.npz", help="frame bundles with labels, forks over open floor")
    m.add_argument("--forks", required=True, metavar="FORKS.yaml", help="the forks file to start from")
    m.add_argument("--calibration", metavar="CAL.json", help="camera pose (default: calibrated from the frames)")
    m.add_argument("--out", required=True, type=out_file(".yaml", ".yml"), help="forks file to write (YAML)")
    m.add_argument("--json", action="store_true", help="print the measured profile as JSON")
    m.set_defaults(func=cmd_forks_measure)

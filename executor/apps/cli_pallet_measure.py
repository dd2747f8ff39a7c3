"""`palletpilot pallet measure FRAME.npz [...] --calibration CAL.json [--family TYPE] [--labels MODE] --out TYPE.yaml`.

Measures a pallet's entry side (face width, block columns, pocket widths and height) from frame bundles
of one pallet standing on the floor (pixels selected as `estimate-pallet` selects them: `--labels
fused`, the default, `geometry` or `model`), its entry face towards the camera, within a family
pallet type (`--family`, a built-in name or a file that declares `family:`; default
`block_2pocket_800`), fuses the frames (median, with their scatter; `perception.pallet_measure`) and
writes an exact pallet type file (atomically; validated before it is written) that `--pallet` and
missions take. Every input is checked first; every problem is one line, exit code 2.

Registered by `executor.cli` through `add_parsers(subparsers)`.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

from pydantic import ValidationError

from palletpilot.executor.apps.cli_args import add_labels_argument, out_file
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.geometry.fileio import write_atomic
from palletpilot.perception.errors import PerceptionError

DEFAULT_FAMILY = "block_2pocket_800"
"""The family `pallet measure` measures within when `--family` is not given."""


def cmd_pallet_measure(args: argparse.Namespace) -> int:
    """Check every input, measure the pallet, write the pallet type file."""
    from palletpilot.executor.apps.cli_pallet import _with_labels
    from palletpilot.perception.calibration_io import load_calibration
    from palletpilot.perception.frames import load_bundles
    from palletpilot.perception.labels_mode import LabelsMode
    from palletpilot.perception.pallet_measure import measure_pallet, pallet_type_yaml
    from palletpilot.perception.specs import pallet_type

    problems: list[str] = []
    family = collect(problems, lambda: pallet_type(args.family))
    if family is not None and family.family is None:
        problems.append(f"--family {args.family}: not a family pallet type (it declares no family: and ranges:)")
    loaded = collect(problems, lambda: load_bundles(args.frames, need_labels=args.labels == "model"))
    calibration = collect(problems, lambda: load_calibration(args.calibration))
    raise_problems(problems, PerceptionError)
    assert family is not None and loaded is not None and calibration is not None
    names = [str(p) for p in args.frames]
    frames = []
    for bundle, where in zip(loaded, names, strict=True):
        labelled = collect(problems, functools.partial(_with_labels, bundle, where, args.labels))
        if labelled is not None:
            frames.append(labelled)
    raise_problems(problems, PerceptionError)
    measured = measure_pallet(frames, calibration, family, names, labels=LabelsMode(args.labels))
    name = args.name or f"measured {Path(args.out).stem}"
    try:
        new = measured.pallet_type(name)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "file"
        raise PerceptionError(f"{args.out}: the measured pallet is not plausible: {where}: {first['msg']}") from None
    write_atomic(args.out, pallet_type_yaml(new, measured, ", ".join(names)))
    doc = {**measured.to_json(), "out": str(args.out)}
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        cols = " / ".join(f"{c:.0f}" for c in doc["block_columns_mm"])
        print(
            f"pallet: face {doc['face_width_mm']:.0f} mm, block columns {cols} mm, pockets "
            f"{doc['pocket_widths_mm'][0]:.0f} / {doc['pocket_widths_mm'][1]:.0f} mm wide, "
            f"{doc['pocket_height_mm']:.0f} mm high ({doc['frames_used']} frames); written to {args.out}"
        )
    for frame, why in measured.frames_refused.items():
        print(f"note: {frame}: not used: {why}", file=sys.stderr)
    return 0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `pallet measure` on the `palletpilot` sub-command parser."""
    p = subparsers.add_parser("pallet", help="pallet type tools")
    sub = p.add_subparsers(dest="pallet_command", required=True)
    m = sub.add_parser("measure", help="measure a pallet's entry side from frames and write a pallet type file")
    m.add_argument("frames", nargs="+", metavar="FRAME.npz", help="labelled frame bundles of one pallet on the floor")
    m.add_argument("--calibration", required=True, metavar="CAL.json", help="the camera's calibration")
    m.add_argument(
        "--family",
        default=DEFAULT_FAMILY,
        metavar="TYPE",
        help=f"family pallet type to measure within (built-in name or file; default {DEFAULT_FAMILY})",
    )
    add_labels_argument(m)
    m.add_argument("--name", help="name of the written type (default: 'measured' and the file's stem)")
    m.add_argument("--out", required=True, type=out_file(".yaml", ".yml"), help="pallet type file to write (YAML)")
    m.add_argument("--json", action="store_true", help="print the measurement (mm) as JSON")
    m.set_defaults(func=cmd_pallet_measure)

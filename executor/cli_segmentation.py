"""`palletpilot segment ...`: segmentation datasets, evaluation and timing (wired in by `executor.cli`).

- `palletpilot segment dataset OUT_DIR --frames N [--seed S] [--start K] [--mounts all|pickup]`: render
  simulator frame bundles for training or evaluation (`sim.dataset.generate_dataset`);
- `palletpilot segment eval DATA_DIR [--model M.onnx] [--frames N] [--json]`: per-class IoU of the
  ONNX model on labelled bundles at full resolution (`perception.segmentation.evaluate_segmenter`);
- `palletpilot segment time DATA_DIR [--model M.onnx] [--frames N] [--json]`: median, p95 and max
  segmentation time (ms) per frame with onnxruntime.

Errors (`PalletpilotError`) reach `executor.cli.main`, which prints one line and exits 2.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from palletpilot.executor.cli_args import count, out_folder, seed

EXIT_OK = 0


def _print(result: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(result, indent=2))
        return
    for key, value in result.items():
        print(f"{key}: {value}")


def cmd_segment_dataset(args: argparse.Namespace) -> int:
    """Render `--frames` simulator frames into OUT_DIR as `frame_%05d.npz`."""
    from palletpilot.sim.dataset import generate_dataset

    paths = generate_dataset(args.out_dir, args.frames, seed=args.seed, start=args.start, mounts=args.mounts)
    print(f"wrote {len(paths)} frame bundles to {args.out_dir}")
    return EXIT_OK


def _files(args: argparse.Namespace) -> list[Path]:
    from palletpilot.perception.errors import PerceptionError

    files = sorted(Path(args.data_dir).glob("*.npz"))[: args.frames]
    if not files:
        raise PerceptionError(f"{args.data_dir}: no .npz frame bundles")
    return files


def cmd_segment_eval(args: argparse.Namespace) -> int:
    """Per-class IoU of the model over the bundles in DATA_DIR."""
    from palletpilot.perception.segmentation import OnnxSegmenter, evaluate_segmenter, format_iou

    result = evaluate_segmenter(OnnxSegmenter(args.model), _files(args))
    print(json.dumps(result, indent=2) if args.json else format_iou(result))
    return EXIT_OK


def cmd_segment_time(args: argparse.Namespace) -> int:
    """Segmentation time per frame (ms) over the bundles' RGB images."""
    from palletpilot.perception.frames import load_bundle
    from palletpilot.perception.segmentation import OnnxSegmenter, benchmark

    seg = OnnxSegmenter(args.model)
    rgbs = [b.rgb for b in map(load_bundle, _files(args)) if b.rgb is not None]
    _print({"providers": seg.providers, **benchmark(seg, rgbs)}, args.json)
    return EXIT_OK


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Add the `segment` command and its subcommands to `palletpilot`'s subparsers."""
    from palletpilot.perception.segmentation import DEFAULT_MODEL

    seg = subparsers.add_parser("segment", help="segmentation datasets, evaluation and timing")
    seg_sub = seg.add_subparsers(dest="segment_command", required=True)

    ds = seg_sub.add_parser("dataset", help="render simulator frame bundles for training or evaluation")
    ds.add_argument("out_dir", type=out_folder)
    ds.add_argument("--frames", type=count(1), required=True, help="number of frames")
    ds.add_argument("--seed", type=seed, default=0)
    ds.add_argument("--start", type=count(0), default=0, help="index of the first frame (to extend a dataset)")
    ds.add_argument(
        "--mounts",
        choices=("all", "pickup"),
        default="all",
        help="camera mounts: all (tilt 15-40 deg) or only those fit for the Pickup (calibrate's view check)",
    )
    ds.set_defaults(func=cmd_segment_dataset)

    for name, func, text in (
        ("eval", cmd_segment_eval, "per-class IoU of the ONNX model on labelled bundles"),
        ("time", cmd_segment_time, "segmentation time per frame (ms) with onnxruntime"),
    ):
        p = seg_sub.add_parser(name, help=text)
        p.add_argument("data_dir", type=Path)
        p.add_argument("--model", type=Path, default=DEFAULT_MODEL)
        p.add_argument("--frames", type=count(1), default=None, help="use only the first N bundles")
        p.add_argument("--json", action="store_true")
        p.set_defaults(func=func)

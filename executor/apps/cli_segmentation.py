"""`palletpilot segment ...`: segmentation datasets, evaluation and timing (wired in by `executor.cli`).

- `palletpilot segment dataset OUT_DIR --frames N [--seed S] [--start K] [--mounts all|pickup|wide]
  [--randomise [novel|real]]`:
  render simulator frame bundles for training or evaluation (`sim.dataset.generate_dataset`; `--randomise`:
  domain randomisation of colours, pallet types and light; `--randomise novel`: looks it never draws, for testing);
- `palletpilot segment scenes OUT_DIR --frames N [--seed S] [--start K] [--jobs J]`: procedural pallet scenes
  (pallets anywhere: floors, tables, stacks, clutter, any viewpoint) as labelled PNG frames, the data of the
  transfer training (`sim.pallet_scenes.generate_scenes`);
- `palletpilot segment train DATA_DIR [DATA_DIR ...] [--init M.onnx] --out OUT.onnx [--steps N | --minutes M]
  [--seed S] [--threads T] [--lr LR] [--thaw-norms] [--heldout DIR]`: fine-tune a model (default: the shipped one) on
  frame bundles and / or folders of labelled PNG frames (`perception.segmentation_data`), with
  `perception.train_segmentation.train`; needs torch and onnx (`pip install '.[train]'`);
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

from palletpilot.executor.apps.cli_args import count, number, out_file, out_folder, seed
from palletpilot.executor.apps.cli_outcome import EXIT_OK


def _print(result: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(result, indent=2))
        return
    for key, value in result.items():
        print(f"{key}: {value}")


def cmd_segment_dataset(args: argparse.Namespace) -> int:
    """Render `--frames` simulator frames into OUT_DIR as `frame_%05d.npz`."""
    from palletpilot.sim.dataset import generate_dataset

    paths = generate_dataset(
        args.out_dir,
        args.frames,
        seed=args.seed,
        start=args.start,
        mounts=args.mounts,
        randomise=args.randomise is not None,
        novel=args.randomise == "novel",
        realism=args.randomise == "real",
    )
    print(f"wrote {len(paths)} frame bundles to {args.out_dir}")
    return EXIT_OK


def cmd_segment_scenes(args: argparse.Namespace) -> int:
    """Render `--frames` procedural pallet scenes into OUT_DIR as labelled PNG frames."""
    from palletpilot.sim.pallet_scenes import generate_scenes

    names = generate_scenes(args.out_dir, args.frames, seed=args.seed, start=args.start, jobs=args.jobs)
    print(f"wrote {len(names)} labelled PNG frames to {args.out_dir}")
    return EXIT_OK


def cmd_segment_train(args: argparse.Namespace) -> int:
    """Fine-tune the `--init` model on the data folders and write `--out` (optionally evaluated on `--heldout`)."""
    from palletpilot.perception.errors import PerceptionError
    from palletpilot.perception.segmentation_data import check_training_inputs

    check_training_inputs(args.data_dirs, args.init)  # bad data is reported first, with or without torch
    try:
        import onnx  # noqa: F401 (only checking that it is there)
        import torch  # noqa: F401
    except ImportError as exc:
        raise PerceptionError(
            f"palletpilot segment train needs torch and onnx ({exc.name} is missing): pip install '.[train]'"
        ) from None
    from palletpilot.perception.train_segmentation import FINETUNE_LR, train

    steps = args.steps if args.steps is not None or args.minutes is not None else 300
    facts = train(
        list(args.data_dirs),
        Path(args.out),
        seed=args.seed,
        steps=steps,
        minutes=args.minutes,
        lr=args.lr if args.lr is not None else FINETUNE_LR,
        threads=args.threads,
        init=args.init,
        thaw_norms=args.thaw_norms,
        log=not args.quiet,
    )
    print(f"wrote {args.out}: {facts['steps']} steps on {facts['frames']} frames in {facts['train_minutes']} min")
    if args.heldout is not None:
        from palletpilot.perception.segmentation import OnnxSegmenter, evaluate_segmenter, format_iou

        files = sorted(args.heldout.glob("*.npz"))
        if not files:
            raise PerceptionError(f"{args.heldout}: no .npz frame bundles")
        print(format_iou(evaluate_segmenter(OnnxSegmenter(Path(args.out)), files)))
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

    seg = subparsers.add_parser("segment", help="segmentation datasets, training, evaluation and timing")
    seg_sub = seg.add_subparsers(dest="segment_command", required=True)

    ds = seg_sub.add_parser("dataset", help="render simulator frame bundles for training or evaluation")
    ds.add_argument("out_dir", type=out_folder)
    ds.add_argument("--frames", type=count(1), required=True, help="number of frames")
    ds.add_argument("--seed", type=seed, default=0)
    ds.add_argument("--start", type=count(0), default=0, help="index of the first frame (to extend a dataset)")
    ds.add_argument(
        "--mounts",
        choices=("all", "pickup", "wide"),
        default="all",
        help="camera mounts: all (tilt 15-40 deg), only those fit for the Pickup (calibrate's view check), or "
        "wide (0.08-1.6 m high, tilt 0-60 deg: the views of real photos)",
    )
    ds.add_argument(
        "--randomise",
        nargs="?",
        const="standard",
        default=None,
        choices=("standard", "novel", "real"),
        help="domain randomisation: colours of floor, racks, pallets and loads, pallet types, light and exposure; "
        "'novel': looks the standard randomisation never draws (to test a model on unseen looks); 'real': the "
        "standard one plus what real pallets and cameras show (worn boards, chip blocks, dirt, glare, "
        "auto-exposure, lens distortion: sim.dataset_realism)",
    )
    ds.set_defaults(func=cmd_segment_dataset)

    sc = seg_sub.add_parser("scenes", help="render procedural pallet scenes (labelled PNG frames) for training")
    sc.add_argument("out_dir", type=out_folder)
    sc.add_argument("--frames", type=count(1), required=True, help="number of frames")
    sc.add_argument("--seed", type=seed, default=0)
    sc.add_argument("--start", type=count(0), default=0, help="index of the first frame (to extend a set)")
    sc.add_argument("--jobs", type=count(1), default=1, help="processes rendering in parallel")
    sc.set_defaults(func=cmd_segment_scenes)

    tr = seg_sub.add_parser("train", help="fine-tune the segmentation model on frame bundles or labelled PNG frames")
    tr.add_argument(
        "data_dirs", type=Path, nargs="+", help="folders of frame bundles (.npz) or of NAME.png + NAME_labels.png"
    )
    tr.add_argument("--init", type=Path, default=DEFAULT_MODEL, help="the ONNX model to start from (default: shipped)")
    tr.add_argument("--out", type=out_file(".onnx"), required=True, help="the fine-tuned ONNX model to write")
    length = tr.add_mutually_exclusive_group()
    length.add_argument("--steps", type=count(1), default=None, help="optimiser steps of 12 crops (default 300)")
    length.add_argument("--minutes", type=number(0.1, 10000.0), default=None, help="train for this wall time")
    tr.add_argument("--seed", type=seed, default=0)
    tr.add_argument("--threads", type=count(1), default=1, help="torch CPU threads")
    tr.add_argument("--lr", type=number(1e-6, 1.0), default=None, help="peak learning rate (default 1e-3)")
    tr.add_argument(
        "--thaw-norms",
        action="store_true",
        help="re-estimate the batch norms on the data and train them (thousands of frames of new looks; "
        "default: frozen, right for a few hundred own frames)",
    )
    tr.add_argument("--heldout", type=Path, default=None, help="evaluate the new model on these bundles")
    tr.add_argument("--quiet", action="store_true", help="no progress lines")
    tr.set_defaults(func=cmd_segment_train)

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

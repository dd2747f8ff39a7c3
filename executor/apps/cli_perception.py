"""`palletpilot perception serve`: the perception service process (wired in by `executor.cli`).

`palletpilot perception serve [--camera realsense|none] [--model M.onnx] [--forks F.yaml] [--pallet P]
[--listen ENDPOINT ...] [--connect ENDPOINT ...] [--prefix KEY]` serves calibration, pallet estimation,
volume checks, segmentation and health over Zenoh (`executor.perception_server`; wire format
`perception.wire`). Endpoints are Zenoh locators, `tcp/HOST:PORT` (default: listen on
`tcp/127.0.0.1:7447`, this computer only; `tcp/0.0.0.0:7447` for a second computer; `--connect` to
join a Zenoh router). Once serving it prints one line on stdout,
`perception service ready on tcp/127.0.0.1:7447 prefix palletpilot/perception`, and serves until
SIGINT or SIGTERM, then closes its session and exits 0. Every input (forks, pallet type, model,
camera, endpoints) is checked first: a problem is one line on stderr and exit 2.

Option types (`endpoint`, `key_prefix`) are argparse `type=` callables, checked when parsed.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import threading
from types import FrameType
from typing import TYPE_CHECKING

from palletpilot.executor.adapters.processes import keep_heap_mapped
from palletpilot.executor.apps.cli_args import add_labels_argument
from palletpilot.executor.apps.cli_outcome import EXIT_OK
from palletpilot.geometry.errors import collect, raise_problems

if TYPE_CHECKING:
    from palletpilot.executor.adapters.zenoh.perception_server import PerceptionServer


_ENDPOINT = re.compile(r"(tcp|udp|tls|quic|ws|unixsock-stream)/(.+)")
_HOST_PORT = re.compile(r"(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})")
_KEY_CHUNK = re.compile(r"[A-Za-z0-9_.\-]+")


def endpoint(text: str) -> str:
    """An argparse type: a Zenoh endpoint `PROTOCOL/ADDRESS`, for tcp, udp, tls, quic and ws `HOST:PORT`."""
    m = _ENDPOINT.fullmatch(text)
    if m is None:
        raise argparse.ArgumentTypeError(
            f"must be a Zenoh endpoint such as tcp/127.0.0.1:7447 (PROTOCOL/HOST:PORT), got '{text}'"
        )
    if m.group(1) != "unixsock-stream":
        hp = _HOST_PORT.fullmatch(m.group(2).split("?")[0].split("#")[0])
        if hp is None or not 0 <= int(hp.group(2)) <= 65535:
            raise argparse.ArgumentTypeError(f"must be {m.group(1)}/HOST:PORT with a port 0..65535, got '{text}'")
    return text


def key_prefix(text: str) -> str:
    """An argparse type: a Zenoh key prefix of plain chunks (`palletpilot/perception`), no wildcards."""
    chunks = text.split("/")
    if not text or not all(_KEY_CHUNK.fullmatch(c) for c in chunks):
        raise argparse.ArgumentTypeError(
            f"must be a key such as palletpilot/perception (chunks of letters, digits, _ . - between '/'; "
            f"no wildcards, no empty chunk), got '{text}'"
        )
    return text


def cmd_perception_serve(args: argparse.Namespace) -> int:
    """Check every input, start the service, print the ready line, serve until SIGINT / SIGTERM."""
    stop = threading.Event()

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        keep_heap_mapped()  # every request brings a frame of megabytes: reuse its pages
        server = _build(args)
        with server:
            from palletpilot.executor.adapters.zenoh.perception_server import PARENT_ENV, zenoh_config

            listen = args.listen or ([] if args.connect else [_default_listen()])
            server.start(zenoh_config(listen=listen, connect=args.connect or []))
            where = ", ".join(listen) if listen else "router " + ", ".join(args.connect)
            print(f"perception service ready on {where} prefix {server.prefix}", flush=True)
            parent = os.environ.get(PARENT_ENV)
            while not stop.wait(0.5):
                if parent is not None and os.getppid() != int(parent):
                    print("perception service: the process that started it is gone; stopping", file=sys.stderr)
                    break
            served = server.stats.served
        print(f"perception service stopped ({served} requests served)", file=sys.stderr)
        return EXIT_OK
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _default_listen() -> str:
    from palletpilot.executor.adapters.zenoh.perception_server import DEFAULT_LISTEN

    return DEFAULT_LISTEN


def _build(args: argparse.Namespace) -> PerceptionServer:
    """The server with its perception, model and camera; every input problem at once (`PerceptionError`)."""
    from palletpilot.executor.adapters.local_perception import LocalPerception
    from palletpilot.executor.adapters.zenoh.perception_server import PerceptionServer
    from palletpilot.geometry.fileio import bundled_path
    from palletpilot.perception.depth_tare import load_tare
    from palletpilot.perception.errors import PerceptionError
    from palletpilot.perception.labels_mode import LabelsMode
    from palletpilot.perception.segmentation import DEFAULT_MODEL, OnnxSegmenter
    from palletpilot.perception.specs import load_forks, pallet_type

    problems: list[str] = []
    forks = collect(problems, lambda: load_forks(args.forks or bundled_path("missions", "forks.yaml")))
    pallet = collect(problems, lambda: pallet_type(args.pallet))
    segmenter = collect(problems, lambda: OnnxSegmenter(args.model or DEFAULT_MODEL))
    tare = collect(problems, lambda: load_tare(args.depth_tare)) if args.depth_tare else None
    raise_problems(problems, PerceptionError)
    assert forks is not None and pallet is not None and segmenter is not None
    camera, serial = None, None
    if args.camera == "realsense":
        from palletpilot.perception.realsense import RealSenseSource

        source = RealSenseSource()
        camera, serial = source, source.serial
    perception = LocalPerception(forks, pallet, segmenter=segmenter, depth_tare=tare, labels=LabelsMode(args.labels))
    return PerceptionServer(perception, prefix=args.prefix, camera=camera, camera_serial=serial)


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `perception serve` on the `palletpilot` sub-command parser."""
    p = subparsers.add_parser("perception", help="perception as a service (Zenoh)")
    sub = p.add_subparsers(dest="perception_command", required=True)
    s = sub.add_parser("serve", help="serve calibration, pallet estimation and segmentation over Zenoh")
    s.add_argument(
        "--camera",
        choices=("none", "realsense"),
        default="none",
        help="the service's own camera for requests without a frame (default none: requests carry frames)",
    )
    s.add_argument("--model", metavar="M.onnx", help="segmentation model (default: the shipped one)")
    s.add_argument("--depth-tare", metavar="TARE.json", help="the camera's depth tare (`palletpilot camera tare`)")
    s.add_argument("--forks", metavar="FORKS.yaml", help="fork geometry (default: the bundled missions/forks.yaml)")
    s.add_argument("--pallet", default="eur", help="default pallet type: eur, another built-in or a YAML file")
    add_labels_argument(s)
    s.add_argument(
        "--listen",
        action="append",
        type=endpoint,
        metavar="ENDPOINT",
        help="listen here, e.g. tcp/0.0.0.0:7447 (repeatable; default tcp/127.0.0.1:7447 without --connect)",
    )
    s.add_argument(
        "--connect", action="append", type=endpoint, metavar="ENDPOINT", help="join a Zenoh router here (repeatable)"
    )
    s.add_argument("--prefix", type=key_prefix, default="palletpilot/perception", help="key prefix of the queryables")
    s.set_defaults(func=cmd_perception_serve)

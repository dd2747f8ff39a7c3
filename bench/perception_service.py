"""`palletpilot bench perception_service`: what the perception service costs on top of the estimation.

Starts `palletpilot perception serve` as a subprocess on a free loopback port (`LocalService`, as
`run --perception serve-local` does), renders one 640x480 RGB-D frame of a misplaced pallet (the
`bench pallet` scene, seeded, with the simulator's labels so that the service does not segment), and
asks the service for the pallet's pose `--calls` times through `RemotePerception` (after `--warmup`
calls). Per call: the round trip the client sees (encoding the frame, Zenoh, decoding, the estimation,
the reply) and the estimation's own runtime inside the service (`PalletEstimate.runtime_ms`); the
overhead is their difference. The same frame is estimated in this process too (`local_estimate_ms`),
and the bare transport is timed with `health` queries (no frame). The CPU is shared by both processes,
as on a truck's perception computer; the machine's other load shows in the figures.

JSON: `calls`, `frame_bytes` (the encoded request), `round_trip_ms`, `service_estimate_ms`,
`overhead_ms` (p50, p95, p99, max), `local_estimate_ms`, `health_round_trip_ms`, and the goal (overhead
p99 <= 5 ms) with whether it was met.

Public API: `add_arguments`, `run`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from palletpilot.executor.apps.cli_args import count, seed

OVERHEAD_GOAL_MS = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--calls", type=count(10, 100_000), default=200, help="timed estimate_pallet calls")
    parser.add_argument("--warmup", type=count(0, 1000), default=10, help="untimed calls first")
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument("--depth", choices=("f32", "mm16"), default="f32", help="depth on the wire")


def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    return {
        "p50": round(float(np.percentile(a, 50)), 3),
        "p95": round(float(np.percentile(a, 95)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "max": round(float(a.max()), 3),
    }


def run(args: argparse.Namespace) -> dict:
    """Time the service against the same estimation in this process; the figures as a dict."""
    from palletpilot.bench.pallet import frame_specs, render
    from palletpilot.executor.adapters.processes import keep_heap_mapped
    from palletpilot.executor.adapters.zenoh.perception_remote import LocalService, RemotePerception
    from palletpilot.geometry import SE2, SE3
    from palletpilot.geometry.fileio import bundled_path
    from palletpilot.perception import wire
    from palletpilot.perception.calibration_io import Calibration
    from palletpilot.perception.pallet import estimate_pallet
    from palletpilot.perception.specs import PalletType, load_forks
    from palletpilot.perception.view import PICKUP_AHEAD_M

    spec = frame_specs(1, args.seed, 0.3, 0.05, 10.0, (PICKUP_AHEAD_M[0], PICKUP_AHEAD_M[1]))[0]
    frame, _ = render(spec)
    calibration = Calibration(SE3.from_matrix(frame.truth["T_forklift_camera_true"]), "true")
    pallet = PalletType.eur()
    forks = load_forks(bundled_path("missions", "forks.yaml"))
    pose = SE2.identity()

    local = []
    for _ in range(max(10, args.calls // 4)):
        t0 = time.perf_counter()
        estimate_pallet(frame, calibration, pallet)
        local.append((time.perf_counter() - t0) * 1e3)

    keep_heap_mapped()  # as `palletpilot run --perception remote|serve-local` does
    round_trip, inside, health = [], [], []
    with LocalService(forks, pallet) as service, RemotePerception([str(service.endpoint)], depth=args.depth) as client:
        for _ in range(args.warmup):
            client.estimate_pallet(frame, calibration, pose)
        for _ in range(args.calls):
            t0 = time.perf_counter()
            est = client.estimate_pallet(frame, calibration, pose)
            round_trip.append((time.perf_counter() - t0) * 1e3)
            inside.append(est.runtime_ms)
        for _ in range(args.calls):
            t0 = time.perf_counter()
            client.health()
            health.append((time.perf_counter() - t0) * 1e3)
        retries = client.stats.retries
    overhead = [r - i for r, i in zip(round_trip, inside, strict=True)]
    frame_bytes = len(wire.encode_request({"timeout_s": 3.0}, [frame], args.depth))
    o = _stats(overhead)
    return {
        "calls": args.calls,
        "seed": args.seed,
        "depth_encoding": args.depth,
        "frame": f"{frame.width}x{frame.height} RGB-D with labels",
        "frame_bytes": frame_bytes,
        "round_trip_ms": _stats(round_trip),
        "service_estimate_ms": _stats(inside),
        "overhead_ms": o,
        "local_estimate_ms": _stats(local),
        "health_round_trip_ms": _stats(health),
        "retries": retries,
        "goal_overhead_p99_ms": {"goal": OVERHEAD_GOAL_MS, "met": o["p99"] <= OVERHEAD_GOAL_MS},
    }

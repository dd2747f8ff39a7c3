"""`palletpilot bench pallet`: pallet pose estimation on simulated frames from pre-pallet positions.

Each frame: one EUR pallet at a random pallet node of the example warehouse (floor or rack, empty or
loaded), misplaced by up to `--lateral` m sideways, `--longitudinal` m along the node and `--yaw-deg`
degrees; the forklift stands on the node's axis with the pallet's entry face 1.2-3.0 m (`--ahead`)
ahead of the fork tips and its forks raised to the pallet (node height + 25 mm). The camera is the
scenario default (D435 at 640x480, mount perturbed per run) with D435 depth noise, dropouts, flying
pixels and 2 px label noise.

Cases are the product of `--labels` (`gt`: the simulator's labels; `onnx` or `model`: the shipped
segmentation model on the RGB; `geometry`: depth alone; `fused`: depth with the model's hints, the
commands' default; `perception.geometry_labels`; every case is told where the pallet should stand and
its support height, as the Pickup tells perception) and `--calibration` (`true`: the simulator's mount;
`estimated`:
`perception.calibration.calibrate(..., method="model")` on two frames with the forks down, taken at
the same spot). A case whose module or model is missing is reported as unavailable with the reason.

Each standpoint gives `--frames-per-estimate` frames (3, as the Pickup takes; fresh sensor noise each).
Per case, over every frame: detection rate, and median / p95 / max of the lateral, longitudinal and
yaw errors (and of the pocket height error), measured in the true pallet frame
(`T_true^-1 @ T_estimated`); runtime of `estimate_pallet` alone (median, p95; segmentation and
calibration excluded). The issue's goals apply to these per-frame figures. `per_estimate` gives the
same errors for the standpoint's frames fused by `perception.pallet.fuse_estimates`, which is what
the Pickup acts on. With ONNX labels, `segmentation` gives the model's per-class IoU on these frames
against the simulator's exact labels (`perception.segmentation.SegmentationScore`). Seeded: the same
`--seed` gives the same frames and figures (runtimes aside).

Pallet families (`--families`): `bench.pallet_families`.
"""

from __future__ import annotations

import argparse
import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from palletpilot.executor.apps.cli_args import count, names, number, seed
from palletpilot.executor.core.behaviour import Settings
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.labels_mode import LabelsMode
from palletpilot.perception.pallet import PalletNotFound, estimate_pallet, fuse_estimates
from palletpilot.perception.segmentation import SegmentationScore
from palletpilot.perception.view import PICKUP_AHEAD_M
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")
FLOOR_NODES = ("floor_a1", "floor_a2", "floor_a3", "floor_b1", "floor_b2", "floor_b3")
RACK_NODES = ("rack_a1", "rack_a2", "rack_a3", "rack_b1", "rack_b2", "rack_b3")
FORK_CLEARANCE_M = 0.025
"""Fork bottoms this far above the pallet's underside when the frame is taken (mid-pocket for 50 mm forks)."""
GOALS = {"lateral_mm_p95": 10.0, "longitudinal_mm_p95": 15.0, "yaw_deg_p95": 0.5, "runtime_ms_median": 50.0}
"""Goals of issue 5 for ground-truth labels and the true calibration."""


FAMILIES = (
    "eur",
    "industrial",
    "industrial_long",
    "half",
    "plastic",
    "tolerance",
    "damage",
    "overhang",
    "film",
    "mismatch",
    "block_2pocket",
)
"""Pallet families of `--families`."""


@dataclass(frozen=True)
class FrameSpec:
    """One benchmark frame: where the pallet is and where the forklift stands."""

    node: str
    loaded: bool
    dx: float
    dy: float
    dyaw_deg: float
    ahead: float  # m from the fork tips to the nominal entry face
    seed: int
    pallet: tuple[tuple[str, Any], ...] = ()  # more fields of the scenario's pallet (type, damage, ...)
    depth_correlation_px: float = 1.0  # the camera's depth noise correlation area (`CameraNoise`), pixels


def scenario(spec: FrameSpec, width: int = 640, noise: bool = True) -> Scenario:
    """The scenario of one frame: a single pallet, the default camera with D435 noise (or an ideal camera)."""
    if noise:
        camera_noise = {
            "depth_noise": True,
            "invalid_rate": 0.005,
            "flying_pixel_rate": 0.5,
            "label_noise": True,
            "label_noise_px": 2,
            "depth_correlation_px": spec.depth_correlation_px,
        }
        perturbation = {"xyz_sigma": 0.002, "angle_sigma_deg": 0.2}
    else:
        camera_noise = {
            "depth_noise": False,
            "label_noise": False,
            "rgb_sigma": 0.0,
            "lighting_variation": False,
            "invalid_rate": 0.0,
        }
        perturbation = {"xyz_sigma": 0.0, "angle_sigma_deg": 0.0}
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": f"{spec.node}_pre",
            "seed": spec.seed,
            "camera": {
                "width": width,
                "mount": {"x": -0.10, "y": 0.0, "z": 0.45, "tilt_deg": 22, "pan_deg": 0.5, "roll_deg": -0.3},
                "perturbation": perturbation,
                "noise": camera_noise,
            },
            "pallets": [
                {
                    "node": spec.node,
                    "dx": spec.dx,
                    "dy": spec.dy,
                    "dyaw_deg": spec.dyaw_deg,
                    "loaded": spec.loaded,
                    **dict(spec.pallet),
                }
            ],
        }
    )
    sc.folder = MISSIONS
    return sc


def place(sim: Simulator, spec: FrameSpec, fork_height: float | None = None) -> None:
    """Stand the forklift on the pallet node's axis, the nominal entry face `spec.ahead` ahead of the tips."""
    node = sim.roadmap.node(spec.node)
    from palletpilot.perception.specs import ENTRY_GAP_M

    back = sim.forks.tip_x + spec.ahead - ENTRY_GAP_M  # node to forklift origin, along the node's heading
    sim.forklift.state.pose = node.pose @ SE2(-back, 0.0, 0.0)
    h = node.height + FORK_CLEARANCE_M if fork_height is None else fork_height
    sim.forklift.command_fork_height(h)
    sim.forklift.state.fork_height = sim.forklift.fork_height_cmd


def render(
    spec: FrameSpec, width: int = 640, noise: bool = True, calibration_frames: int = 0
) -> tuple[FrameBundle, list[FrameBundle]]:
    """The pallet frame of `spec` and, if asked, frames with the forks down for calibration."""
    frames, cal = render_frames(spec, 1, width, noise, calibration_frames)
    return frames[0], cal


def render_frames(
    spec: FrameSpec, n: int, width: int = 640, noise: bool = True, calibration_frames: int = 0
) -> tuple[list[FrameBundle], list[FrameBundle]]:
    """`n` pallet frames of `spec` from the same standpoint (fresh sensor noise each) and calibration frames."""
    sim = Simulator(scenario(spec, width, noise))
    cal = []
    if calibration_frames:
        place(sim, spec, fork_height=0.0)
        cal = [sim.grab() for _ in range(calibration_frames)]
    place(sim, spec)
    return [sim.grab() for _ in range(n)], cal


def standpoint(spec: FrameSpec, width: int = 640, noise: bool = True) -> Callable[[int], list[FrameBundle]]:
    """Frames of `spec` from its standpoint on demand: the returned function grabs the next `n` (fresh
    sensor noise each; the first `n` are those of `render_frames(spec, n)`)."""
    sim = Simulator(scenario(spec, width, noise))
    place(sim, spec)
    return lambda n: [sim.grab() for _ in range(n)]


def frame_specs(
    n: int, seed: int, lateral: float, longitudinal: float, yaw_deg: float, ahead: tuple[float, float]
) -> list[FrameSpec]:
    """`n` seeded frames: floor and rack alternate, empty or loaded at random."""
    rng = np.random.default_rng(seed)
    specs = []
    for k in range(n):
        nodes = FLOOR_NODES if k % 2 == 0 else RACK_NODES
        specs.append(
            FrameSpec(
                node=str(nodes[int(rng.integers(len(nodes)))]),
                loaded=bool(rng.random() < 0.5),
                dx=float(rng.uniform(-longitudinal, longitudinal)),
                dy=float(rng.uniform(-lateral, lateral)),
                dyaw_deg=float(rng.uniform(-yaw_deg, yaw_deg)),
                ahead=float(rng.uniform(*ahead)),
                seed=int(rng.integers(2**31)),
            )
        )
    return specs


LABEL_KINDS = ("gt", "onnx", "model", "geometry", "fused")
"""`--labels`: the simulator's labels (`gt`) or the shipped model's (`onnx`, alias `model`) in the model mode;
depth alone (`geometry`); depth with the shipped model's hints (`fused`, the commands' default)."""


def _labels_mode(kind: str) -> LabelsMode:
    """The estimator's labels mode of a `--labels` kind."""
    return LabelsMode(kind) if kind in ("geometry", "fused") else LabelsMode.MODEL


def expected_at(spec: FrameSpec) -> tuple[SE2, float]:
    """Where the pallet of `spec` should stand, as the Pickup tells perception: `T_forklift_pallet` of the
    node's nominal pallet (the forklift stands on the node's axis, `place`) and its support height (m)."""
    from palletpilot.perception.specs import load_forks

    roadmap = _roadmap()
    return SE2(load_forks(MISSIONS / "forks.yaml").tip_x + spec.ahead, 0.0, 0.0), roadmap.node(spec.node).height


@functools.cache
def _roadmap() -> Any:
    from palletpilot.roadmap import load_map

    return load_map(MISSIONS / "warehouse.yaml")


def _labeller(kind: str) -> tuple[Callable[[FrameBundle], FrameBundle] | None, str | None]:
    """How a case gets its labels (the simulator's, the model's, none for geometry), or why it cannot."""
    if kind == "gt":
        return (lambda f: f), None
    if kind == "geometry":
        import dataclasses

        return (lambda f: dataclasses.replace(f, labels=None)), None
    try:
        from palletpilot.perception import segmentation as seg

        segmenter = seg.OnnxSegmenter(seg.DEFAULT_MODEL)
    except Exception as exc:  # ImportError, a missing model file (PerceptionError), ...
        return None, f"{type(exc).__name__}: {exc}"
    import dataclasses

    return (lambda f: dataclasses.replace(f, labels=segmenter.segment(f.rgb))), None


def _calibrator(kind: str) -> tuple[Callable[[FrameBundle, list[FrameBundle], Any], Calibration] | None, str | None]:
    """How a case gets its calibration, or why it cannot."""
    if kind == "true":
        return (lambda f, cal, forks: Calibration(SE3.from_matrix(f.truth["T_forklift_camera_true"]), "true")), None
    try:
        from palletpilot.perception.calibration import calibrate
    except Exception as exc:
        return None, f"{type(exc).__name__}: {exc}"
    return (lambda f, cal, forks: calibrate(cal, forks, method="model")), None


def _stats(values: list[float], scale: float, digits: int) -> dict[str, float | None]:
    if not values:
        return {"median": None, "p95": None, "max": None}
    a = np.abs(np.asarray(values)) * scale
    return {
        "median": round(float(np.median(a)), digits),
        "p95": round(float(np.percentile(a, 95)), digits),
        "max": round(float(a.max()), digits),
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--frames", type=count(1), default=200)
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument(
        "--labels", type=names(LABEL_KINDS), default=["gt"], help=f"comma list of {', '.join(LABEL_KINDS)}"
    )
    parser.add_argument(
        "--calibration", type=names(("true", "estimated")), default=["true"], help="comma list of true, estimated"
    )
    parser.add_argument("--width", type=int, default=640, choices=(640, 848))
    parser.add_argument("--lateral", type=number(0.0, 1.0, "m"), default=0.35, help="max lateral misplacement (m)")
    parser.add_argument(
        "--longitudinal", type=number(0.0, 1.0, "m"), default=0.05, help="max misplacement along the node (m)"
    )
    parser.add_argument("--yaw-deg", type=number(0.0, 45.0, "deg"), default=15.0, help="max yaw misplacement (deg)")
    parser.add_argument(
        "--ahead", type=number(0.1, 10.0, "m"), nargs=2, default=PICKUP_AHEAD_M, help="entry face ahead of the tips (m)"
    )
    parser.add_argument(
        "--families",
        type=names(FAMILIES),
        default=None,
        help=f"pallet families instead of the cases (comma list of {','.join(FAMILIES)})",
    )
    parser.add_argument(
        "--frames-per-estimate",
        type=count(1, 100),
        default=Settings.frames_per_estimate,
        help="frames per standpoint (per round with --families), fused as the Pickup does",
    )
    parser.add_argument(
        "--max-frames-per-estimate",
        type=count(1, 100),
        default=Settings.max_frames_per_estimate,
        help="--families: more rounds while the fused yaw is uncertain, up to this many frames (as the Pickup)",
    )
    parser.add_argument(
        "--depth-correlation-px",
        type=number(1.0, 100.0, "px"),
        default=1.0,
        help="--families: the simulated camera's depth noise is correlated over this many pixels, and the "
        "estimator is told so (as `camera noise` tells it through the camera file); 1: independent pixels",
    )
    parser.add_argument(
        "--estimate-yaw-sigma-deg",
        type=number(0.0, 10.0, "deg"),
        default=Settings.estimate_yaw_sigma_deg,
        help="--families: another round while the fused yaw 1-sigma is above this (deg)",
    )


def run(args: argparse.Namespace) -> dict:
    """Render the frames, run every requested case (or pallet family) and return the figures."""
    if getattr(args, "families", None):
        from palletpilot.bench.pallet_families import run_families

        if len(args.labels) == 1:
            return run_families(args, args.labels[0])
        return {f"labels={kind}": run_families(args, kind) for kind in args.labels}
    label_kinds, cal_kinds = args.labels, args.calibration
    labellers = {k: _labeller(k) for k in label_kinds}
    calibrators = {k: _calibrator(k) for k in cal_kinds}
    cases: dict[str, dict[str, Any]] = {}
    runnable = []
    for lk in label_kinds:
        for ck in cal_kinds:
            name = f"labels={lk},calibration={ck}"
            why = labellers[lk][1] or calibrators[ck][1]
            if why:
                cases[name] = {"available": False, "reason": why}
            else:
                runnable.append((name, lk, ck))
                cases[name] = {"available": True}
    specs = frame_specs(args.frames, args.seed, args.lateral, args.longitudinal, args.yaw_deg, tuple(args.ahead))
    need_cal = any(ck == "estimated" for _, _, ck in runnable)
    per = args.frames_per_estimate
    acc: dict[str, dict[str, list]] = {
        name: {k: [] for k in ("lat", "lon", "yaw", "z", "ms", "fail", "kind", "fused")} for name, _, _ in runnable
    }
    render_s = 0.0
    seg_score = SegmentationScore()
    from palletpilot.perception.specs import load_forks

    forks = load_forks(MISSIONS / "forks.yaml")
    label_kinds_used = {lk for _, lk, _ in runnable}
    cal_kinds_used = {ck for _, _, ck in runnable}
    for spec in specs:
        t0 = time.perf_counter()
        frames, cal_frames = render_frames(spec, per, args.width, calibration_frames=2 if need_cal else 0)
        render_s += time.perf_counter() - t0
        T_true = SE3.from_matrix(frames[0].truth["T_forklift_pallet_true"])
        labelled = {lk: [labellers[lk][0](f) for f in frames] for lk in label_kinds_used}  # type: ignore[misc]
        expected, support = expected_at(spec)
        seg_kind = next((k for k in ("onnx", "model", "fused") if k in labelled), None)
        if seg_kind is not None:
            for frame, seg_frame in zip(frames, labelled[seg_kind], strict=True):
                assert seg_frame.labels is not None  # the onnx labeller sets the segmenter's labels
                seg_score.add(frame.truth["labels_true"], seg_frame.labels)
        calibs: dict[str, Calibration | Exception] = {}
        for ck in cal_kinds_used:
            try:
                calibs[ck] = calibrators[ck][0](frames[0], cal_frames, forks)  # type: ignore[misc]
            except Exception as exc:  # a failed calibration counts as a missed frame
                calibs[ck] = exc
        kind = (spec.ahead, spec.loaded)
        for name, lk, ck in runnable:
            a = acc[name]
            cal = calibs[ck]
            if isinstance(cal, Exception):
                a["fail"].extend([f"calibration: {type(cal).__name__}"] * per)
                continue
            found = []
            for frame in labelled[lk]:
                t1 = time.perf_counter()
                try:
                    est = estimate_pallet(
                        frame, cal, expected=expected, labels=_labels_mode(lk), support_height_m=support
                    )
                except PalletNotFound as exc:
                    a["fail"].append(exc.reason)
                    continue
                a["ms"].append((time.perf_counter() - t1) * 1e3)
                found.append(est)
                for key, value in zip(("lat", "lon", "yaw", "z"), _errors(T_true, est.T_forklift_pallet), strict=True):
                    a[key].append(value)
                a["kind"].append(kind)
            if found:
                a["fused"].append(_errors(T_true, fuse_estimates(found).T_forklift_pallet))
    for name, lk, _ in runnable:
        a = acc[name]
        n_ok = len(a["lat"])
        fails: dict[str, int] = {}
        for reason in a["fail"]:
            fails[reason] = fails.get(reason, 0) + 1
        n_frames = len(specs) * per
        fused = np.array(a["fused"]).reshape(-1, 4)
        res: dict[str, Any] = {
            "available": True,
            "frames": n_frames,
            "detected": n_ok,
            "detection_rate": round(n_ok / max(n_frames, 1), 4),
            "not_found": fails,
            "lateral_mm": _stats(a["lat"], 1e3, 2),
            "longitudinal_mm": _stats(a["lon"], 1e3, 2),
            "yaw_deg": _stats(a["yaw"], 180.0 / math.pi, 3),
            "pocket_height_mm": _stats(a["z"], 1e3, 2),
            "runtime_ms_median": round(float(np.median(a["ms"])), 2) if a["ms"] else None,
            "runtime_ms_p95": round(float(np.percentile(a["ms"], 95)), 2) if a["ms"] else None,
        }
        # Split by distance: the far half carries most of the depth noise (sigma grows with z^2).
        mid = 0.5 * (args.ahead[0] + args.ahead[1])
        # ... and by load: a load hides the top deck, whose board edges refine the yaw of empty pallets.
        groups = {
            "near": [ahead < mid for ahead, _ in a["kind"]],
            "far": [ahead >= mid for ahead, _ in a["kind"]],
            "empty": [not loaded for _, loaded in a["kind"]],
            "loaded": [loaded for _, loaded in a["kind"]],
        }
        for label, member in groups.items():
            idx = [i for i, m in enumerate(member) if m]
            res[f"{label}_p95"] = {
                "lateral_mm": _stats([a["lat"][i] for i in idx], 1e3, 2)["p95"],
                "longitudinal_mm": _stats([a["lon"][i] for i in idx], 1e3, 2)["p95"],
                "yaw_deg": _stats([a["yaw"][i] for i in idx], 180.0 / math.pi, 3)["p95"],
            }
        res["per_estimate"] = {
            "frames_per_estimate": per,
            "estimates": len(specs),
            "detection_rate": round(len(fused) / max(len(specs), 1), 4),
            "lateral_mm": _stats(list(fused[:, 0]), 1e3, 2),
            "longitudinal_mm": _stats(list(fused[:, 1]), 1e3, 2),
            "yaw_deg": _stats(list(fused[:, 2]), 180.0 / math.pi, 3),
        }
        if name == "labels=gt,calibration=true" and n_ok:
            res["goals"] = {key: {"goal": goal, "met": _meets(_value(res, key), goal)} for key, goal in GOALS.items()}
        if lk in ("onnx", "model", "fused"):
            res["segmentation"] = seg_score.result()
        cases[name] = res
    return {
        "standpoints": len(specs),
        "frames_per_estimate": per,
        "seed": args.seed,
        "width": args.width,
        "misplacement": {"lateral_m": args.lateral, "longitudinal_m": args.longitudinal, "yaw_deg": args.yaw_deg},
        "entry_face_ahead_m": list(args.ahead),
        "render_s": round(render_s, 1),
        "cases": cases,
    }


def _errors(T_true: SE3, T_est: SE3) -> tuple[float, float, float, float]:
    """Lateral, longitudinal (m), yaw (rad) and height (m) errors of an estimate in the true pallet frame."""
    err = T_true.inv() @ T_est
    e2 = err.to_se2()
    return e2.y, e2.x, e2.yaw, float(err.t[2])


def _meets(value: float | None, goal: float) -> bool:
    return value is not None and value <= goal


def _value(res: dict[str, Any], key: str) -> float | None:
    if key == "runtime_ms_median":
        return res["runtime_ms_median"]
    quantity, _, stat = key.rpartition("_")
    unit_key = {"lateral_mm": "lateral_mm", "longitudinal_mm": "longitudinal_mm", "yaw_deg": "yaw_deg"}[quantity]
    return res[unit_key][stat]


# -- pallet families (issue 17) --------------------------------------------------------------------

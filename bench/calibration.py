"""`palletpilot bench calibration`: both calibration methods on the same random camera mounts, per fork family.

Each pose: a random true mount (tilt 18-40 deg down, pan +-3 deg, roll about the optical axis +-2 deg,
lateral +-30 mm, height 0.3-0.6 m, forward offset -0.25..+0.10 m from the fork heels), rendered in the
simulator with the default camera noise (`sim.camera.CameraNoise()`: D435 depth noise, flying pixels
and whatever else the camera model adds) plus label boundary noise, at a seeded place of the example
warehouse; mounts whose view does not reach past the fork tips are drawn again (the paper did the
same: its mounts all tilt more than 23 deg so that the tips stay in view), and the number redrawn is
reported. Errors are `estimate - truth`: translation of `T_forklift_camera` in the forklift frame (mm)
and the mount angles tilt, pan, roll (deg). Writes a CSV of every result and two plots like the
paper's Figures 8 and 9 to `--out`.

Fork families (`--families`; the simulator renders the true blades, calibration reads the file):
- `box`: box blades, the forks file stating them (`missions/forks.yaml` plus `taper_length: 0`: a user
  who checked that the blades are plain boxes; without it the profile is unknown and shallow mounts warn);
- `taper_nominal`: ISO 2328 blades whose top face thins over the last 50-150 mm to a 12-25 mm tip
  (random per pose), with the forks file stating only the nominal box (a user who has not measured
  the taper): the calibration must warn that the tips cannot be trusted (`tip_trusted` false);
- `taper_measured`: the same blades with their profile in the forks file (`forks measure`);
- `taper_bottom`: blades whose bottom face slopes up (top flat to the tip), nominal box in the file.
Per family and method: successes, failures, untrusted tips (warnings), poses beyond the goal (`GOAL_MM`,
`GOAL_DEG` on any axis) with trusted tips (`beyond_goal_trusted`: must be 0), and error statistics.

Depth tare (`--tare`): the simulated D435 has a depth scale error (+-0.3 %, fixed per camera), which no
frame of the forks and the floor reveals: it moves the camera back by the error times the fork-tip
distance. With `--tare both` (the default) every pose is calibrated twice: as it is (`model`, `paper`)
and after the camera's depth tare (`model+tare`, `paper+tare`): the same camera renders a flat wall
2.0-3.0 m ahead, turned up to 5 deg, whose distance a laser distance meter gives to +-1.5 mm
(uniform), `perception.depth_tare` measures the scale error from it, and the fork frame's depth is
corrected before calibrating (what `palletpilot camera tare` and `--depth-tare` do on a truck).
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np

from palletpilot.executor.apps.cli_args import count, names, out_folder, seed
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path, write_atomic
from palletpilot.perception.calibration import METHODS, CalibrationError, Method, calibrate
from palletpilot.perception.calibration_io import mount_angles
from palletpilot.perception.depth_tare import DepthTare, correct_depth, measure_depth_tare
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.specs import ForkGeometry, load_forks
from palletpilot.sim.camera import D435_COLOR_VFOV_DEG, RaycastRenderer
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator
from palletpilot.sim.world import wall_mesh

MISSIONS = bundled_path("missions")
PLACES = ("c_w", "j_charge", "j_drop", "b1", "a2", "t_e")  # open floor ahead of the forks
FAMILIES = ("box", "taper_nominal", "taper_measured", "taper_bottom")
TARE_MODES = ("none", "laser", "both")
LASER_ERROR_M = 0.0015
"""Accuracy of the laser distance meter that measures the tare wall's distance (uniform +-)."""
GOAL_MM, GOAL_DEG = 3.0, 0.2
"""The calibration's goal per axis: translation (mm) and mount angles (deg); a pose beyond it must warn."""
AXES = ("err_x_mm", "err_y_mm", "err_z_mm", "err_tilt_deg", "err_pan_deg", "err_roll_deg")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--poses", type=count(1), default=40, help="poses per family")
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument("--families", type=names(FAMILIES), default=list(FAMILIES), help="comma-separated subset")
    parser.add_argument(
        "--tare", choices=TARE_MODES, default="both", help="calibrate without (none) or after (laser) a depth tare"
    )
    parser.add_argument(
        "--out", type=out_folder, default="out/bench_calibration", help="folder for the CSV and the plots"
    )


def _tips_in_view(x: float, z: float, tilt_deg: float, tip_x: float, thickness: float) -> bool:
    """Does the top edge of the image see the fork-top plane at least 15 cm beyond the tips?"""
    top_ray_deg = tilt_deg - 0.5 * D435_COLOR_VFOV_DEG - 1.5  # a margin for pan and roll
    if top_ray_deg <= 0.5:
        return True
    reach = (z - thickness) / math.tan(math.radians(top_ray_deg))
    return x + reach > tip_x + 0.15


def _scenario(rng: np.random.Generator, tip_x: float, thickness: float) -> tuple[Scenario, int]:
    redrawn = 0
    while True:
        mount = {
            "x": float(rng.uniform(-0.25, 0.10)),
            "y": float(rng.uniform(-0.03, 0.03)),
            "z": float(rng.uniform(0.3, 0.6)),
            "tilt_deg": float(rng.uniform(18.0, 40.0)),
            "pan_deg": float(rng.uniform(-3.0, 3.0)),
            "roll_deg": float(rng.uniform(-2.0, 2.0)),
        }
        if _tips_in_view(mount["x"], mount["z"], mount["tilt_deg"], tip_x, thickness):
            break
        redrawn += 1
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": str(rng.choice(PLACES)),
            "seed": int(rng.integers(2**31)),
            "camera": {"mount": mount, "noise": {"label_noise": True, "label_noise_px": 2}},  # else the defaults
        }
    )
    sc.folder = MISSIONS
    return sc, redrawn


def _tare(sim: Simulator, rng: np.random.Generator) -> DepthTare:
    """The depth tare of the simulator's camera: a wall 2-3 m ahead, its distance measured to +-1.5 mm."""
    distance = float(rng.uniform(2.0, 3.0))
    wall = RaycastRenderer(wall_mesh((distance + 0.1, -4.0), (distance + 0.1, 4.0), height=6.0, thickness=0.2))
    look = SE3.from_matrix(np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, 0, 1]], dtype=float))
    turn = SE3.from_xyz_rpy((0.0, 0.0, 0.0), np.radians(rng.uniform(-5.0, 5.0, 3)))  # the camera a little off square
    frame = wall.render(look @ turn, sim.camera, sim.scenario.camera.noise, sim._cam_rng)
    measured = distance + float(rng.uniform(-LASER_ERROR_M, LASER_ERROR_M))
    return measure_depth_tare([frame], measured)


def _errors(T_est: SE3, T_true: SE3) -> list[float]:
    dt = (T_est.t - T_true.t) * 1e3
    da = np.degrees(np.array(mount_angles(T_est)) - np.array(mount_angles(T_true)))
    return [*dt.tolist(), *da.tolist()]


def _blades(family: str, nominal: ForkGeometry, rng: np.random.Generator) -> tuple[ForkGeometry, ForkGeometry]:
    """(the true blades the simulator renders, the forks file calibration reads) of one pose.

    The files of `box` state the profile (`taper_length: 0`); those of `taper_nominal` and `taper_bottom`
    leave it out (unknown, `ForkGeometry.profile_stated` false), whatever `nominal`'s file says.
    """
    box = nominal.model_dump(exclude_unset=True, exclude={"taper_length", "tip_thickness", "taper_side"})
    if family == "box":
        stated = ForkGeometry.model_validate({**box, "taper_length": 0.0})
        return stated, stated
    taper = {
        "taper_length": round(float(rng.uniform(0.05, 0.15)), 4),
        "tip_thickness": round(float(rng.uniform(0.012, 0.025)), 4),
        "taper_side": "bottom" if family == "taper_bottom" else "top",
    }
    true = ForkGeometry.model_validate({**box, **taper})
    return true, true if family == "taper_measured" else ForkGeometry.model_validate(box)


def _yaml(forks: ForkGeometry) -> str:
    return "".join(f"{k}: {v}\n" for k, v in forks.model_dump().items() if v is not None)


def run(args: argparse.Namespace) -> dict:
    """Render the poses of each family, calibrate each with both methods, return the statistics; write CSV and plots."""
    nominal = load_forks(MISSIONS / "forks.yaml")
    rng = np.random.default_rng(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    tare_rows: list[dict] = []
    tare_rng = np.random.default_rng([args.seed, 1])  # its own stream: the same poses with or without the tare
    redrawn_total = 0
    families = list(getattr(args, "families", FAMILIES))
    for family in families:
        for i in range(args.poses):
            true, in_file = _blades(family, nominal, rng)
            sc, redrawn = _scenario(rng, true.tip_x, true.thickness)
            redrawn_total += redrawn
            blades = out / "true_forks.yaml"
            write_atomic(blades, _yaml(true))
            sc.forks = str(blades.resolve())
            sim = Simulator(sc)
            frame = sim.grab()
            tare: DepthTare | None = None
            if args.tare != "none":
                tare = _tare(sim, tare_rng)
                tare_rows.append({"true": float(frame.truth["depth_scale_true"]), "est": tare.depth_scale_error})
            variants = [("", frame)] if args.tare != "laser" else []
            if tare is not None:
                variants.append(("+tare", correct_depth(frame, tare)))
            for suffix, seen in variants:
                for method in METHODS:
                    row = _calibrate_one(seen, in_file, method, sim)
                    row.update({"family": family, "pose": i, "method": method + suffix, "start": sc.start})
                    row.update({f"mount_{k}": v for k, v in sc.camera.mount.model_dump().items()})
                    row.update(
                        {"taper_length": true.taper_length, "tip_thickness": true.tip_thickness or true.thickness}
                    )
                    rows.append(row)

    with (out / "calibration.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    result: dict = {"poses_per_family": args.poses, "seed": args.seed, "mounts_redrawn_tips_out_of_view": redrawn_total}
    if tare_rows:
        err = np.array([(r["est"] - r["true"]) * 100.0 for r in tare_rows])
        result["depth_tare"] = {
            "cameras": len(tare_rows),
            "scale_error_true_pct_max_abs": round(max(abs(r["true"]) * 100.0 for r in tare_rows), 3),
            "scale_error_residual_pct_p95_abs": round(float(np.percentile(np.abs(err), 95)), 4),
            "scale_error_residual_pct_max_abs": round(float(np.max(np.abs(err))), 4),
        }
    methods = sorted({r["method"] for r in rows}, key=lambda m: (m.endswith("+tare"), m != "model"))
    for family in families:
        result[family] = {
            method: _stats([r for r in rows if r["family"] == family and r["method"] == method]) for method in methods
        }
    _plot(rows, out)
    result["csv"] = str(out / "calibration.csv")
    result["plots"] = [str(out / "translation_errors.png"), str(out / "rotation_errors.png")]
    return result


def _calibrate_one(frame: FrameBundle, forks: ForkGeometry, method: Method, sim: Simulator) -> dict:
    """One calibration's result row: errors per axis against the simulator's truth, or the error message."""
    row: dict = {}
    t0 = time.perf_counter()
    try:
        calib = calibrate([frame], forks, method)
        row["runtime_ms"] = (time.perf_counter() - t0) * 1e3
        row.update(dict(zip(AXES, _errors(calib.T_forklift_camera, sim.T_forklift_camera_true), strict=True)))
        row["tip_trusted"] = bool(calib.quality.get("tip_trusted", True))
        row["beyond_tip_points"] = calib.quality.get("beyond_tip_points", 0)
        row["tip_view_deg"] = calib.quality.get("tip_view_deg", math.nan)
        row["error"] = ""
    except CalibrationError as exc:
        row["runtime_ms"] = (time.perf_counter() - t0) * 1e3
        row.update(dict.fromkeys(AXES, math.nan))
        row["tip_trusted"] = False
        row["beyond_tip_points"] = 0
        row["tip_view_deg"] = math.nan
        row["error"] = str(exc)
    return row


def _stats(mine: list[dict]) -> dict:
    """Successes, failures, untrusted tips, trusted poses beyond the goal; p95 of |error| per axis (all, trusted)."""
    ok = [r for r in mine if not r["error"]]
    trusted = [r for r in ok if r["tip_trusted"]]
    stats: dict = {"succeeded": len(ok), "failed": len(mine) - len(ok), "tip_untrusted": len(ok) - len(trusted)}
    stats["beyond_goal_trusted"] = sum(
        any(abs(r[a]) > (GOAL_MM if a.endswith("_mm") else GOAL_DEG) for a in AXES) for r in trusted
    )
    for axis in AXES:
        e = np.array([r[axis] for r in ok])
        if len(e) == 0:
            continue
        stats[axis] = {
            "median_abs": round(float(np.median(np.abs(e))), 3),
            "p95_abs": round(float(np.percentile(np.abs(e), 95)), 3),
            "max_abs": round(float(np.max(np.abs(e))), 3),
            "mean_bias": round(float(np.mean(e)), 3),
        }
        if trusted and len(trusted) < len(ok):
            et = np.array([r[axis] for r in trusted])
            stats[axis]["p95_abs_trusted"] = round(float(np.percentile(np.abs(et), 95)), 3)
    stats["runtime_ms_median"] = round(float(np.median([r["runtime_ms"] for r in mine])), 1)
    if len(ok) < len(mine):
        stats["failures"] = sorted({r["error"].split(": ", 1)[-1][:80] for r in mine if r["error"]})[:5]
    return stats


def _plot(rows: list[dict], out: Path) -> None:
    """Per-pose errors of both methods, translation (mm) and rotation (deg), like the paper's Fig. 8 and 9."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for axes, unit, name in ((AXES[:3], "mm", "translation_errors.png"), (AXES[3:], "deg", "rotation_errors.png")):
        fig, panels = plt.subplots(len(axes), 1, figsize=(10, 8), sharex=True, dpi=110)
        for panel, axis in zip(panels, axes, strict=True):
            for method, marker in (("paper", "x"), ("model", "o"), ("model+tare", ".")):
                mine = [r for r in rows if r["method"] == method]
                panel.plot(range(len(mine)), [r[axis] for r in mine], marker, ms=3, label=method)
            panel.axhline(0.0, color="k", lw=0.5)
            panel.set_ylabel(f"{axis.split('_')[1]} error ({unit})")
            panel.grid(True, lw=0.3)
        panels[0].legend()
        panels[-1].set_xlabel("pose (families in turn)")
        fig.suptitle("calibration error, estimate - truth (simulated D435, label noise)")
        fig.tight_layout()
        fig.savefig(out / name)
        plt.close(fig)

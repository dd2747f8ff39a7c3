"""`palletpilot bench calibration`: both calibration methods on the same random camera mounts.

Each pose: a random true mount (tilt 18-40 deg down, pan +-3 deg, roll about the optical axis +-2 deg,
lateral +-30 mm, height 0.3-0.6 m, forward offset -0.25..+0.10 m from the fork heels), rendered in the
simulator with D435 depth noise, flying pixels and label boundary noise, at a seeded place of the
example warehouse; mounts whose view does not reach past the fork tips are drawn again (the paper
did the same: its mounts all tilt more than 23 deg so that the tips stay in view), and the number
redrawn is reported. Errors are `estimate - truth`: translation of `T_forklift_camera` in the forklift
frame (mm) and the mount angles tilt, pan, roll (deg). Writes a CSV of every result and two plots
like the paper's Figures 8 and 9 to `--out`.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np

from palletpilot.executor.cli_args import count, out_folder, seed
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration import METHODS, CalibrationError, calibrate
from palletpilot.perception.calibration_io import mount_angles
from palletpilot.perception.specs import load_forks
from palletpilot.sim.camera import D435_COLOR_VFOV_DEG
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")
PLACES = ("c_w", "j_charge", "j_drop", "b1", "a2", "t_e")  # open floor ahead of the forks
AXES = ("err_x_mm", "err_y_mm", "err_z_mm", "err_tilt_deg", "err_pan_deg", "err_roll_deg")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--poses", type=count(1), default=100)
    parser.add_argument("--seed", type=seed, default=0)
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
            "camera": {
                "mount": mount,
                "noise": {"depth_noise": True, "flying_pixel_rate": 0.5, "label_noise": True, "label_noise_px": 2},
            },
        }
    )
    sc.folder = MISSIONS
    return sc, redrawn


def _errors(T_est: SE3, T_true: SE3) -> list[float]:
    dt = (T_est.t - T_true.t) * 1e3
    da = np.degrees(np.array(mount_angles(T_est)) - np.array(mount_angles(T_true)))
    return [*dt.tolist(), *da.tolist()]


def run(args: argparse.Namespace) -> dict:
    """Render the poses, calibrate each with both methods, return the statistics; write CSV and plots."""
    forks = load_forks(MISSIONS / "forks.yaml")
    rng = np.random.default_rng(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    redrawn_total = 0
    for i in range(args.poses):
        sc, redrawn = _scenario(rng, forks.tip_x, forks.thickness)
        redrawn_total += redrawn
        sim = Simulator(sc)
        frame = sim.grab()
        for method in METHODS:
            mount = {f"mount_{k}": v for k, v in sc.camera.mount.model_dump().items()}
            row: dict = {"pose": i, "method": method, "start": sc.start, **mount}
            t0 = time.perf_counter()
            try:
                calib = calibrate([frame], forks, method)
                row["runtime_ms"] = (time.perf_counter() - t0) * 1e3
                row.update(dict(zip(AXES, _errors(calib.T_forklift_camera, sim.T_forklift_camera_true), strict=True)))
                row["error"] = ""
            except CalibrationError as exc:
                row["runtime_ms"] = (time.perf_counter() - t0) * 1e3
                row.update(dict.fromkeys(AXES, math.nan))
                row["error"] = str(exc)
            rows.append(row)

    with (out / "calibration.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    result: dict = {"poses": args.poses, "seed": args.seed, "mounts_redrawn_tips_out_of_view": redrawn_total}
    for method in METHODS:
        mine = [r for r in rows if r["method"] == method]
        ok = [r for r in mine if not r["error"]]
        stats: dict = {"succeeded": len(ok), "failed": len(mine) - len(ok)}
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
        stats["runtime_ms_median"] = round(float(np.median([r["runtime_ms"] for r in mine])), 1)
        if len(ok) < len(mine):
            stats["failures"] = sorted({r["error"].split(": ", 1)[-1][:80] for r in mine if r["error"]})[:5]
        result[method] = stats
    _plot(rows, out)
    result["csv"] = str(out / "calibration.csv")
    result["plots"] = [str(out / "translation_errors.png"), str(out / "rotation_errors.png")]
    return result


def _plot(rows: list[dict], out: Path) -> None:
    """Per-pose errors of both methods, translation (mm) and rotation (deg), like the paper's Fig. 8 and 9."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for axes, unit, name in ((AXES[:3], "mm", "translation_errors.png"), (AXES[3:], "deg", "rotation_errors.png")):
        fig, panels = plt.subplots(len(axes), 1, figsize=(10, 8), sharex=True, dpi=110)
        for panel, axis in zip(panels, axes, strict=True):
            for method, marker in (("paper", "x"), ("model", "o")):
                mine = [r for r in rows if r["method"] == method]
                panel.plot([r["pose"] for r in mine], [r[axis] for r in mine], marker, ms=3, label=method)
            panel.axhline(0.0, color="k", lw=0.5)
            panel.set_ylabel(f"{axis.split('_')[1]} error ({unit})")
            panel.grid(True, lw=0.3)
        panels[0].legend()
        panels[-1].set_xlabel("pose")
        fig.suptitle("calibration error, estimate - truth (simulated D435, label noise)")
        fig.tight_layout()
        fig.savefig(out / name)
        plt.close(fig)

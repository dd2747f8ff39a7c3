"""A RealSense stream's lens distortion as OpenCV's 5 coefficients (k1, k2, p1, p2, k3).

`rs.align` puts each depth point where librealsense's own projection (`rs2_project_point_to_pixel`, with
the colour stream's model) lands it, so a bundle's `dist` must describe that projection:

- `none`, or all coefficients zero (as many D435 colour streams report): no distortion (None).
- `brown_conrady` is OpenCV's model, coefficient for coefficient.
- `inverse_brown_conrady` (most D4xx colour streams) and `modified_brown_conrady` are, in pyrealsense2 2.59,
  the same polynomial with the tangential terms applied to the radially distorted point, both for
  projecting (the "inverse" in the name describes how older SDKs used the coefficients, distorted to
  ideal, which 2.59 no longer does); their coefficients are converted by fitting OpenCV's 5 to the SDK's
  projection over the whole image (`perception.distortion.fit_brown_conrady`), refused when the fit misses
  by more than `MAX_DIST_FIT_PX`.
- The fisheye models (`ftheta`, `kannala_brandt4`) are refused.

Refusals are `PerceptionError`s naming the stream. The fit is kept per stream (`functools.lru_cache`).

Public API: `opencv_distortion`, `MAX_DIST_FIT_PX` (also importable from `perception.realsense`).
"""

from __future__ import annotations

import functools
from types import ModuleType
from typing import Any

import numpy as np

from palletpilot.perception.distortion import fit_brown_conrady
from palletpilot.perception.errors import PerceptionError

__all__ = ["MAX_DIST_FIT_PX", "opencv_distortion"]

MAX_DIST_FIT_PX = 0.1
"""The largest miss (px) of OpenCV's 5 coefficients fitted to a RealSense stream's own lens model."""
_FIT_GRID = (33, 25)  # ideal points across the image (and 5 % beyond its borders) for that fit


def opencv_distortion(rs: ModuleType, intr: Any, where: str) -> np.ndarray | None:
    """A RealSense stream's lens distortion (`rs.intrinsics`) as OpenCV's 5 coefficients, or None when it has
    none; `PerceptionError` for a model this cannot express (module docstring)."""
    model = intr.model
    coeffs = tuple(float(c) for c in intr.coeffs)
    if model == rs.distortion.none or not any(coeffs):
        return None
    if model == rs.distortion.brown_conrady:
        return np.array(coeffs[:5], dtype=np.float64)
    if model in (rs.distortion.inverse_brown_conrady, rs.distortion.modified_brown_conrady):
        key = (int(model), coeffs, intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy)
        dist, miss_px = _fitted_distortion(rs, key)
        if miss_px > MAX_DIST_FIT_PX:
            raise PerceptionError(
                f"{where}: colour lens model {model.name} [{', '.join(f'{c:.4g}' for c in coeffs)}]: OpenCV's 5 "
                "coefficients fitted to "
                f"librealsense's projection miss it by {miss_px:.2f} px (at most {MAX_DIST_FIT_PX:g}): not supported"
            )
        return dist
    raise PerceptionError(
        f"{where}: colour lens model {model.name} (a fisheye model) is not supported: perception undistorts "
        "Brown-Conrady lenses (OpenCV's k1, k2, p1, p2, k3)"
    )


@functools.lru_cache(maxsize=8)
def _fitted_distortion(rs: ModuleType, key: tuple[Any, ...]) -> tuple[np.ndarray | None, float]:
    """OpenCV's 5 coefficients fitted to librealsense's own projection of a stream (`key`: its model, the
    coefficients, width, height, fx, fy, ppx, ppy) and the largest miss (px); None when they are all zero."""
    model, coeffs, w, h, fx, fy, ppx, ppy = key
    intr = rs.intrinsics()
    intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = w, h, fx, fy, ppx, ppy
    intr.model, intr.coeffs = rs.distortion(model), list(coeffs)
    us = np.linspace(-0.05 * w, 1.05 * w, _FIT_GRID[0])
    vs = np.linspace(-0.05 * h, 1.05 * h, _FIT_GRID[1])
    ideal = np.array([((u - ppx) / fx, (v - ppy) / fy) for v in vs for u in us])
    pixels = np.array([rs.rs2_project_point_to_pixel(intr, [x, y, 1.0]) for x, y in ideal], dtype=np.float64)
    distorted = np.column_stack([(pixels[:, 0] - ppx) / fx, (pixels[:, 1] - ppy) / fy])
    dist, miss = fit_brown_conrady(ideal, distorted)
    if not np.any(np.abs(dist) > 1e-9):  # an SDK that projects this model without distortion
        return None, 0.0
    return dist, miss * max(fx, fy)

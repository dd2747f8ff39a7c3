"""The simulated camera's noise model: what `sim.camera.RaycastRenderer` adds to exact depth, labels and RGB.

`CameraNoise` (a scenario file's `camera.noise` block; `CameraNoise.off()` is an ideal camera) says which
imperfections a rendered frame gets; the renderer draws them all from the `numpy.random.Generator`
passed in:

- D435 stereo depth noise: a disparity error of `disparity_sigma_px` (`D435_SUBPIXEL_PX`, 0.08 px
  subpixel) turned into depth through `z = f B / d`, so sigma(z) = z^2 s / (f B) (`CameraNoise.sigma_z`)
  with B = `D435_BASELINE_M` (0.050 m) and f the depth sensor's focal length in pixels at the stream
  resolution (`sim.camera.d435_depth_focal_px`);
- flying pixels: at depth edges a share of pixels takes a depth between foreground and background;
- correlated noise (`depth_correlation_px` > 1): the disparity errors are spread over patches of about that
  many pixels (white noise blurred by a Gaussian, its per-pixel sigma kept: `_correlation_kernel`), as real
  stereo block matching and ToF filtering give them;
- dropouts at `invalid_rate`, depth quantised to `depth_unit_m` (1 mm, the Z16 unit);
- no depth closer than the camera's `min_depth_m` (0.28 m) or beyond its `max_depth_m`;
- stereo shadow (`stereo_shadow`): no depth where the right IR imager, `baseline_m` to the image right,
  cannot see the point: the no-depth band on the image-left side of foreground objects, computed from
  the exact depth (`sim.depth_artefacts`);
- depth scale error (`depth_scale_error`): every depth times `1 + s`, s uniform in +-`depth_scale_error`,
  fixed per camera (per seeded generator) and recorded in the bundle's truth as `depth_scale_true`;
- `depth_noise: false` turns every depth artefact off (exact depth, only the range limits apply);
- optional label noise (`perturb_labels`): each class's boundary dilated or eroded by up to
  `label_noise_px` pixels (the exact labels stay in the bundle's truth as `labels_true`);
- RGB sensor noise (`rgb_sigma`: one random byte per sample picks a Gaussian quantile, `_rgb_noise_luts`)
  and per-frame lighting variation (`lighting_variation`, `sim.camera.Lighting.varied`).

Public API (all also importable from `sim.camera`): `CameraNoise`, `perturb_labels`, `D435_BASELINE_M`,
`D435_SUBPIXEL_PX`. Package-internal (used by `sim.camera`): `_correlation_kernel`, `_rgb_noise_luts`.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import ArrayLike
from pydantic import ConfigDict, Field
from scipy import special

from palletpilot.geometry.fileio import FileModel

__all__ = ["D435_BASELINE_M", "D435_SUBPIXEL_PX", "CameraNoise", "perturb_labels"]

D435_BASELINE_M = 0.050
"""Baseline (m) of the D435's two IR imagers: the stereo depth noise's B."""
D435_SUBPIXEL_PX = 0.08
"""The D435's subpixel disparity error (px): the default `CameraNoise.disparity_sigma_px`."""


class CameraNoise(FileModel):
    """Sensor imperfections; `CameraNoise.off()` is an ideal camera. Scenario files may carry this block."""

    model_config = ConfigDict(frozen=True)

    depth_noise: bool = True  # every depth artefact below; false: exact depth
    disparity_sigma_px: float = Field(D435_SUBPIXEL_PX, ge=0, le=5.0, description="stereo subpixel error (px)")
    baseline_m: float = Field(D435_BASELINE_M, gt=0, le=1.0)
    depth_correlation_px: float = Field(
        1.0, ge=1.0, le=100.0, description="correlation area (px) of the disparity noise; 1 = independent pixels"
    )
    depth_unit_m: float = Field(0.001, ge=0, le=0.1, description="depth quantisation (m); 0 = none")
    invalid_rate: float = Field(0.005, ge=0, le=1, description="share of pixels randomly without depth")
    flying_pixel_rate: float = Field(0.5, ge=0, le=1, description="share of depth-edge pixels that fly")
    edge_jump_rel: float = Field(0.08, gt=0, le=1.0, description="depth jump (fraction of z) that makes an edge")
    stereo_shadow: bool = Field(True, description="no depth where something hides the point from the right IR imager")
    depth_scale_error: float = Field(
        0.003, ge=0, le=0.05, description="max relative depth scale error, drawn once per camera in +-this"
    )
    label_noise: bool = False
    label_noise_px: int = Field(2, ge=0, le=50, description="max boundary dilation / erosion (px)")
    rgb_sigma: float = Field(2.0, ge=0, le=100.0, description="RGB sensor noise std (8-bit levels)")
    lighting_variation: bool = True

    @classmethod
    def off(cls) -> CameraNoise:
        """An ideal camera: exact depth (only the range limits apply), clean labels, steady light."""
        return cls(
            depth_noise=False,
            stereo_shadow=False,
            depth_scale_error=0.0,
            label_noise=False,
            rgb_sigma=0.0,
            lighting_variation=False,
        )

    def sigma_z(self, z: ArrayLike, depth_focal_px: float) -> np.ndarray:
        """Depth noise std (m) at z-depth z (m): z^2 s / (f B)."""
        z = np.asarray(z, dtype=float)
        return z * z * self.disparity_sigma_px / (depth_focal_px * self.baseline_m)


def perturb_labels(labels: np.ndarray, max_px: int, rng: np.random.Generator) -> np.ndarray:
    """Dilate or erode each class's region by a random 0..max_px pixels (a segmentation network's boundary error).

    Classes are visited in random order. A dilation grows the class over its neighbours; an erosion
    hands its boundary band to the neighbouring class (the highest id where several meet).
    Returns a new uint8 image.
    """
    out = labels.copy()
    if max_px <= 0:
        return out
    present = np.flatnonzero(np.bincount(labels.ravel(), minlength=256)).astype(np.uint8)  # np.unique, 4x faster
    for cls in rng.permutation(present):
        radius = int(rng.integers(0, max_px + 1))
        grow = rng.random() < 0.5
        if radius == 0:
            continue
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        mask = (out == cls).astype(np.uint8)
        if grow:
            out[cv2.dilate(mask, kernel).astype(bool)] = cls
            continue
        band = mask.astype(bool) & ~cv2.erode(mask, kernel, borderType=cv2.BORDER_REPLICATE).astype(bool)
        others = np.where(mask.astype(bool), np.uint8(0), out)
        neighbour = cv2.dilate(others, kernel, borderType=cv2.BORDER_REPLICATE)
        out[band] = neighbour[band]
    return out


@lru_cache(maxsize=8)
def _correlation_kernel(area_px: float) -> tuple[np.ndarray, float]:
    """A 1-D Gaussian kernel (float32 column) whose separable 2-D blur turns independent unit-variance
    pixels into noise correlated over `area_px` pixels (the sum of its autocorrelation, `(sum k)^2 / sum k^2`
    of the 2-D kernel), and the gain that brings that noise back to unit variance."""

    def area(s: float) -> tuple[float, np.ndarray]:
        half = max(1, int(np.ceil(4.0 * s)))
        k = np.exp(-0.5 * (np.arange(-half, half + 1) / s) ** 2)
        k /= k.sum()
        return 1.0 / float(np.sum(k * k)) ** 2, k

    lo, hi = 0.05, 10.0  # the Gaussian's sigma (px), by bisection on the area it gives
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if area(mid)[0] < area_px else (lo, mid)
    got, k = area(0.5 * (lo + hi))
    return k.astype(np.float32).reshape(-1, 1), float(np.sqrt(got))


@lru_cache(maxsize=8)
def _rgb_noise_luts(sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Byte -> (positive part, negative part) of a Gaussian quantile of std `sigma` (8-bit levels).

    Byte k stands for the normal quantile at (k + 0.5) / 256, rounded to whole levels and rescaled
    so the 256 values have exactly the requested std; add one part and subtract the other.
    """
    quantiles = special.ndtri((np.arange(256) + 0.5) / 256.0)
    levels = np.rint(quantiles * sigma)
    if levels.std() > 0:
        levels = np.rint(quantiles * sigma * sigma / levels.std())
    return (
        np.clip(levels, 0, 255).astype(np.uint8).reshape(256, 1),
        np.clip(-levels, 0, 255).astype(np.uint8).reshape(256, 1),
    )

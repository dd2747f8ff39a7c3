"""Depth noise correlation: how many pixels a depth camera's errors are correlated over (issue 37).

A pallet estimate's spread comes from fits over thousands of pixels whose covariance assumes each pixel's
depth error is independent. Real stereo and ToF depth is not: block matching, the ToF's lens and
filtering spread one error over a patch of pixels, so N fitted pixels carry about as much as N / `area`
independent ones, and the stated spread is sqrt(`area`) too small (3-5 times on the real frames of
issue 37). `area`, the correlation area (the effective pixel count), is a property of the camera and its
depth settings, measured here from still frames:

`measure_depth_correlation(frames)`: two or more frames of one still scene from a still camera. Per pixel
with depth in every frame, inverse depth `w = 1 / z` (a stereo camera's noise is constant in `w`) minus its
mean over the frames leaves the temporal noise (the scene, whatever it is, cancels); pixels whose
deviation passes `OUTLIER_SIGMAS` robust sigmas in any frame (flying pixels at edges, dropouts) are left
out. The noise's normalised spatial autocorrelation `rho(dx, dy)` (over the valid pixel pairs, by FFT) is
summed over lags within `max_lag_px`: `area = sum rho`, 1 for independent pixels, `4 pi s^2` for noise
blurred by a Gaussian of `s` pixels. What stays the same in every frame (a fixed pattern) cancels with
the scene and is not counted.

Frames: camera images, pixels. Public API: `DepthNoise`, `measure_depth_correlation`, `MAX_LAG_PX`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle

MAX_LAG_PX = 8
"""Lags summed in each direction (pixels): a 17 x 17 window, wider than any camera's noise patch."""
OUTLIER_SIGMAS = 5.0
"""A pixel deviating more than this many robust sigmas from its mean in some frame is left out."""
MIN_PIXELS = 2000
"""Fewest pixels with depth in every frame for a measurement."""


@dataclass(frozen=True)
class DepthNoise:
    """A depth camera's measured noise: its correlation area (pixels, at least 1), the per-pixel inverse-depth
    noise (1/m, 1-sigma), the pixels and frames it came from."""

    depth_correlation_px: float
    inverse_depth_sigma: float
    pixels: int
    frames: int

    def to_json(self) -> dict[str, Any]:
        """The measurement as JSON."""
        return dataclasses.asdict(self)


def measure_depth_correlation(frames: Sequence[FrameBundle], max_lag_px: int = MAX_LAG_PX) -> DepthNoise:
    """The correlation area of the depth noise of `frames` (a still camera, a still scene; see the module
    docstring). Raises `PerceptionError` (one line) for fewer than two frames, frames of different sizes
    or too few pixels with depth in all of them."""
    if len(frames) < 2:
        raise PerceptionError(f"camera noise: needs two or more frames of one still scene (got {len(frames)})")
    shape = frames[0].depth.shape
    if any(f.depth.shape != shape for f in frames):
        raise PerceptionError("camera noise: the frames differ in size (they must come from one camera mode)")
    z = np.stack([np.asarray(f.depth, float) for f in frames])
    valid = np.all(np.isfinite(z) & (z > 0), axis=0)
    if int(valid.sum()) < MIN_PIXELS:
        raise PerceptionError(
            f"camera noise: only {int(valid.sum())} pixels have depth in every frame (at least {MIN_PIXELS})"
        )
    w = np.where(valid, 1.0 / np.where(valid, z, 1.0), 0.0)
    r = np.where(valid, w - w.mean(axis=0), 0.0)
    scale = 1.4826 * float(np.median(np.abs(r[:, valid]))) + 1e-12
    valid &= np.all(np.abs(r) <= OUTLIER_SIGMAS * scale, axis=0)
    if int(valid.sum()) < MIN_PIXELS:
        raise PerceptionError(f"camera noise: only {int(valid.sum())} pixels are steady in every frame")
    r = np.where(valid, r, 0.0)
    rho = _autocorrelation(r, valid, max_lag_px)
    k = len(frames)
    sigma = float(np.sqrt(np.mean(r[:, valid] ** 2) * k / (k - 1)))  # the mean took 1/k of the variance
    return DepthNoise(max(float(rho.sum()), 1.0), sigma, int(valid.sum()), k)


def _autocorrelation(r: np.ndarray, valid: np.ndarray, max_lag: int) -> np.ndarray:
    """Normalised autocorrelation (2 L + 1, 2 L + 1) of the residual images `r` (K, H, W; 0 off `valid`) over
    lags up to `max_lag`, each lag averaged over the valid pixel pairs it has."""
    _, h, wd = r.shape
    fh, fw = h + max_lag, wd + max_lag  # zero padding: no wrap-around within the lags used
    fr = np.fft.rfft2(r, s=(fh, fw))
    num = np.fft.irfft2(np.sum(fr * np.conj(fr), axis=0), s=(fh, fw))
    fm = np.fft.rfft2(valid.astype(float), s=(fh, fw))
    pairs = np.fft.irfft2(fm * np.conj(fm), s=(fh, fw)) * len(r)
    lags = np.r_[0 : max_lag + 1, -max_lag:0]
    num = num[np.ix_(lags, lags)]
    pairs = np.maximum(np.rint(pairs[np.ix_(lags, lags)]), 1.0)
    cov = num / pairs
    rho = cov / cov[0, 0]
    return np.fft.fftshift(rho)

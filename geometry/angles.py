"""Angle helpers (radians)."""

from __future__ import annotations

from typing import overload

import numpy as np
from numpy.typing import ArrayLike


@overload
def wrap_angle(angle: float) -> float: ...
@overload
def wrap_angle(angle: ArrayLike) -> np.ndarray | float: ...
def wrap_angle(angle: ArrayLike) -> np.ndarray | float:
    """Wrap an angle (rad, scalar or array) into [-pi, pi)."""
    wrapped = (np.asarray(angle, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi
    return float(wrapped) if wrapped.ndim == 0 else wrapped


@overload
def angle_diff(a: float, b: float) -> float: ...
@overload
def angle_diff(a: ArrayLike, b: ArrayLike) -> np.ndarray | float: ...
def angle_diff(a: ArrayLike, b: ArrayLike) -> np.ndarray | float:
    """Smallest signed difference a - b (rad), in [-pi, pi)."""
    return wrap_angle(np.asarray(a, dtype=float) - np.asarray(b, dtype=float))

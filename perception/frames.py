"""Frame bundles: one aligned RGB-D frame (plus labels) as it leaves a camera source.

Data contract (ARCHITECTURE.md), all in the camera's optical frame (x right, y down, z forward):

- `depth`: float32 H x W, z-depth in metres along the optical axis (not the ray length);
  0 or NaN means no data. Depth is aligned to the colour image.
- `K`: float64 3 x 3 pinhole intrinsics of that image (pixel centres at integer coordinates,
  the OpenCV / librealsense convention: `u = fx * x / z + cx`).
- `labels`: optional uint8 H x W semantic class ids (`SemanticClass`; 255 = unlabeled).
- `rgb`: optional uint8 H x W x 3, RGB order.
- `fork_height`: lift height (m) of the fork bottoms when the frame was taken, default 0.
- `dist`: optional float64 lens distortion coefficients of the colour image, in OpenCV's order and
  model (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tau_x, tau_y]]]]: 4, 5, 8, 12 or 14 of them; ROS
  `plumb_bob` is the 5, `rational_polynomial` the 8). None or all zero: an ideal pinhole image. With
  coefficients, `K` alone does not deproject a pixel: `perception.distortion.undistort_bundle` gives
  the same frame as an ideal pinhole camera with the same K, and perception calls it first.
- `truth`: simulator-only arrays under keys ending in `_true` (for example
  `T_forklift_camera_true`, `T_forklift_pallet_true`, 4 x 4 float64). Perception never reads them;
  they exist so tests and benchmarks can score estimates against the truth.

`save_bundle` / `load_bundle` store a bundle as an `.npz` with exactly these keys.

Public API: `FrameBundle`, `save_bundle`, `load_bundle`, `load_bundles`, and re-exported from the
modules below (import them from here): `SemanticClass`, `BUNDLE_KEYS`, `TRUTH_SUFFIX` and the limits
(`MAX_IMAGE_SIDE`, `MAX_DEPTH_M`, `FOCAL_RANGE`, `PIXEL_ASPECT_RANGE`, `MAX_SKEW`,
`FORK_HEIGHT_RANGE_M`, `FORK_HEIGHT_TOLERANCE_M`, `MAX_TRUTH_ELEMENTS`, `MAX_BUNDLE_FILE_BYTES`,
`MAX_BUNDLE_BYTES`, `MAX_MEMBERS`, `MAX_HEADER_BYTES`, `DIST_LENGTHS`).

Every bundle is checked, however it was made (`FrameBundle.__post_init__`, the checks in
`perception.bundle_contract`): dtypes and shapes, image size, depth in metres, a plausible pinhole K,
known class ids, a plausible fork height, a lens model that fits the image. A bundle file may come
from anywhere (a camera, a colleague, a damaged disk, someone hostile), so `load_bundle` reads it with
`perception.bundle_archive`: the zip directory and every `.npy` header are checked against the limits
before a single array is decompressed, object arrays (pickles) are never loaded, and a damaged archive
is `FILE: corrupt frame bundle: ...`. Every problem is one line that starts with the file's path
(`FILE: KEY: problem`), and every problem of a file is reported (`PerceptionError.problems`);
`load_bundles` reports every bad file of a list at once.

The fork height is checked against the generic `FORK_HEIGHT_RANGE_M` unless the caller knows the
truck and passes its mast's range (`mast_range_m` of `load_bundle` / `load_bundles`, e.g.
`palletpilot estimate-pallet --vehicle V.yaml`).
"""

from __future__ import annotations

import io
from collections.abc import Iterable
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from palletpilot.geometry.fileio import write_atomic
from palletpilot.perception.bundle_archive import (
    MAX_BUNDLE_BYTES,
    MAX_BUNDLE_FILE_BYTES,
    MAX_HEADER_BYTES,
    MAX_MEMBERS,
    _read_arrays,
)
from palletpilot.perception.bundle_contract import (
    BUNDLE_KEYS,
    DIST_LENGTHS,
    FOCAL_RANGE,
    FORK_HEIGHT_RANGE_M,
    FORK_HEIGHT_TOLERANCE_M,
    MAX_DEPTH_M,
    MAX_IMAGE_SIDE,
    MAX_SKEW,
    MAX_TRUTH_ELEMENTS,
    PIXEL_ASPECT_RANGE,
    TRUTH_SUFFIX,
    SemanticClass,
    _check_bundle,
    _error,
)
from palletpilot.perception.errors import PerceptionError

__all__ = [
    "BUNDLE_KEYS",
    "DIST_LENGTHS",
    "FOCAL_RANGE",
    "FORK_HEIGHT_RANGE_M",
    "FORK_HEIGHT_TOLERANCE_M",
    "MAX_BUNDLE_BYTES",
    "MAX_BUNDLE_FILE_BYTES",
    "MAX_DEPTH_M",
    "MAX_HEADER_BYTES",
    "MAX_IMAGE_SIDE",
    "MAX_MEMBERS",
    "MAX_SKEW",
    "MAX_TRUTH_ELEMENTS",
    "PIXEL_ASPECT_RANGE",
    "TRUTH_SUFFIX",
    "FrameBundle",
    "SemanticClass",
    "load_bundle",
    "load_bundles",
    "save_bundle",
]

# Where a bundle is being checked (a file path, or "FrameBundle" for one built in memory) and the
# mast's range: `load_bundle` sets them for the `FrameBundle` it builds, so that its constructor's
# one validation pass names the file.
_CHECK_AS: ContextVar[tuple[str, tuple[float, float] | None]] = ContextVar(
    "palletpilot_frame_check_as", default=("FrameBundle", None)
)


@dataclass(frozen=True, eq=False)
class FrameBundle:
    """One aligned RGB-D frame in the camera's optical frame (see the module docstring).

    Construction validates the contract and raises `PerceptionError` with one line per bad field
    (`FrameBundle: K: ...`; `load_bundle` names the file instead). Compared by identity (arrays have
    no single truth value).
    """

    depth: np.ndarray
    K: np.ndarray
    labels: np.ndarray | None = None
    rgb: np.ndarray | None = None
    fork_height: float = 0.0
    truth: dict[str, np.ndarray] = field(default_factory=dict)
    stamp_s: float | None = None
    """Capture time (s, on the clock of whoever grabbed it: the runner's) when known; not stored in `.npz`."""
    dist: np.ndarray | None = None
    """Lens distortion coefficients (OpenCV order, float64; module docstring), or None for an ideal pinhole."""

    def __post_init__(self) -> None:
        where, mast_range_m = _CHECK_AS.get()
        _check_bundle(
            self.depth, self.K, self.labels, self.rgb, self.fork_height, self.truth, where, mast_range_m, self.dist
        )
        object.__setattr__(self, "fork_height", float(self.fork_height))

    @property
    def distorted(self) -> bool:
        """Whether the image has lens distortion (`dist` with a coefficient other than zero)."""
        return self.dist is not None and bool(np.any(self.dist != 0.0))

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return int(self.depth.shape[1])

    def valid_depth(self) -> np.ndarray:
        """Boolean H x W mask of pixels with a depth measurement (finite and > 0)."""
        return np.isfinite(self.depth) & (self.depth > 0)


def save_bundle(path: str | Path, bundle: FrameBundle) -> Path:
    """Write `bundle` to `path` as a compressed `.npz` (`.npz` appended if missing), atomically; return the path."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    arrays: dict[str, np.ndarray] = {
        "depth": bundle.depth,
        "K": bundle.K,
        "fork_height": np.array(bundle.fork_height, dtype=np.float64),
    }
    if bundle.labels is not None:
        arrays["labels"] = bundle.labels
    if bundle.rgb is not None:
        arrays["rgb"] = bundle.rgb
    if bundle.dist is not None:
        arrays["dist"] = bundle.dist
    arrays.update(bundle.truth)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)  # type: ignore[arg-type]  # numpy stubs: a key could be allow_pickle
    return write_atomic(path, buf.getvalue())  # OutputError (one line) when it cannot be written


def load_bundle(
    path: str | Path, mast_range_m: tuple[float, float] | None = None, need_labels: bool = False
) -> FrameBundle:
    """Read and validate a bundle `.npz` (module docstring); problems raise `PerceptionError`, one line each.

    `mast_range_m`: (lowest, highest) lift height (m) of the truck's mast when the caller knows the
    vehicle; without it the fork height is checked against `FORK_HEIGHT_RANGE_M`. `need_labels`: the
    caller needs labels (calibration, pallet estimation), so a bundle with neither labels nor rgb
    to segment them from is refused too.
    """
    path = Path(path)
    arrays = _read_arrays(path)
    truth = {key: value for key, value in arrays.items() if key.endswith(TRUTH_SUFFIX)}
    fork_height = arrays.get("fork_height")
    token = _CHECK_AS.set((str(path), mast_range_m))
    try:
        bundle = FrameBundle(
            depth=arrays["depth"],
            K=arrays["K"],
            labels=arrays.get("labels"),
            rgb=arrays.get("rgb"),
            fork_height=0.0 if fork_height is None else float(fork_height),
            truth=truth,
            dist=arrays.get("dist"),
        )
    finally:
        _CHECK_AS.reset(token)
    if need_labels and bundle.labels is None and bundle.rgb is None:
        raise PerceptionError(f"{path}: labels: missing, and there is no rgb to segment them from")
    return bundle


def load_bundles(
    paths: Iterable[str | Path], mast_range_m: tuple[float, float] | None = None, need_labels: bool = False
) -> list[FrameBundle]:
    """Load every bundle of a list (`load_bundle`); the problems of all bad files raise one `PerceptionError`.

    Its `problems` hold one line per problem, each starting with its file's path; its message is the
    first (with how many files are bad and how many more problems there are). No paths is an error too.
    """
    paths = list(paths)
    if not paths:
        raise PerceptionError("no frame bundles given")
    bundles: list[FrameBundle] = []
    problems: list[str] = []
    bad_files = 0
    for path in paths:
        try:
            bundles.append(load_bundle(path, mast_range_m, need_labels))
        except PerceptionError as exc:
            problems += exc.problems
            bad_files += 1
    if problems:
        raise _error(problems, f"{bad_files} of {len(paths)} frame bundles are bad" if bad_files > 1 else "")
    return bundles

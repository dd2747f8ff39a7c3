"""Frame bundles: one aligned RGB-D frame (plus labels) as it leaves a camera source.

Data contract (ARCHITECTURE.md), all in the camera's optical frame (x right, y down, z forward):

- `depth`: float32 H x W, z-depth in metres along the optical axis (not the ray length);
  0 or NaN means no data. Depth is aligned to the colour image.
- `K`: float64 3 x 3 pinhole intrinsics of that image (pixel centres at integer coordinates,
  the OpenCV / librealsense convention: `u = fx * x / z + cx`).
- `labels`: optional uint8 H x W semantic class ids (`SemanticClass`; 255 = unlabeled).
- `rgb`: optional uint8 H x W x 3, RGB order.
- `fork_height`: lift height (m) of the fork bottoms when the frame was taken, default 0.
- `truth`: simulator-only arrays under keys ending in `_true` (for example
  `T_forklift_camera_true`, `T_forklift_pallet_true`, 4 x 4 float64). Perception never reads them;
  they exist so tests and benchmarks can score estimates against the truth.

`save_bundle` / `load_bundle` store a bundle as an `.npz` with exactly these keys; `load_bundle`
validates every key and raises `PerceptionError` with one line naming the file and the bad key.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import numpy as np

from palletpilot.geometry.fileio import write_atomic
from palletpilot.perception.errors import PerceptionError


class SemanticClass(IntEnum):
    """The ten semantic classes of the paper, ids fixed, plus 255 for unlabeled pixels."""

    DRIVABLE = 0
    VERTICAL = 1
    OTHER_OBJECT = 2
    OTHER_FORKLIFT = 3
    OTHER_VEHICLE = 4
    FORKS = 5
    CARGO = 6
    PALLET_EMPTY = 7
    PALLET_FULL = 8
    PERSON = 9
    UNLABELED = 255


BUNDLE_KEYS = ("depth", "K", "labels", "rgb", "fork_height")
"""Keys a bundle file may hold besides truth keys (which end in `TRUTH_SUFFIX`)."""
TRUTH_SUFFIX = "_true"
_VALID_LABELS = np.array([int(c) for c in SemanticClass], dtype=np.uint8)


def _check_bundle(
    depth: object,
    K: object,
    labels: object,
    rgb: object,
    fork_height: object,
    truth: Mapping[str, object],
    where: str,
) -> None:
    """Raise `PerceptionError` (`where: key: problem`) for the first entry that breaks the contract."""

    def fail(key: str, problem: str) -> None:
        raise PerceptionError(f"{where}: {key}: {problem}")

    def array(key: str, value: object) -> np.ndarray:
        if not isinstance(value, np.ndarray):
            fail(key, f"expected a numpy array, got {type(value).__name__}")
        return value  # type: ignore[return-value]

    d = array("depth", depth)
    if d.dtype != np.float32:
        fail("depth", f"dtype must be float32 (metres), got {d.dtype}")
    if d.ndim != 2 or d.shape[0] == 0 or d.shape[1] == 0:
        fail("depth", f"shape must be (H, W), got {d.shape}")
    if np.isinf(d).any():
        fail("depth", "contains inf (use 0 or NaN for no data)")
    if (d < 0).any():  # NaN compares False: allowed
        fail("depth", f"contains negative depths (min {float(np.nanmin(d)):.4g} m)")
    shape = d.shape

    k = array("K", K)
    if k.dtype != np.float64:
        fail("K", f"dtype must be float64, got {k.dtype}")
    if k.shape != (3, 3):
        fail("K", f"shape must be (3, 3), got {k.shape}")
    if not np.all(np.isfinite(k)):
        fail("K", "has non-finite entries")
    if not (k[0, 0] > 0 and k[1, 1] > 0) or not np.allclose(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0:
        fail("K", f"is not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0: {k.tolist()}")

    if labels is not None:
        lab = array("labels", labels)
        if lab.dtype != np.uint8:
            fail("labels", f"dtype must be uint8, got {lab.dtype}")
        if lab.shape != shape:
            fail("labels", f"shape {lab.shape} does not match depth {shape}")
        present = np.flatnonzero(np.bincount(lab.ravel(), minlength=256))
        bad = np.setdiff1d(present, _VALID_LABELS)
        if bad.size:
            fail("labels", f"unknown class ids {bad[:5].tolist()} (valid: 0..9 and 255)")

    if rgb is not None:
        im = array("rgb", rgb)
        if im.dtype != np.uint8:
            fail("rgb", f"dtype must be uint8, got {im.dtype}")
        if im.shape != (*shape, 3):
            fail("rgb", f"shape must be {(*shape, 3)} to match depth, got {im.shape}")

    if isinstance(fork_height, np.ndarray):
        if fork_height.shape != () or fork_height.dtype.kind not in "fiu":
            fail("fork_height", f"must be a scalar number, got shape {fork_height.shape} dtype {fork_height.dtype}")
        fork_height = float(fork_height)
    if not isinstance(fork_height, (int, float)) or isinstance(fork_height, bool) or not np.isfinite(fork_height):
        fail("fork_height", f"must be a finite number (m), got {fork_height!r}")

    for key, value in truth.items():
        if not key.endswith(TRUTH_SUFFIX):
            fail(key, f"truth keys must end in '{TRUTH_SUFFIX}'")
        arr = array(key, value)
        if arr.dtype.kind not in "fiub":
            fail(key, f"truth arrays must be numeric, got dtype {arr.dtype}")
        if key.startswith("T_") and (arr.shape != (4, 4) or not np.all(np.isfinite(arr))):
            fail(key, f"a transform must be a finite 4 x 4 matrix, got shape {arr.shape}")


@dataclass(frozen=True, eq=False)
class FrameBundle:
    """One aligned RGB-D frame in the camera's optical frame (see the module docstring).

    Construction validates the contract and raises `PerceptionError` naming the bad field.
    Compared by identity (arrays have no single truth value).
    """

    depth: np.ndarray
    K: np.ndarray
    labels: np.ndarray | None = None
    rgb: np.ndarray | None = None
    fork_height: float = 0.0
    truth: dict[str, np.ndarray] = field(default_factory=dict)
    stamp_s: float | None = None
    """Capture time (s, on the clock of whoever grabbed it: the runner's) when known; not stored in `.npz`."""

    def __post_init__(self) -> None:
        _check_bundle(self.depth, self.K, self.labels, self.rgb, self.fork_height, self.truth, "FrameBundle")
        object.__setattr__(self, "fork_height", float(self.fork_height))

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
    arrays.update(bundle.truth)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)  # type: ignore[arg-type]  # numpy stubs: a key could be allow_pickle
    return write_atomic(path, buf.getvalue())  # OutputError (one line) when it cannot be written


def load_bundle(path: str | Path) -> FrameBundle:
    """Read and validate a bundle `.npz`; any problem raises `PerceptionError` naming the file and key."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise PerceptionError(f"{path}: no such file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise PerceptionError(f"{path}: not a readable .npz frame bundle: {exc}") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise PerceptionError(f"{path}: not an .npz archive (a single .npy array)")
    try:
        with data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise PerceptionError(f"{path}: not a readable .npz frame bundle: {exc}") from None

    for key in ("depth", "K"):
        if key not in arrays:
            raise PerceptionError(f"{path}: {key}: missing (a bundle needs depth and K)")
    truth = {}
    for key in arrays:
        if key in BUNDLE_KEYS:
            continue
        if not key.endswith(TRUTH_SUFFIX):
            raise PerceptionError(
                f"{path}: {key}: unknown key (expected {', '.join(BUNDLE_KEYS)} or truth keys ending in '_true')"
            )
        truth[key] = arrays[key]
    fork_height = arrays.get("fork_height", np.array(0.0))
    _check_bundle(arrays["depth"], arrays["K"], arrays.get("labels"), arrays.get("rgb"), fork_height, truth, str(path))
    return FrameBundle(
        depth=arrays["depth"],
        K=arrays["K"],
        labels=arrays.get("labels"),
        rgb=arrays.get("rgb"),
        fork_height=float(fork_height),
        truth=truth,
    )

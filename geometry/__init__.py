"""Poses and frames shared by every palletpilot package.

Public API:
- `SE2(x, y, yaw)`: immutable planar transform; `@`, `inv()`, `apply(points)`, `matrix`,
  `from_matrix`, `to_se3(z)`.
- `SE3(rotation, translation)`: immutable spatial transform over `scipy.spatial.transform.Rotation`;
  `@`, `inv()`, `apply(points)`, `apply_vectors`, `matrix`, `from_matrix`, `from_xyz_rpy` /
  `to_xyz_rpy` (roll, pitch, yaw = extrinsic x, y, z), `from_translation`, `to_se2()`.
- `wrap_angle`, `angle_diff`: radians.
- `PalletpilotError`: base of every expected error; `GeometryError`; `OutputError` (a write failed).
- `fileio`: YAML + pydantic loading, `bundled_path`, atomic writes (`write_atomic`, `write_json`), strict JSON.
- `processes`: `spawn_pool(jobs)`, the worker processes of every benchmark, campaign and renderer.

Frames are named `T_a_b` (maps points from b into a); see ARCHITECTURE.md.
"""

from palletpilot.geometry.angles import angle_diff, wrap_angle
from palletpilot.geometry.errors import GeometryError, OutputError, PalletpilotError
from palletpilot.geometry.poses import SE2, SE3

__all__ = ["SE2", "SE3", "GeometryError", "OutputError", "PalletpilotError", "angle_diff", "wrap_angle"]

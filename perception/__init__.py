"""Perception: frame bundles, fork and pallet geometry; later calibration, pallet pose, segmentation, cameras.

Public API so far:
- `perception.frames`: `FrameBundle` (depth m, K, labels, rgb, fork_height, simulator-only `truth`),
  `save_bundle`, `load_bundle` (.npz, ARCHITECTURE.md), `SemanticClass` (the paper's ten ids, 255 unlabeled).
- `perception.specs`: `ForkGeometry` / `load_forks` (forks file), `PalletType` (EUR/EPAL by default, its
  boards and blocks as boxes in the pallet frame), `pallet_pose_at_node` / `node_pose_for_pallet`
  (pallet node <-> `T_world_pallet`, entry face `ENTRY_GAP_M` ahead of the fork heels).
- `PerceptionError`.
"""

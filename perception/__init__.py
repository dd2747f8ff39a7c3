"""Perception: frame bundles, fork and pallet geometry, camera calibration, pallet pose, segmentation, cameras.

Public API:
- `perception.frames`: `FrameBundle` (depth m, K, labels, rgb, fork_height, simulator-only `truth`),
  `save_bundle`, `load_bundle` / `load_bundles` (.npz, ARCHITECTURE.md), `SemanticClass` (the paper's ten
  ids, 255 unlabeled) and the bundle limits, re-exported from `perception.bundle_contract` (the data
  contract: class ids, keys, limits and the checks of every field) and `perception.bundle_archive`
  (reading an untrusted .npz: zip directory and .npy headers checked before any data is unpacked).
- `perception.labels_mode`: `LabelsMode` (`model`, `geometry`, `fused`: which source selects the pallet's, the
  floor's and the forks' pixels; `MODES`, what each needs and is robust to); `perception.geometry_labels`:
  those pixels from depth (`pallet_labels`, `calibration_labels`, `load_mask`, `sources_note`).
- `perception.distortion`: `undistort_bundle` (a bundle's lens distortion `dist` removed, same K).
- `perception.specs`: `ForkGeometry` / `load_forks` (forks file; `perception.fork_geometry`), `PalletType`
  (EUR/EPAL by default, its boards and blocks as boxes in the pallet frame; `pallet_type("eur" or
  FILE.yaml)`; a family with ranges: `perception.pallet_family`, measured by `perception.pallet_measure`),
  `pallet_pose_at_node` / `node_pose_for_pallet` (pallet node <-> `T_world_pallet`, entry face
  `ENTRY_GAP_M` ahead of the fork heels).
- `perception.calibration`: `calibrate` (`T_forklift_camera` from fork and floor frames; `model` and
  `paper` methods), `Calibrator` (keeps the last good calibration), `CalibrationError`, warnings when
  the fork tips cannot be trusted; `perception.calibration_features`: the evidence it fits (floor and fork
  points, the forks' edge rays); `perception.calibration_paper`: the paper's method (the baseline);
  `perception.fork_profile`: `forks measure`, the blade's taper estimated from frames of the forks;
  `perception.calibration_io`: `Calibration` and its JSON; `perception.view`: `pickup_view` (does a
  mount show the entry face and a load at the Pickup's distances).
- `perception.pallet`: `estimate_pallet` (`T_forklift_pallet` / `T_world_pallet` with a spread from one
  labelled RGB-D frame), `fuse_estimates` (several frames of one standpoint), `FramePolicy` (how many
  frames a standpoint takes: more while the fused yaw is uncertain), `PalletNotFound` (reason),
  `PalletEstimate`, `PalletEstimatorConfig`; its pieces: `perception.pallet_estimate` (tuning, result,
  failure, fusion), `perception.pallet_face` (rays and the entry-face plane), `perception.pallet_model`
  (the pallet model and its scores, the pocket check), `perception.pallet_steps` (the steps on one
  frame), `perception.pallet_deck` (yaw from the deck);
  `perception.alignment`: `AlignmentTolerances`, `check_alignment` (against the pallet node).
- `perception.segmentation`: `SegmentationService`, `OnnxSegmenter` (the shipped `DEFAULT_MODEL`),
  `GroundTruthSegmenter`, `evaluate_segmenter`, `SegmentationScore` (pooled per-class IoU),
  `load_hidden_mask` (pallets cut off where their load would be); `perception.train_segmentation`
  trains the model, on batches from `perception.training_batches` (frames, crops, augmentation, workers).
- `perception.realsense`: `RealSenseSource` (live D435/D435i), `RecordingSource` (.db3 recordings);
  its parts: `perception.realsense_frames` (librealsense frames to stamped bundles),
  `perception.realsense_distortion` (a stream's lens model as OpenCV's coefficients),
  `perception.realsense_recording` (playback); `perception.realsense_synthetic`: `write_software_recording`
  (a recording of synthetic frames).
- `PerceptionError`: every perception failure.
"""

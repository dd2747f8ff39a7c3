"""Semantic segmentation: RGB (H x W x 3 uint8) to the paper's ten class ids (H x W uint8).

- `SegmentationService`: the Protocol the rest of perception uses, `segment(rgb) -> labels`.
- `OnnxSegmenter`: a network run with onnxruntime. Everything about the network comes from the
  model file's custom metadata (`metadata_props`, written by `perception.train_segmentation`):
  `input_width`, `input_height` (pixels), `mean`, `std` (JSON lists of three floats on the 0..1 RGB
  scale), `classes` (JSON `{"id": "name"}`, one output channel per id in ascending id order), and
  optionally `labels_output`: the name of a graph output holding the per-pixel argmax of the logits
  (uint8 or int64, (1, H, W) at the input size). The image is resized to the input size (area
  filter; not at all when it already has that size) and normalised. When its size is the input size
  and the model has a labels output, that output is the result (the argmax runs inside onnxruntime,
  which is much faster than numpy at 640 x 480); otherwise the output logits are upsampled bilinearly
  to the full image size before the per-pixel argmax. CPU by default; the TensorRT and CUDA execution
  providers are used first when onnxruntime offers them.
- `GroundTruthSegmenter`: the simulator's exact labels behind the same Protocol.
- `ensure_labels(bundle, segmenter)`: fills a bundle's labels from its RGB when it has none.
- `evaluate_segmenter`: per-class IoU (and runtime) over labelled bundles, for held-out sets, strict
  and with either pallet class counted as right on pallets whose load the image cannot show
  (`load_hidden_mask`); `SegmentationScore` pools the same scores over frames segmented elsewhere;
  `python -m palletpilot.perception.segmentation eval DATA_DIR [--model M] [--json]` runs it, and
  `python -m palletpilot.perception.segmentation time DATA_DIR [--frames N]` times `segment` (`benchmark`).

`DEFAULT_MODEL` is the model shipped in `perception/models/` (how it was trained: its README).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.distortion import undistort_bundle
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, SemanticClass, load_bundle

DEFAULT_MODEL = bundled_path("perception", "models", "segmenter.onnx")
"""The segmentation model shipped with the package."""

PREFERRED_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider")
"""Execution providers in order of preference; only those onnxruntime offers are used."""

_REQUIRED_METADATA = ("input_width", "input_height", "mean", "std", "classes")


@runtime_checkable
class SegmentationService(Protocol):
    """Turns an RGB image into semantic class ids."""

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        """Labels (H x W uint8, `SemanticClass` ids, 255 = unlabeled) of an H x W x 3 uint8 RGB image."""
        ...


def _check_rgb(rgb: object, who: str) -> np.ndarray:
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        desc = f"{rgb.dtype} {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
        raise PerceptionError(f"{who}: rgb must be a uint8 H x W x 3 array, got {desc}")
    if rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise PerceptionError(f"{who}: rgb is empty, shape {rgb.shape}")
    return rgb


@dataclasses.dataclass(frozen=True)
class ModelInfo:
    """What an ONNX segmentation model's metadata says about its input and output."""

    input_width: int
    input_height: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    class_ids: tuple[int, ...]
    class_names: tuple[str, ...]
    metadata: dict[str, str]
    labels_output: str | None = None


def _parse_metadata(meta: dict[str, str], where: str) -> ModelInfo:
    missing = [k for k in _REQUIRED_METADATA if k not in meta]
    if missing:
        raise PerceptionError(f"{where}: model metadata lacks {', '.join(missing)} (export with train_segmentation)")
    try:
        width, height = int(meta["input_width"]), int(meta["input_height"])
        mean = tuple(float(v) for v in json.loads(meta["mean"]))
        std = tuple(float(v) for v in json.loads(meta["std"]))
        classes = {int(k): str(v) for k, v in json.loads(meta["classes"]).items()}
    except (ValueError, TypeError, AttributeError) as exc:
        raise PerceptionError(f"{where}: bad model metadata: {exc}") from None
    if width <= 0 or height <= 0 or len(mean) != 3 or len(std) != 3 or min(std) <= 0:
        raise PerceptionError(f"{where}: bad model metadata: input {width}x{height}, mean {mean}, std {std}")
    valid = {int(c) for c in SemanticClass}
    if not classes or not set(classes) <= valid or SemanticClass.UNLABELED in classes:
        raise PerceptionError(f"{where}: bad model metadata: class ids {sorted(classes)} (valid: 0..9)")
    ids = tuple(sorted(classes))
    labels_output = meta.get("labels_output") or None
    names = tuple(classes[i] for i in ids)
    return ModelInfo(width, height, mean, std, ids, names, dict(meta), labels_output)


def available_providers(requested: Sequence[str] | None = None) -> list[str]:
    """The execution providers to use: `requested` as given, else the available ones of `PREFERRED_PROVIDERS`."""
    import onnxruntime as ort

    if requested is not None:
        return list(requested)
    have = set(ort.get_available_providers())
    return [p for p in PREFERRED_PROVIDERS if p in have] or ["CPUExecutionProvider"]


class OnnxSegmenter:
    """A segmentation network run with onnxruntime (see the module docstring for the model contract).

    A missing, unreadable or corrupt model file, or one without the metadata, raises
    `PerceptionError` with one line naming the file.
    """

    def __init__(
        self, model_path: str | Path = DEFAULT_MODEL, providers: Sequence[str] | None = None, threads: int | None = None
    ) -> None:
        import onnxruntime as ort

        self.model_path = Path(model_path)
        where = str(self.model_path)
        if not self.model_path.is_file():
            raise PerceptionError(f"{where}: segmentation model not found")
        options = ort.SessionOptions()
        options.log_severity_level = 3
        if threads is not None:
            options.intra_op_num_threads = int(threads)
        self.providers = available_providers(providers)
        try:
            self.session = ort.InferenceSession(str(self.model_path), options, providers=self.providers)
        except Exception as exc:  # onnxruntime raises its own pybind exception types
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise PerceptionError(f"{where}: not a readable ONNX segmentation model ({reason[:200]})") from None
        self.info = _parse_metadata(self.session.get_modelmeta().custom_metadata_map, where)
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise PerceptionError(f"{where}: expected one NCHW image input, got {[i.shape for i in inputs]}")
        self._input_name = inputs[0].name
        self._output_name = outputs[0].name
        self._labels_name = self.info.labels_output
        if self._labels_name is not None and self._labels_name not in {o.name for o in outputs}:
            name = self._labels_name
            raise PerceptionError(f"{where}: metadata labels_output {name!r} is not an output of the model")
        mean, std = np.asarray(self.info.mean, np.float32), np.asarray(self.info.std, np.float32)
        self._scale = (1.0 / (255.0 * std)).astype(np.float32)  # x_norm = rgb * scale + offset
        self._offset = (-mean / std).astype(np.float32)
        self._lut = np.asarray(self.info.class_ids, dtype=np.uint8)
        self._identity = bool(np.array_equal(self._lut, np.arange(len(self._lut))))  # channel index = class id

    @property
    def input_size(self) -> tuple[int, int]:
        """(width, height) in pixels of the network input."""
        return self.info.input_width, self.info.input_height

    def _input(self, rgb: np.ndarray) -> np.ndarray:
        """The network input (1, 3, h, w) float32 of an RGB image: resized to the input size, normalised."""
        w, h = self.input_size
        small = rgb if rgb.shape[:2] == (h, w) else cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        x = np.empty((1, 3, h, w), np.float32)
        for c, plane in enumerate(cv2.split(small)):  # per plane: much faster than one broadcast expression
            np.multiply(plane, self._scale[c], out=x[0, c], casting="unsafe")
            x[0, c] += self._offset[c]
        return x

    def logits(self, rgb: np.ndarray) -> np.ndarray:
        """The network's raw output for an RGB image: float32 (C, h, w) at the network's output size."""
        rgb = _check_rgb(rgb, f"{self.model_path}")
        out = self.session.run([self._output_name], {self._input_name: self._input(rgb)})[0]
        return out[0]

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        """Labels (H x W uint8 class ids) of an H x W x 3 uint8 RGB image, at the image's full size."""
        rgb = _check_rgb(rgb, f"{self.model_path}")
        H, W = rgb.shape[:2]
        if self._labels_name is not None and (W, H) == self.input_size:
            index = self.session.run([self._labels_name], {self._input_name: self._input(rgb)})[0][0]
            if index.shape == (H, W):
                return index.astype(np.uint8, copy=False) if self._identity else self._lut[index]
        logits = self.logits(rgb)
        if logits.shape[1:] != (H, W):
            hwc = np.ascontiguousarray(logits.transpose(1, 2, 0))
            if hwc.shape[2] <= 512:  # OpenCV's channel limit for resize
                hwc = cv2.resize(hwc, (W, H), interpolation=cv2.INTER_LINEAR)
            index = hwc.argmax(axis=2)
        else:
            index = logits.argmax(axis=0)
        return self._lut[index]


class GroundTruthSegmenter:
    """The simulator's exact labels as a `SegmentationService`.

    `truth` is either a labels image (H x W uint8; a segmenter for one frame) or a zero-argument
    callable returning the labels of the frame being segmented (for example
    `lambda: simulator_frame.labels`). `segment(rgb)` ignores the pixels and returns a copy of
    the truth after checking that its size matches the image.
    """

    def __init__(self, truth: np.ndarray | Callable[[], np.ndarray]) -> None:
        self._truth = truth

    @classmethod
    def from_bundle(cls, bundle: FrameBundle) -> GroundTruthSegmenter:
        """A segmenter returning `bundle`'s labels (which must exist)."""
        if bundle.labels is None:
            raise PerceptionError("GroundTruthSegmenter: the bundle has no labels")
        return cls(bundle.labels)

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        """The ground-truth labels (uint8 H x W) of the frame whose RGB is `rgb`."""
        rgb = _check_rgb(rgb, "GroundTruthSegmenter")
        labels = self._truth() if callable(self._truth) else self._truth
        if not isinstance(labels, np.ndarray) or labels.dtype != np.uint8 or labels.shape != rgb.shape[:2]:
            desc = f"{labels.dtype} {labels.shape}" if isinstance(labels, np.ndarray) else type(labels).__name__
            raise PerceptionError(f"GroundTruthSegmenter: truth labels {desc} do not fit rgb {rgb.shape}")
        return labels.copy()


def ensure_labels(bundle: FrameBundle, segmenter: SegmentationService) -> FrameBundle:
    """`bundle` itself when it has labels, else a copy with labels segmented from its RGB.

    A bundle with lens distortion is undistorted first (`perception.distortion.undistort_bundle`): the
    model learnt from ideal pinhole images, and its labels then fit the depth perception deprojects.
    Raises `PerceptionError` when the bundle has neither labels nor RGB.
    """
    bundle = undistort_bundle(bundle)
    if bundle.labels is not None:
        return bundle
    if bundle.rgb is None:
        raise PerceptionError("FrameBundle: labels: missing, and there is no rgb to segment")
    return dataclasses.replace(bundle, labels=segmenter.segment(bundle.rgb))


# -- evaluation ------------------------------------------------------------------------------------


def confusion(truth: np.ndarray, pred: np.ndarray, n: int = 10) -> np.ndarray:
    """n x n pixel confusion matrix (rows truth, columns prediction); truth pixels >= n (255) are ignored."""
    t, p = truth.ravel().astype(np.int64), pred.ravel().astype(np.int64)
    keep = (t < n) & (p < n)
    return np.bincount(t[keep] * n + p[keep], minlength=n * n).reshape(n, n)


def iou_from_confusion(cm: np.ndarray) -> dict[int, float | None]:
    """Per-class IoU = TP / (TP + FP + FN) from a confusion matrix; None for classes absent from both."""
    tp = np.diag(cm).astype(float)
    union = cm.sum(axis=0) + cm.sum(axis=1) - tp
    return {k: (float(tp[k] / union[k]) if union[k] > 0 else None) for k in range(cm.shape[0])}


_PALLET_CLASSES = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))


def load_hidden_mask(labels: np.ndarray, margin_px: int = 3) -> np.ndarray:
    """Pixels (H x W bool) of pallets whose load state the image cannot show, from true labels.

    A pallet's load stands above its deck. A pallet region (one connected region of pallet-empty or
    of pallet-full pixels) that touches the top image row, with no cargo pixel within `margin_px`
    of it, is cut off where its load would be: the picture of an empty and of a loaded pallet is
    the same there. Such regions are typical of steep camera mounts and far or raised pallets.
    """
    cargo_near = cv2.dilate(
        (labels == SemanticClass.CARGO).astype(np.uint8), np.ones((2 * margin_px + 1,) * 2, np.uint8)
    ).astype(bool)
    hidden = np.zeros(labels.shape, dtype=bool)
    for cls in _PALLET_CLASSES:
        pallet = labels == cls
        if not pallet[0].any():
            continue
        _, regions = cv2.connectedComponents(pallet.astype(np.uint8), connectivity=8)
        at_top = np.unique(regions[0][pallet[0]])
        with_load = np.unique(regions[cargo_near & pallet])
        hidden |= np.isin(regions, np.setdiff1d(at_top, with_load)) & pallet
    return hidden


class SegmentationScore:
    """Per-class IoU of predictions against true labels, pixels pooled over every `add`ed frame.

    `result()` gives `{"frames", "iou": {name: IoU or None}, "pixels": {name: truth pixel count},
    "predicted_pixels": {name: count}, "iou_load_hidden_either": {name: IoU or None},
    "load_hidden_share": {pallet class: share}}`.
    `iou` is the strict score. `iou_load_hidden_either` scores the same predictions, except that on
    pallets whose load the image cannot show (`load_hidden_mask`) either pallet class counts as
    right; `load_hidden_share` is the share of each pallet class's true pixels on such pallets.
    Unlabeled (255) truth pixels are ignored.
    """

    def __init__(self) -> None:
        self.cm = np.zeros((10, 10), dtype=np.int64)
        self.cm_either = np.zeros((10, 10), dtype=np.int64)
        self.hidden_px = np.zeros(10, dtype=np.int64)
        self.frames = 0

    def add(self, truth: np.ndarray, pred: np.ndarray) -> None:
        """Score one frame's predicted labels against its true labels (both H x W class ids)."""
        self.cm += confusion(truth, pred)
        hidden = load_hidden_mask(truth)
        self.hidden_px += np.bincount(truth[hidden], minlength=256)[:10]
        either = hidden & np.isin(pred, _PALLET_CLASSES)
        self.cm_either += confusion(truth, np.where(either, truth, pred))
        self.frames += 1

    def result(self) -> dict:
        """The pooled scores (see the class docstring), IoUs rounded to 4 decimals."""
        names = {int(c): c.name.lower() for c in SemanticClass if c != SemanticClass.UNLABELED}

        def named(ious: dict[int, float | None]) -> dict[str, float | None]:
            return {names[k]: (None if v is None else round(v, 4)) for k, v in ious.items()}

        truth_px = self.cm.sum(axis=1)
        return {
            "frames": self.frames,
            "iou": named(iou_from_confusion(self.cm)),
            "pixels": {names[k]: int(truth_px[k]) for k in range(10)},
            "predicted_pixels": {names[k]: int(self.cm[:, k].sum()) for k in range(10)},
            "iou_load_hidden_either": named(iou_from_confusion(self.cm_either)),
            "load_hidden_share": {
                names[k]: round(float(self.hidden_px[k] / truth_px[k]), 4) if truth_px[k] else None
                for k in _PALLET_CLASSES
            },
        }


def evaluate_segmenter(segmenter: SegmentationService, bundles: Iterable[FrameBundle | str | Path]) -> dict:
    """Per-class IoU of `segmenter` over labelled bundles (paths or `FrameBundle`s), pixels pooled over all frames.

    Returns `SegmentationScore.result()` plus `"segment_ms_median"` and `"segment_ms_p95"`.
    """
    score = SegmentationScore()
    times = []
    for item in bundles:
        bundle = item if isinstance(item, FrameBundle) else load_bundle(item)
        if bundle.rgb is None or bundle.labels is None:
            raise PerceptionError("evaluate_segmenter: every bundle needs rgb and labels")
        t0 = time.perf_counter()
        pred = segmenter.segment(bundle.rgb)
        times.append(time.perf_counter() - t0)
        score.add(bundle.labels, pred)
    return {
        **score.result(),
        "segment_ms_median": round(1000 * float(np.median(times)), 2) if times else None,
        "segment_ms_p95": round(1000 * float(np.percentile(times, 95)), 2) if times else None,
    }


def format_iou(result: dict) -> str:
    """A small text table of an `evaluate_segmenter` result."""
    lines = [
        f"frames: {result['frames']}  segment ms median {result['segment_ms_median']} p95 {result['segment_ms_p95']}",
        f"  {'class':15s} {'IoU':>6s}  {'IoU*':>6s}  truth pixels",
    ]
    either = result.get("iou_load_hidden_either", {})
    for name, iou in result["iou"].items():
        value = "   -  " if iou is None else f"{iou:.4f}"
        other = either.get(name)
        value_either = "   -  " if other is None else f"{other:.4f}"
        lines.append(f"  {name:15s} {value}  {value_either}  {result['pixels'][name]}")
    shares = result.get("load_hidden_share", {})
    if shares:
        text = ", ".join(f"{name} {share:.1%}" for name, share in shares.items() if share is not None)
        lines.append(f"  IoU*: either pallet class is right on pallets whose load is out of view ({text} of pixels)")
    return "\n".join(lines)


def benchmark(segmenter: SegmentationService, rgbs: Sequence[np.ndarray], warmup: int = 3) -> dict:
    """Median, p95 and max segmentation time (ms) over `rgbs` after `warmup` untimed runs."""
    for rgb in list(rgbs)[:warmup]:
        segmenter.segment(rgb)
    times = []
    for rgb in rgbs:
        t0 = time.perf_counter()
        segmenter.segment(rgb)
        times.append(1000 * (time.perf_counter() - t0))
    return {
        "frames": len(times),
        "ms_median": round(float(np.median(times)), 2),
        "ms_p95": round(float(np.percentile(times, 95)), 2),
        "ms_max": round(float(np.max(times)), 2),
    }


def main(argv: list[str] | None = None) -> int:
    """`python -m palletpilot.perception.segmentation eval|time DATA_DIR [--model M] [--frames N] [--json]`.

    (`bench` = `time`.)
    """
    ap = argparse.ArgumentParser(prog="python -m palletpilot.perception.segmentation")
    ap.add_argument(
        "what", choices=("eval", "time", "bench"), help="eval: per-class IoU; time (or bench): inference time"
    )
    ap.add_argument("data_dir", type=Path, help="folder of frame bundles (.npz)")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--frames", type=int, default=None, help="use only the first N bundles")
    ap.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    try:
        seg = OnnxSegmenter(args.model, threads=args.threads)
        files = sorted(args.data_dir.glob("*.npz"))[: args.frames]
        if not files:
            raise PerceptionError(f"{args.data_dir}: no .npz frame bundles")
        if args.what == "eval":
            result = evaluate_segmenter(seg, files)
            print(json.dumps(result, indent=2) if args.json else format_iou(result))
        else:
            rgbs = [b.rgb for b in map(load_bundle, files) if b.rgb is not None]
            result = {"providers": seg.providers, **benchmark(seg, rgbs)}
            print(json.dumps(result, indent=2) if args.json else result)
    except PerceptionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

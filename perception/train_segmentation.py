"""Train the shipped segmentation model (`perception/models/segmenter.onnx`) on frame bundles.

Usage (torch and onnx come with the optional `train` extra; CPU is enough)::

    palletpilot segment dataset DATA_DIR --frames 900 --seed 0     # or sim.dataset.generate_dataset
    python -m palletpilot.perception.train_segmentation DATA_DIR [DATA_DIR ...] --out perception/models/segmenter.onnx \
        --seed 0 [--steps N | --minutes M] [--heldout HELDOUT_DIR] [--batch 12] [--crop 384 288] \
        [--focus 0.75] [--weight-power 0.5] [--dice 0.5] [--channels 16,32,48,64,96] [--refine 0] [--lr 4e-3] \
        [--threads 2] [--workers 0] [--device cpu] [--weights-out W.pt]

`--init MODEL.onnx` fine-tunes an exported model instead of training from scratch (its weights and widths,
`perception.segmentation_data.import_onnx_weights`; batch norms frozen; peak learning rate 1e-3 unless
`--lr`); `palletpilot segment train` is the same with the fine-tuning defaults. A data folder holds frame
bundles (`.npz`) or the user's own labelled PNG frames (`NAME.png` + `NAME_labels.png`, class ids, 255 =
ignore; `perception.segmentation_data`). The script never imports the simulator. Steps:

1. Cache: every bundle's RGB and labels at the network's full input size (640 x 480; other sizes are
   resized, area filter and nearest neighbour) go into `DATA_DIR/.segcache_640x480_{rgb,labels}.npy`
   with the list of bundle files in `.segcache_640x480_files.json` (rebuilt when that list changes).
   Training reads the caches memory-mapped, so thousands of frames need no extra RAM.
2. Train `SegNet` (`build_model`: a light encoder-decoder, 0.42-0.43 M parameters, fully convolutional, no
   global pooling, the row coordinate as an input of its coarsest level) on random full-resolution
   crops (`--crop`, default 384 x 288; the network is then run on whole 640 x 480 frames). `--focus`
   (default 0.75) of the crops are placed around a random pallet pixel (pallet_empty or pallet_full),
   with the pallet in the lower part of the crop so that what stands on it is in view; the rest lie
   anywhere. Loss: class-weighted cross-entropy (weights: pixel frequency ** -`--weight-power`,
   default 0.5, normalised and clipped to 0.5..10; the two pallet classes share one weight) plus
   `--dice` (default 0.5) times a soft-Dice term; label 255 ignored. `--refine N` gives the network a
   sub-pixel refinement stage of width N (`build_model`); with `--init` a model without one gets it
   added, starting from exactly what the model computed. Augmentation (`augment`): horizontal
   flips and photometric effects drawn anew every step (brightness, contrast, white balance, gamma,
   vignetting, Gaussian or motion blur, luminance and colour noise, JPEG re-encoding). AdamW with a
   warm-up plus cosine learning rate. Deterministic for `--seed`, `--steps`, the data and `--threads`
   (torch, numpy and the crop order are seeded; single process). `--workers N` makes the batches in N
   forked processes ahead of the training loop, each batch from its own generator seeded by (seed, step),
   so the crops do not depend on N (but differ from the single-process runs'); `--device cuda` trains on a
   GPU (not run here yet: the project's one GPU attempt ended before training, `perception/models/README.md`).
   `--minutes M` picks the step count
   from the measured speed and prints it, so that run is repeated with `--steps N`.
3. Export to ONNX (opset 17): input `rgb` (1, 3, 480, 640) float32, normalised; outputs `logits`
   (1, 10, 480, 640) and `labels` (1, 480, 640) uint8, their per-pixel argmax (computed in the graph,
   much faster than numpy). The metadata (`metadata_props`) carries what `OnnxSegmenter` needs:
   `input_width`, `input_height`, `mean`, `std` (JSON lists, 0..1 RGB scale), `classes` (JSON {id: name}),
   `channel_order` ("RGB"), `layout` ("NCHW"), `output` ("logits"), `labels_output` ("labels"), plus the
   training facts (`training`: seed, steps, epochs, frames, crop, ...).
4. With `--heldout`, evaluate the exported model with onnxruntime at full resolution
   (`perception.segmentation.evaluate_segmenter`) and print the per-class IoU.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import SemanticClass, load_bundle
from palletpilot.perception.segmentation_data import (
    check_training_inputs,
    file_sha256,
    freeze_batchnorm,
    import_onnx_weights,
    is_png_folder,
    load_png_folder,
    onnx_training_facts,
    thaw_batchnorm,
)

INPUT_WIDTH = 640
INPUT_HEIGHT = 480
CROP = (384, 288)
"""Default training crop (width, height) in pixels of the full-resolution frames."""
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
N_CLASSES = 10
IGNORE = int(SemanticClass.UNLABELED)
CLASS_NAMES = {int(c): c.name.lower() for c in SemanticClass if c != SemanticClass.UNLABELED}
FOCUS_CLASSES = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))
"""Crops placed around a pixel of one of these classes (`--focus` of them)."""
CHANNELS = (16, 32, 48, 64, 96)
"""SegNet feature channels at 1/2, 1/4, 1/8, 1/16 and 1/32 of the input."""
FINETUNE_LR = 1e-3
"""Default peak learning rate when fine-tuning from an existing model (`--init`)."""
THAW_BATCHES = 20
"""Batches of training crops over which `--thaw-norms` measures the batch norms' input statistics."""


# -- data ---------------------------------------------------------------------------------------


def load_cached(data_dir: Path, width: int = INPUT_WIDTH, height: int = INPUT_HEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """RGB (N, H, W, 3) uint8 and labels (N, H, W) uint8 of every bundle in `data_dir` at the input size.

    Bundles without RGB or labels are skipped. The arrays are cached next to the data as .npy files
    (rebuilt when the list of bundle files changes) and returned memory-mapped, read-only.
    """
    files = sorted(f for f in data_dir.glob("*.npz") if not f.name.startswith("."))
    stem = f".segcache_{width}x{height}"
    rgb_path, lab_path, key_path = (data_dir / f"{stem}_{s}" for s in ("rgb.npy", "labels.npy", "files.json"))
    names = [f.name for f in files]
    if key_path.exists() and rgb_path.exists() and lab_path.exists():
        if json.loads(key_path.read_text()).get("files") == names:
            return np.load(rgb_path, mmap_mode="r"), np.load(lab_path, mmap_mode="r")
    key_path.unlink(missing_ok=True)
    rgbs = np.lib.format.open_memmap(rgb_path, mode="w+", dtype=np.uint8, shape=(len(files), height, width, 3))
    labs = np.lib.format.open_memmap(lab_path, mode="w+", dtype=np.uint8, shape=(len(files), height, width))
    kept: list[str] = []
    for i, f in enumerate(files):
        b = load_bundle(f)
        if b.rgb is None or b.labels is None:
            continue
        rgb, lab = b.rgb, b.labels
        if rgb.shape[:2] != (height, width):
            rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
            lab = cv2.resize(lab, (width, height), interpolation=cv2.INTER_NEAREST)
        rgbs[len(kept)], labs[len(kept)] = rgb, lab
        kept.append(f.name)
        if (i + 1) % 500 == 0:
            print(f"{data_dir}: cached {i + 1}/{len(files)} bundles", flush=True)
    if not kept:
        raise SystemExit(f"{data_dir}: no frame bundles with rgb and labels")
    rgbs.flush()
    labs.flush()
    del rgbs, labs
    if len(kept) < len(files):  # drop the rows of the skipped bundles
        for path in (rgb_path, lab_path):
            tmp = path.with_name(path.name + ".tmp.npy")
            np.save(tmp, np.load(path, mmap_mode="r")[: len(kept)])
            tmp.replace(path)
    key_path.write_text(json.dumps({"files": names, "kept": kept}))
    return np.load(rgb_path, mmap_mode="r"), np.load(lab_path, mmap_mode="r")


class Frames:
    """The frames of several data folders as one indexable set.

    A folder of frame bundles is read through its memory-mapped cache (`load_cached`); a folder of
    labelled PNG frames (`perception.segmentation_data`: `NAME.png` + `NAME_labels.png`) is read into memory.
    """

    def __init__(self, data_dirs: list[Path]) -> None:
        self.parts = [
            load_png_folder(Path(d), INPUT_WIDTH, INPUT_HEIGHT) if is_png_folder(Path(d)) else load_cached(Path(d))
            for d in data_dirs
        ]
        self.offsets = np.cumsum([0] + [len(rgb) for rgb, _ in self.parts])

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        part = int(np.searchsorted(self.offsets, i, side="right")) - 1
        rgb, lab = self.parts[part]
        j = i - int(self.offsets[part])
        return rgb[j], lab[j]

    def class_pixels(self, every: int = 8) -> np.ndarray:
        """Pixel count per label value (256,) over every `every`-th frame (for the class weights)."""
        counts = np.zeros(256, np.int64)
        for i in range(0, len(self), every):
            counts += np.bincount(self[i][1].ravel(), minlength=256)
        return counts


def class_weights(counts: np.ndarray, power: float = 0.5) -> np.ndarray:
    """Per-class loss weights (N_CLASSES,) from pixel counts: frequency ** -power, normalised, clipped to 0.5..10.

    Pallet-empty and pallet-full share one weight (from their joint frequency): the loss must not
    favour either state of a pallet whose load is out of view.
    """
    counts = counts[:N_CLASSES].astype(float)
    freq = counts / max(counts.sum(), 1.0)
    pallet = list(FOCUS_CLASSES)
    w = np.maximum(freq, 1e-4) ** -power
    w[pallet] = max(float(freq[pallet].sum()), 1e-4) ** -power
    w /= np.average(w, weights=np.maximum(freq, 1e-12))
    return np.clip(w, 0.5, 10.0)


def sample_crop(lab: np.ndarray, crop: tuple[int, int], focus: float, rng: np.random.Generator) -> tuple[slice, slice]:
    """Rows and columns of a random `crop` (width, height) window of a (H, W) labels image.

    With probability `focus` and when the frame has pallet pixels (`FOCUS_CLASSES`), the window holds a
    random one of them, horizontally anywhere in its middle 80 % and vertically in its lower part
    (25..90 % of the height) so that what stands on the pallet is in the crop; else it is anywhere.
    """
    H, W = lab.shape
    cw, ch = min(crop[0], W), min(crop[1], H)
    if rng.random() < focus:
        ys, xs = np.nonzero((lab == FOCUS_CLASSES[0]) | (lab == FOCUS_CLASSES[1]))
        if len(ys):
            k = int(rng.integers(len(ys)))
            x0 = int(xs[k]) - int(cw * rng.uniform(0.1, 0.9))
            y0 = int(ys[k]) - int(ch * rng.uniform(0.25, 0.9))
            x0, y0 = min(max(x0, 0), W - cw), min(max(y0, 0), H - ch)
            return slice(y0, y0 + ch), slice(x0, x0 + cw)
    x0, y0 = int(rng.integers(W - cw + 1)), int(rng.integers(H - ch + 1))
    return slice(y0, y0 + ch), slice(x0, x0 + cw)


def augment(rgb: np.ndarray, lab: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Flip and photometric jitter of one (H, W, 3) uint8 image and its (H, W) labels; returns float32 0..1 RGB.

    Every training step draws (labels are only flipped): brightness, per-channel gain (white balance),
    contrast, gamma 0.7..1.45; vignetting (one time in three, up to 45 % darker corners, off-centre);
    Gaussian blur (one in four) or motion blur (one in five, 3..11 px at any angle); sensor noise,
    partly per channel (colour noise) and partly in low-frequency blotches; JPEG re-encoding at
    quality 40..95 (`cv2.imencode`, one time in two) last, as a camera's compressed stream would.
    """
    if rng.random() < 0.5:
        rgb, lab = rgb[:, ::-1], lab[:, ::-1]
    img: np.ndarray = rgb.astype(np.float32) / 255.0
    h, w = img.shape[:2]
    img = img * rng.uniform(0.6, 1.4) * rng.uniform(0.85, 1.15, 3).astype(np.float32)
    mean = img.mean()
    img = (img - mean) * rng.uniform(0.7, 1.3) + mean
    img = np.clip(img, 0.0, 1.0) ** rng.uniform(0.7, 1.45)
    if rng.random() < 1.0 / 3.0:
        cy, cx = h * rng.uniform(0.3, 0.7), w * rng.uniform(0.3, 0.7)
        yy, xx = np.ogrid[:h, :w]
        r2 = ((yy - cy) ** 2 + (xx - cx) ** 2) / float(0.25 * (h * h + w * w))
        img = img * (1.0 - rng.uniform(0.1, 0.45) * np.minimum(r2, 1.5)).astype(np.float32)[..., None]
    k = rng.random()
    if k < 0.25:
        size = int(rng.choice([3, 5]))
        img = cv2.GaussianBlur(img, (size, size), 0)
    elif k < 0.45:
        length = int(rng.integers(3, 12))
        line = np.zeros((length, length), np.float32)
        line[length // 2, :] = 1.0 / length
        rot = cv2.getRotationMatrix2D(((length - 1) / 2.0, (length - 1) / 2.0), float(rng.uniform(0.0, 180.0)), 1.0)
        kernel: np.ndarray = cv2.warpAffine(line, rot, (length, length))
        img = cv2.filter2D(img, -1, kernel / max(float(kernel.sum()), 1e-6))
    sigma = rng.uniform(0.0, 0.04)
    img = img + rng.normal(0.0, sigma, (h, w, 1)).astype(np.float32)
    img = img + rng.normal(0.0, rng.uniform(0.0, 0.025), img.shape).astype(np.float32)
    if rng.random() < 0.2:  # low-frequency colour blotches
        low = rng.normal(0.0, rng.uniform(0.01, 0.04), (max(2, h // 32), max(2, w // 32), 3)).astype(np.float32)
        img = img + cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    img = np.clip(img, 0.0, 1.0)
    if rng.random() < 0.5:
        quality = int(rng.integers(40, 96))
        ok, buf = cv2.imencode(".jpg", (img * 255.0 + 0.5).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, quality])
        decoded = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if ok else None
        if decoded is not None:
            img = decoded.astype(np.float32) / 255.0
    return np.ascontiguousarray(img, np.float32), np.ascontiguousarray(lab)


# -- model ----------------------------------------------------------------------------------------


def build_model(channels: tuple[int, ...] = CHANNELS, refine: int = 0):  # -> torch.nn.Module (lazy torch)
    """The `SegNet` encoder-decoder: input (B, 3, H, W) normalised RGB, output (B, 10, H, W) logits.

    Fully convolutional (no global pooling, so crops in training and whole frames at run time see the
    same operations). Encoder: a stride-2 stem to 1/2, then one stride-2 and one plain 3x3 convolution
    per level to 1/4, 1/8, 1/16, and at 1/32 two more with dilations 2 and 4 (context: the receptive
    field covers the cargo above a pallet). The 1/32 level also gets the row coordinate in the full
    frame (-1 top .. 1 bottom; for training crops, offset by the crop's first row `top`), so that a
    crop edge is not mistaken for the top of the image (a pallet cut off by the image top with no
    cargo in view is more often empty; one cut off by a crop edge may well be loaded). Decoder: at
    each level back to 1/2, the coarser features 1x1-projected, upsampled bilinearly, added to the
    encoder's features and refined (a 3x3 convolution; depthwise-separable at 1/2). A 1x1 head gives
    the 1/2-resolution logits, upsampled bilinearly to the input size inside the network. `channels`
    are the widths at 1/2 .. 1/32 (multiples of 16 suit onnxruntime's blocked CPU kernels).

    With `refine` > 0 a sub-pixel refinement stage adds a full-resolution correction to those
    upsampled logits, for the pixels on class boundaries (most of the pallet classes' errors): the
    1/2-resolution decoder features, concatenated with the frame's own pixels of each 2 x 2 cell (a
    learned space-to-depth, `detail`: 2 x 2 stride-2 convolution to 12 channels), a 3x3 convolution
    to `refine` channels, ReLU, and a 2 x 2 stride-2 transposed convolution to the 10 logits of each
    full-resolution pixel. That last layer starts at zero, so adding the stage to a trained model
    (`train(..., refine=N)` with `init`) starts from exactly what the model computed. The input's
    sides must then be even.
    """
    import torch
    from torch import nn
    from torch.nn import functional as F  # noqa: N812 (the usual torch alias)

    def cbr(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
        )

    def dws(c: int) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(c, c, 3, 1, 1, groups=c, bias=False),
            nn.BatchNorm2d(c),
            nn.ReLU(inplace=True),
            nn.Conv2d(c, c, 1, bias=False),
            nn.BatchNorm2d(c),
            nn.ReLU(inplace=True),
        )

    def proj(cin: int, cout: int) -> nn.Sequential:
        return nn.Sequential(nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout))

    ch = tuple(int(c) for c in channels)

    class SegNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.stem = cbr(3, ch[0], 2)  # 1/2
            levels = []
            for i in range(1, len(ch)):
                last = i == len(ch) - 1  # its input gets the row coordinate as one more channel
                layers = [cbr(ch[i - 1] + int(last), ch[i], 2)]
                if last:
                    layers += [cbr(ch[i], ch[i], dilation=2), cbr(ch[i], ch[i], dilation=4)]
                else:
                    layers += [cbr(ch[i], ch[i])]
                levels.append(nn.Sequential(*layers))
            self.encoder = nn.ModuleList(levels)
            self.projections = nn.ModuleList(proj(ch[i + 1], ch[i]) for i in range(len(ch) - 1))
            self.decoder = nn.ModuleList((dws(ch[i]) if i == 0 else cbr(ch[i], ch[i])) for i in range(len(ch) - 1))
            self.head = nn.Conv2d(ch[0], N_CLASSES, 1)
            self.refine: nn.Sequential | None = None
            if refine > 0:
                self.detail = nn.Conv2d(3, 4 * 3, 2, 2)
                mix = nn.Conv2d(ch[0] + 4 * 3, refine, 3, 1, 1)
                to_pixels = nn.ConvTranspose2d(refine, N_CLASSES, 2, 2)
                nn.init.zeros_(to_pixels.weight)
                assert to_pixels.bias is not None  # built with one
                nn.init.zeros_(to_pixels.bias)
                self.refine = nn.Sequential(mix, nn.ReLU(inplace=True), to_pixels)

        @staticmethod
        def up(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
            return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)

        def forward(self, x: torch.Tensor, top: torch.Tensor | None = None) -> torch.Tensor:
            feats = [self.stem(x)]
            for level in self.encoder[:-1]:
                feats.append(level(feats[-1]))
            f = feats[-1]
            b, _, h, w = f.shape
            # the row coordinate of the feature cells in the full frame, -1 (top) .. 1 (bottom)
            rows = (torch.arange(h, dtype=x.dtype, device=x.device) + 0.5) * (x.shape[2] / h)
            rows = rows.view(1, 1, h, 1)
            if top is not None:  # crops: their first rows in the full frame
                rows = rows + top.to(x.dtype).view(-1, 1, 1, 1)
            coord = (rows * (2.0 / INPUT_HEIGHT) - 1.0).expand(b, 1, h, w)
            feats.append(self.encoder[-1](torch.cat([f, coord], dim=1)))
            y = feats[-1]
            for i in range(len(feats) - 2, -1, -1):
                y = self.decoder[i](F.relu(self.up(self.projections[i](y), feats[i]) + feats[i]))
            logits = self.up(self.head(y), x)
            if self.refine is not None:
                logits = logits + self.refine(torch.cat([y, self.detail(x)], dim=1))
            return logits

    return SegNet()


# -- training -------------------------------------------------------------------------------------


def _batch_arrays(
    frames: Frames, idx: np.ndarray, crop: tuple[int, int], focus: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One training batch from the frames `idx` as numpy: normalised crops (B, 3, h, w) float32, labels
    (B, h, w) int64, crop tops (B,) int64. Each crop is placed by `sample_crop`, flipped and jittered by `augment`."""
    pairs, tops = [], []
    for i in idx:
        rgb, lab = frames[int(i)]
        rows, cols = sample_crop(lab, crop, focus, rng)
        pairs.append(augment(rgb[rows, cols], lab[rows, cols], rng))
        tops.append(rows.start)
    x = np.stack([p[0] for p in pairs]).transpose(0, 3, 1, 2)
    x = (x - np.asarray(MEAN, np.float32).reshape(1, 3, 1, 1)) / np.asarray(STD, np.float32).reshape(1, 3, 1, 1)
    y = np.stack([p[1] for p in pairs]).astype(np.int64)
    return np.ascontiguousarray(x, np.float32), y, np.asarray(tops, np.int64)


def _batch(frames: Frames, idx: np.ndarray, crop: tuple[int, int], focus: float, rng: np.random.Generator):
    """`_batch_arrays` as torch tensors (CPU)."""
    import torch

    x, y, tops = _batch_arrays(frames, idx, crop, focus, rng)
    return torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(tops)


_WORKER_FRAMES: Frames | None = None
"""The training frames in a batch worker process (inherited through fork, memory shared)."""


def _worker_batch(job: tuple[np.ndarray, tuple[int, int], float, int, int]) -> tuple[np.ndarray, ...]:
    """A batch worker's job: the batch of frames `idx` with its own generator seeded by (seed, step)."""
    idx, crop, focus, seed, step = job
    assert _WORKER_FRAMES is not None
    return _batch_arrays(_WORKER_FRAMES, idx, crop, focus, np.random.default_rng([seed, step, 11]))


def _worker_signals() -> None:
    """A batch worker takes the default SIGTERM (die) and ignores SIGINT: a handler inherited from the parent
    (a Python one runs only between bytecodes) would leave a worker blocked on a full result pipe alive when
    the pool is closed with batches still pending, and the parent waiting for it forever."""
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class BatchSource:
    """Training batches in order: made in this process (`workers` 0: one generator, the historic runs' crops)
    or by `workers` forked processes ahead of the training loop (each batch seeded by (seed, step), so the
    crops do not depend on the number of workers)."""

    def __init__(self, frames: Frames, batch: int, crop: tuple[int, int], focus: float, seed: int,
                 rng: np.random.Generator, workers: int = 0) -> None:  # fmt: skip
        self.frames, self.batch, self.crop, self.focus, self.seed, self.rng = frames, batch, crop, focus, seed, rng
        self.order, self.cursor = rng.permutation(len(frames)), 0
        self.pool = None
        self.ahead = 0
        self.pending: list = []
        self.step = 0
        if workers > 0:
            import multiprocessing

            global _WORKER_FRAMES
            _WORKER_FRAMES = frames
            self.pool = multiprocessing.get_context("fork").Pool(workers, initializer=_worker_signals)
            self.ahead = 4 * workers

    def _next_idx(self) -> np.ndarray:
        if self.cursor + self.batch > len(self.frames):
            self.order, self.cursor = self.rng.permutation(len(self.frames)), 0
        idx = self.order[self.cursor : self.cursor + self.batch]
        self.cursor += self.batch
        return idx

    def next(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The next batch (numpy arrays, `_batch_arrays`)."""
        if self.pool is None:
            return _batch_arrays(self.frames, self._next_idx(), self.crop, self.focus, self.rng)
        while len(self.pending) < self.ahead:
            job = (self._next_idx(), self.crop, self.focus, self.seed, self.step + len(self.pending))
            self.pending.append(self.pool.apply_async(_worker_batch, (job,)))
        self.step += 1
        return self.pending.pop(0).get()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.terminate()


def _dice_loss(logits, target, n_classes: int):  # torch tensors
    import torch

    valid = (target != IGNORE).unsqueeze(1)
    prob = torch.softmax(logits, dim=1) * valid
    onehot = torch.zeros_like(prob).scatter_(1, target.clamp(max=n_classes - 1).unsqueeze(1), 1.0) * valid
    inter = (prob * onehot).sum(dim=(0, 2, 3))
    union = prob.sum(dim=(0, 2, 3)) + onehot.sum(dim=(0, 2, 3))
    present = onehot.sum(dim=(0, 2, 3)) > 0
    dice = 1.0 - (2.0 * inter + 1.0) / (union + 1.0)
    return dice[present].mean() if bool(present.any()) else logits.sum() * 0.0


WARMUP_STEPS = 30
"""Linear learning-rate warm-up (steps); then a cosine decay to 2 % over the remaining steps."""


def learning_rate(step: int, total: int, peak: float) -> float:
    """The learning rate at `step` of `total`: linear warm-up over `WARMUP_STEPS`, then cosine to 2 % of `peak`."""
    if step < WARMUP_STEPS:
        return peak * (step + 1) / WARMUP_STEPS
    progress = min(1.0, (step - WARMUP_STEPS) / max(1, total - WARMUP_STEPS))
    return peak * (0.02 + 0.98 * 0.5 * (1.0 + np.cos(np.pi * progress)))


def train(
    data_dirs: list[Path],
    out: Path,
    seed: int = 0,
    steps: int | None = None,
    minutes: float | None = None,
    batch: int = 12,
    lr: float = 4e-3,
    threads: int = 2,
    crop: tuple[int, int] = CROP,
    focus: float = 0.75,
    channels: tuple[int, ...] = CHANNELS,
    weight_power: float = 0.5,
    dice: float = 0.5,
    init: Path | None = None,
    thaw_norms: bool = False,
    log: bool = True,
    refine: int | None = None,
    device: str = "cpu",
    workers: int = 0,
    weights_out: Path | None = None,
) -> dict:
    """Train on the bundles in `data_dirs`, export the ONNX model to `out`; return the training facts.

    The length of training is `steps` optimiser steps of `batch` crops, or, with `minutes` instead,
    as many steps as fit that wall time: the time of steps 10..19 fixes the step count, printed and
    stored in the model metadata, so `--steps N` with the same seed and data repeats the run exactly
    (the learning-rate schedule depends only on N).

    With `init` (an ONNX model written by `export_onnx`) the network starts from that model's weights
    and widths (its `training.channels` metadata; `channels` is then ignored) and is fine-tuned: its
    batch norms stay frozen (`segmentation_data.freeze_batchnorm`), the rest trains as above, and the
    facts record the starting model (`init`: file name, SHA-256 and its own training facts). With
    `thaw_norms` the batch norms are instead re-estimated on the data and trained
    (`segmentation_data.thaw_batchnorm`), for fine-tuning sets of thousands of frames whose looks differ
    from the old ones: the network then fits the new looks more closely and the old ones less
    (`perception/models/README.md`, "What the fine-tuning traded").
    `refine` is the width of the sub-pixel refinement stage (`build_model`; None: the `init` model's,
    else 0, none). A larger one than the `init` model's 0 adds the stage to it, starting from exactly
    what the model computed; any other change of width is refused (`PerceptionError`).
    `device` is the torch device that trains (`cpu`, `cuda`); `workers` forked processes make the batches
    ahead of it (`BatchSource`; 0: this process, the crops of the runs in perception/models/README.md).
    `weights_out`: also save the trained weights there (`torch.save` of the state dict) before the export.
    `log=False` prints nothing (tests).
    """
    import torch
    from torch.nn import functional as F  # noqa: N812 (the usual torch alias)

    if (steps is None) == (minutes is None):
        raise ValueError("train: give exactly one of steps and minutes")
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)

    def say(text: str) -> None:
        if log:
            print(text, flush=True)

    # the model's facts and the options are checked before any data is read (caches take minutes)
    init_refine = 0
    if init is not None:
        previous = onnx_training_facts(init)
        channels = tuple(int(c) for c in previous.get("channels", channels))
        init_refine = int(previous.get("refine", 0))
        if refine is not None and refine != init_refine and init_refine != 0:
            raise PerceptionError(
                f"{init}: has a refinement stage of width {init_refine}; --refine {refine} cannot change it"
            )
    refine = init_refine if refine is None else refine
    if refine < 0:
        raise PerceptionError(f"--refine {refine}: the refinement width must be 0 (none) or more")
    if refine and (crop[0] % 2 or crop[1] % 2):
        raise PerceptionError(f"--crop {crop[0]} {crop[1]}: the refinement stage needs even crop sides")

    frames = Frames(data_dirs)
    n = len(frames)
    say(f"{n} frames from {', '.join(map(str, data_dirs))} at {INPUT_WIDTH}x{INPUT_HEIGHT}")
    weights = torch.tensor(class_weights(frames.class_pixels(), weight_power), dtype=torch.float32)
    say(f"class weights {np.round(weights.numpy(), 2).tolist()}")

    init_facts: dict | None = None
    model = build_model(channels, refine)
    if init is not None:
        import_onnx_weights(model, init, added_tail=refine > init_refine)
        if refine > init_refine:
            say(f"added a sub-pixel refinement stage of width {refine} (starts as a no-op)")
        init_facts = {"file": Path(init).name, "sha256": file_sha256(init), "training": previous}
        if thaw_norms:
            stats_rng = np.random.default_rng([seed, 1])
            picks = [stats_rng.choice(n, min(batch, n), replace=False) for _ in range(THAW_BATCHES)]
            thaw_batchnorm(model, (_batch(frames, p, crop, focus, stats_rng)[::2] for p in picks))
            say(f"fine-tuning {init} (batch norms re-estimated on {THAW_BATCHES} x {batch} crops, trained)")
        else:
            freeze_batchnorm(model)
            say(f"fine-tuning {init} (batch norms frozen)")
    n_params = sum(p.numel() for p in model.parameters())
    say(f"SegNet channels {list(channels)}, refine {refine}: {n_params / 1e6:.3f} M parameters")
    model = model.to(device)
    weights = weights.to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    total = steps if steps is not None else 10**9
    t0 = time.time()
    t10 = t0
    step = 0
    running = []
    source = BatchSource(frames, batch, crop, focus, seed, rng, workers)
    # `minutes`: the speed is measured once the workers' head start is used up
    measure_from, measure_steps = (10, 10) if workers == 0 else (10 + source.ahead, 40)
    stopped_early = False
    while step < total:
        x, y, tops = (torch.from_numpy(a).to(device, non_blocking=True) for a in source.next())
        for group in opt.param_groups:
            group["lr"] = learning_rate(step, total, lr)
        logits = model(x, tops)
        loss = F.cross_entropy(logits, y, weight=weights, ignore_index=IGNORE)
        if dice > 0:
            loss = loss + dice * _dice_loss(logits, y, N_CLASSES)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        running.append(loss.item())
        if step == measure_from:
            t10 = time.time()
        if minutes is not None and step == measure_from + measure_steps:
            per_step = (time.time() - t10) / measure_steps
            total = max(40, int((60.0 * minutes - (time.time() - t0)) / per_step) + step)
            say(f"{per_step:.3f} s per step: training for {total} steps (--steps {total} repeats this run)")
        if minutes is not None and time.time() - t0 > 66.0 * minutes:  # the speed changed: stop in time
            say(f"step {step}: past {minutes} min by a tenth, stopping ({total} were planned)")
            stopped_early = True
            break
        if step % 50 == 0:
            say(
                f"step {step}/{total} epoch {step * batch / n:.2f} loss {np.mean(running[-50:]):.4f} "
                f"lr {learning_rate(step, total, lr):.2e} {(time.time() - t0) / 60:.1f} min"
            )
    source.close()
    minutes_used = (time.time() - t0) / 60.0
    model = model.cpu()
    facts = {
        "seed": seed,
        "steps": step,
        "batch": batch,
        "crop": list(crop),
        "focus": focus,
        "epochs": round(step * batch / n, 2),
        "frames": n,
        "lr": lr,
        "channels": list(channels),
        "refine": refine,
        "weight_power": weight_power,
        "dice": dice,
        "threads": threads,
        "device": device,
        "workers": workers,
        "train_minutes": round(minutes_used, 1),
        **({"stopped_early": True} if stopped_early else {}),
        "data": [Path(d).name for d in data_dirs],
    }
    if init_facts is not None:
        facts["fine_tuned"] = True
        facts["batch_norms"] = "re-estimated, trained" if thaw_norms else "frozen"
        facts["init"] = init_facts
    if weights_out is not None:  # the weights as torch saves them, in case the export fails
        torch.save(model.state_dict(), weights_out)
    export_onnx(model, out, facts, log)
    return facts


def export_onnx(model, out: Path, facts: dict, log: bool = True) -> None:
    """Export `model` (eval mode, 1 x 3 x H x W) to ONNX opset 17 with the metadata `OnnxSegmenter` reads.

    The graph has two outputs: `logits` (1, 10, H, W) float32 and `labels` (1, H, W) uint8, the argmax.
    """
    import onnx
    import torch

    class WithLabels(torch.nn.Module):
        def __init__(self, net: torch.nn.Module) -> None:
            super().__init__()
            self.net = net

        def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            logits = self.net(x)
            return logits, logits.argmax(dim=1).to(torch.uint8)

    model.eval()
    out.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, 3, INPUT_HEIGHT, INPUT_WIDTH)
    tmp = out.with_suffix(".tmp.onnx")
    torch.onnx.export(
        WithLabels(model),
        (dummy,),
        str(tmp),
        input_names=["rgb"],
        output_names=["logits", "labels"],
        opset_version=17,
        dynamo=False,
    )
    proto = onnx.load(str(tmp))
    tmp.unlink()
    meta = {
        "input_width": str(INPUT_WIDTH),
        "input_height": str(INPUT_HEIGHT),
        "mean": json.dumps(list(MEAN)),
        "std": json.dumps(list(STD)),
        "classes": json.dumps({str(k): v for k, v in CLASS_NAMES.items()}),
        "channel_order": "RGB",
        "layout": "NCHW",
        "output": "logits",
        "labels_output": "labels",
        "training": json.dumps(facts),
    }
    del proto.metadata_props[:]
    for key, value in meta.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.producer_name = "palletpilot.perception.train_segmentation"
    onnx.checker.check_model(proto)
    onnx.save(proto, str(tmp))
    tmp.replace(out)  # atomic: a failed export leaves an older file as it was
    if log:
        print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)", flush=True)


def main(argv: list[str] | None = None) -> int:
    """Command line: train, export, optionally evaluate on a held-out folder."""
    ap = argparse.ArgumentParser(
        prog="python -m palletpilot.perception.train_segmentation", description=__doc__.split("\n")[0]
    )
    ap.add_argument("data_dirs", type=Path, nargs="+", help="folders of frame bundles (.npz) with rgb and labels")
    ap.add_argument("--out", type=Path, default=Path("perception/models/segmenter.onnx"))
    ap.add_argument("--seed", type=int, default=0)
    length = ap.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, default=None, help="optimiser steps (default: 1500)")
    length.add_argument("--minutes", type=float, default=None, help="train for this wall time instead")
    ap.add_argument("--batch", type=int, default=12, help="crops per step")
    ap.add_argument("--crop", type=int, nargs=2, default=list(CROP), metavar=("W", "H"), help="training crop size")
    ap.add_argument("--focus", type=float, default=0.75, help="share of crops placed around a pallet pixel")
    ap.add_argument("--channels", default=",".join(map(str, CHANNELS)), help="SegNet widths at 1/2 .. 1/32")
    ap.add_argument(
        "--refine", type=int, default=None, help="sub-pixel refinement width (default: the --init model's, else 0)"
    )
    ap.add_argument("--weight-power", type=float, default=0.5, help="class weights: frequency ** -power")
    ap.add_argument("--dice", type=float, default=0.5, help="weight of the soft-Dice loss term")
    ap.add_argument("--lr", type=float, default=None, help="peak learning rate (default 4e-3, 1e-3 with --init)")
    ap.add_argument("--init", type=Path, default=None, help="fine-tune from the weights of this ONNX model")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--device", default="cpu", help="torch device that trains: cpu, cuda, cuda:1, ...")
    ap.add_argument("--workers", type=int, default=0, help="processes that make the batches ahead (0: none)")
    ap.add_argument("--weights-out", type=Path, default=None, help="also save the torch weights (state dict) here")
    ap.add_argument(
        "--thaw-norms", action="store_true", help="with --init: re-estimate the batch norms on the data and train them"
    )
    ap.add_argument("--heldout", type=Path, default=None, help="evaluate the exported model on these bundles")
    args = ap.parse_args(argv)
    steps = 1500 if args.steps is None and args.minutes is None else args.steps
    channels = tuple(int(c) for c in args.channels.split(","))
    lr = args.lr if args.lr is not None else (FINETUNE_LR if args.init is not None else 4e-3)
    try:
        check_training_inputs(args.data_dirs, args.init)
        facts = train(
            args.data_dirs,
            args.out,
            args.seed,
            steps,
            args.minutes,
            args.batch,
            lr,
            args.threads,
            tuple(args.crop),
            args.focus,
            channels,
            args.weight_power,
            args.dice,
            args.init,
            args.thaw_norms,
            refine=args.refine,
            device=args.device,
            workers=args.workers,
            weights_out=args.weights_out,
        )
    except PerceptionError as exc:  # bad input: one line, exit 2
        print(exc, file=sys.stderr)
        return 2
    print(json.dumps(facts), flush=True)
    if args.heldout is not None:
        from palletpilot.perception.segmentation import OnnxSegmenter, evaluate_segmenter, format_iou

        result = evaluate_segmenter(OnnxSegmenter(args.out), sorted(args.heldout.glob("*.npz")))
        print(format_iou(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Train the shipped segmentation model (`perception/models/segmenter.onnx`) on frame bundles.

Usage (torch comes with the optional `train` extra; CPU is enough)::

    palletpilot segment dataset DATA_DIR --frames 900 --seed 0     # or sim.dataset.generate_dataset
    python -m perception.train_segmentation DATA_DIR --out perception/models/segmenter.onnx --seed 0 \
        [--steps N | --minutes M] [--heldout HELDOUT_DIR] [--batch 12] [--lr 4e-3] [--threads 2]

The script only reads frame bundles (`perception.frames.load_bundle`, RGB plus labels); it never imports
the simulator. Steps:

1. Cache: every bundle's RGB is downscaled to the network's input size (320 x 240, `cv2.INTER_AREA`)
   and its labels by nearest neighbour; the arrays are cached in `DATA_DIR/.segcache_320x240.npz`
   (rebuilt when the file list changes).
2. Train `SegNet` (a light encoder-decoder, 0.19 M parameters) with AdamW, a warm-up plus cosine
   learning rate, class-weighted cross-entropy plus a soft-Dice term (label 255 ignored), horizontal
   flips and photometric jitter (brightness, contrast, per-channel gain, gamma, noise, blur).
   Deterministic for `--seed` and `--steps` (torch, numpy and the batch order are seeded; single
   process). `--minutes M` picks the step count from the measured speed and prints it, so that run
   is repeated with `--steps N`.
3. Export to ONNX (opset 17) with input `rgb` (1, 3, H, W) float32, normalised, and output `logits`
   (1, 10, H, W); the metadata (`metadata_props`) carries what `OnnxSegmenter` needs: `input_width`,
   `input_height`, `mean`, `std` (JSON lists, 0..1 RGB scale), `classes` (JSON {id: name}),
   `channel_order` ("RGB"), `layout` ("NCHW"), plus the training facts (`training`: seed, steps, epochs, frames, ...).
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

from perception.frames import SemanticClass, load_bundle

INPUT_WIDTH = 320
INPUT_HEIGHT = 240
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
N_CLASSES = 10
IGNORE = int(SemanticClass.UNLABELED)
CLASS_NAMES = {int(c): c.name.lower() for c in SemanticClass if c != SemanticClass.UNLABELED}


# -- data ---------------------------------------------------------------------------------------


def load_cached(data_dir: Path, width: int = INPUT_WIDTH, height: int = INPUT_HEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """RGB (N, H, W, 3) uint8 and labels (N, H, W) uint8 of every bundle in `data_dir`, downscaled to the input size.

    Bundles without RGB or labels are skipped. The result is cached next to the data.
    """
    files = sorted(data_dir.glob("*.npz"))
    files = [f for f in files if not f.name.startswith(".")]
    cache = data_dir / f".segcache_{width}x{height}.npz"
    names = np.array([f.name for f in files])
    if cache.exists():
        with np.load(cache) as c:
            if c["names"].shape == names.shape and np.all(c["names"] == names):
                return c["rgb"], c["labels"]
    rgbs, labels, kept = [], [], []
    for i, f in enumerate(files):
        b = load_bundle(f)
        if b.rgb is None or b.labels is None:
            continue
        rgbs.append(cv2.resize(b.rgb, (width, height), interpolation=cv2.INTER_AREA))
        labels.append(cv2.resize(b.labels, (width, height), interpolation=cv2.INTER_NEAREST))
        kept.append(f.name)
        if (i + 1) % 500 == 0:
            print(f"cached {i + 1}/{len(files)} bundles", flush=True)
    if not rgbs:
        raise SystemExit(f"{data_dir}: no frame bundles with rgb and labels")
    rgb_arr, lab_arr = np.stack(rgbs), np.stack(labels)
    if len(kept) == len(files):
        np.savez(cache, names=names, rgb=rgb_arr, labels=lab_arr)
    return rgb_arr, lab_arr


def class_weights(labels: np.ndarray) -> np.ndarray:
    """Per-class loss weights (N_CLASSES,): inverse square root of the pixel frequency, normalised, clipped."""
    counts = np.bincount(labels.ravel(), minlength=256)[:N_CLASSES].astype(float)
    freq = counts / max(counts.sum(), 1.0)
    w = 1.0 / np.sqrt(np.maximum(freq, 1e-4))
    w /= np.average(w, weights=np.maximum(freq, 1e-12))
    return np.clip(w, 0.5, 10.0)


def augment(rgb: np.ndarray, lab: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Flip and photometric jitter of one (H, W, 3) uint8 image and its (H, W) labels; returns float32 0..1 RGB."""
    if rng.random() < 0.5:
        rgb, lab = rgb[:, ::-1], lab[:, ::-1]
    img = rgb.astype(np.float32) / 255.0
    if rng.random() < 0.3:
        k = int(rng.choice([3, 5]))
        img = cv2.GaussianBlur(img, (k, k), 0)
    img = img * rng.uniform(0.6, 1.4) * rng.uniform(0.92, 1.08, 3).astype(np.float32)
    mean = img.mean()
    img = (img - mean) * rng.uniform(0.75, 1.25) + mean
    img = np.clip(img, 0.0, 1.0) ** rng.uniform(0.8, 1.25)
    img = img + rng.normal(0.0, rng.uniform(0.0, 0.03), img.shape).astype(np.float32)
    return np.clip(img, 0.0, 1.0).astype(np.float32), np.ascontiguousarray(lab)


# -- model ----------------------------------------------------------------------------------------


def build_model():  # -> torch.nn.Module (torch is imported lazily: the module imports without it)
    """The `SegNet` encoder-decoder: input (B, 3, H, W) normalised RGB, output (B, 10, H, W) logits.

    Encoder at 1/2, 1/4, 1/8, 1/16 of the input with dilated context convolutions and a global pooling
    branch; a decoder adding 1x1-projected skips back to 1/2; the 1/2-resolution logits are upsampled
    bilinearly to the input size inside the network.
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

    class SegNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.stem = nn.Sequential(cbr(3, 16, 2), cbr(16, 16))  # 1/2
            self.e2 = nn.Sequential(cbr(16, 32, 2), cbr(32, 32))  # 1/4
            self.e3 = nn.Sequential(cbr(32, 48, 2), cbr(48, 48))  # 1/8
            self.e4 = nn.Sequential(cbr(48, 64, 2), cbr(64, 64, dilation=2), cbr(64, 64, dilation=4))  # 1/16
            self.ctx = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(64, 64, 1), nn.ReLU(inplace=True))
            self.p3, self.d3 = proj(64, 48), cbr(48, 48)
            self.p2, self.d2 = proj(48, 32), cbr(32, 32)
            self.p1, self.d1 = proj(32, 16), dws(16)
            self.head = nn.Conv2d(16, N_CLASSES, 1)

        @staticmethod
        def up(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
            return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            f1 = self.stem(x)
            f2 = self.e2(f1)
            f3 = self.e3(f2)
            f4 = self.e4(f3)
            f4 = f4 + self.ctx(f4)
            y = self.d3(F.relu(self.up(self.p3(f4), f3) + f3))
            y = self.d2(F.relu(self.up(self.p2(y), f2) + f2))
            y = self.d1(F.relu(self.up(self.p1(y), f1) + f1))
            return self.up(self.head(y), x)

    return SegNet()


# -- training -------------------------------------------------------------------------------------


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
    data_dir: Path,
    out: Path,
    seed: int = 0,
    steps: int | None = None,
    minutes: float | None = None,
    batch: int = 12,
    lr: float = 4e-3,
    threads: int = 2,
) -> dict:
    """Train on the bundles in `data_dir`, export the ONNX model to `out`; return the training facts.

    The length of training is `steps` optimiser steps of `batch` frames, or, with `minutes` instead,
    as many steps as fit that wall time: the time of steps 10..19 fixes the step count, printed and
    stored in the model metadata, so `--steps N` with the same seed and data repeats the run exactly
    (the learning-rate schedule depends only on N).
    """
    import torch
    from torch.nn import functional as F  # noqa: N812 (the usual torch alias)

    if (steps is None) == (minutes is None):
        raise ValueError("train: give exactly one of steps and minutes")
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    rgb, labels = load_cached(data_dir)
    n = len(rgb)
    print(f"{n} frames from {data_dir} at {INPUT_WIDTH}x{INPUT_HEIGHT}", flush=True)
    weights = torch.tensor(class_weights(labels), dtype=torch.float32)
    print("class weights", np.round(weights.numpy(), 2).tolist(), flush=True)
    mean = torch.tensor(MEAN).view(1, 3, 1, 1)
    std = torch.tensor(STD).view(1, 3, 1, 1)

    model = build_model()
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    total = steps if steps is not None else 10**9
    t0 = time.time()
    t10 = t0
    step = 0
    running = []
    order = rng.permutation(n)
    cursor = 0
    while step < total:
        if cursor + batch > n:
            order, cursor = rng.permutation(n), 0
        idx = order[cursor : cursor + batch]
        cursor += batch
        pairs = [augment(rgb[i], labels[i], rng) for i in idx]
        x = torch.from_numpy(np.stack([p[0] for p in pairs])).permute(0, 3, 1, 2)
        x = (x - mean) / std
        y = torch.from_numpy(np.stack([p[1] for p in pairs]).astype(np.int64))
        for group in opt.param_groups:
            group["lr"] = learning_rate(step, total, lr)
        logits = model(x)
        loss = F.cross_entropy(logits, y, weight=weights, ignore_index=IGNORE) + 0.5 * _dice_loss(logits, y, N_CLASSES)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        running.append(loss.item())
        if step == 10:
            t10 = time.time()
        if minutes is not None and step == 20:
            per_step = (time.time() - t10) / 10
            total = max(40, int((60.0 * minutes - (time.time() - t0)) / per_step) + 20)
            print(f"{per_step:.2f} s per step: training for {total} steps (--steps {total} repeats this run)")
        if step % 50 == 0:
            print(
                f"step {step}/{total} epoch {step * batch / n:.1f} loss {np.mean(running[-50:]):.4f} "
                f"lr {learning_rate(step, total, lr):.2e} {(time.time() - t0) / 60:.1f} min",
                flush=True,
            )
    minutes_used = (time.time() - t0) / 60.0
    facts = {
        "seed": seed,
        "steps": step,
        "batch": batch,
        "epochs": round(step * batch / n, 2),
        "frames": n,
        "lr": lr,
        "train_minutes": round(minutes_used, 1),
    }
    export_onnx(model, out, facts)
    return facts


def export_onnx(model, out: Path, facts: dict) -> None:
    """Export `model` (eval mode, 1 x 3 x H x W) to ONNX opset 17 with the metadata `OnnxSegmenter` reads."""
    import onnx
    import torch

    model.eval()
    out.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, 3, INPUT_HEIGHT, INPUT_WIDTH)
    tmp = out.with_suffix(".tmp.onnx")
    torch.onnx.export(
        model, (dummy,), str(tmp), input_names=["rgb"], output_names=["logits"], opset_version=17, dynamo=False
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
        "training": json.dumps(facts),
    }
    del proto.metadata_props[:]
    for key, value in meta.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.producer_name = "palletpilot.perception.train_segmentation"
    onnx.checker.check_model(proto)
    onnx.save(proto, str(out))
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)", flush=True)


def main(argv: list[str] | None = None) -> int:
    """Command line: train, export, optionally evaluate on a held-out folder."""
    ap = argparse.ArgumentParser(prog="python -m perception.train_segmentation", description=__doc__.split("\n")[0])
    ap.add_argument("data_dir", type=Path, help="folder of frame bundles (.npz) with rgb and labels")
    ap.add_argument("--out", type=Path, default=Path("perception/models/segmenter.onnx"))
    ap.add_argument("--seed", type=int, default=0)
    length = ap.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, default=None, help="optimiser steps (default: 1500)")
    length.add_argument("--minutes", type=float, default=None, help="train for this wall time instead")
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("--lr", type=float, default=4e-3)
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--heldout", type=Path, default=None, help="evaluate the exported model on these bundles")
    args = ap.parse_args(argv)
    steps = 1500 if args.steps is None and args.minutes is None else args.steps
    facts = train(args.data_dir, args.out, args.seed, steps, args.minutes, args.batch, args.lr, args.threads)
    print(json.dumps(facts), flush=True)
    if args.heldout is not None:
        from perception.segmentation import OnnxSegmenter, evaluate_segmenter, format_iou

        result = evaluate_segmenter(OnnxSegmenter(args.out), sorted(args.heldout.glob("*.npz")))
        print(format_iou(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

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
   spawned processes ahead of the training loop (`perception.training_batches`; PNG frames are written
   once to a temporary folder that they map), each batch from its own generator seeded by (seed, step),
   so the crops do not depend on N (but differ from the single-process runs'); `--device cuda` trains on a
   GPU (perception/models/README.md, "Transfer to real photos").
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

import numpy as np

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import SemanticClass
from palletpilot.perception.segmentation_data import (
    check_training_inputs,
    file_sha256,
    freeze_batchnorm,
    import_onnx_weights,
    onnx_training_facts,
    thaw_batchnorm,
)
from palletpilot.perception.training_batches import (
    CROP,
    FOCUS_CLASSES,
    INPUT_HEIGHT,
    INPUT_WIDTH,
    MEAN,
    STD,
    BatchSource,
    Frames,
    batch_arrays,
)

N_CLASSES = 10
IGNORE = int(SemanticClass.UNLABELED)
CLASS_NAMES = {int(c): c.name.lower() for c in SemanticClass if c != SemanticClass.UNLABELED}
CHANNELS = (16, 32, 48, 64, 96)
"""SegNet feature channels at 1/2, 1/4, 1/8, 1/16 and 1/32 of the input."""
FINETUNE_LR = 1e-3
"""Default peak learning rate when fine-tuning from an existing model (`--init`)."""
THAW_BATCHES = 20
"""Batches of training crops over which `--thaw-norms` measures the batch norms' input statistics."""


# -- data (the frames, crops and batches: `perception.training_batches`) -------------------------


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


def _batch(frames: Frames, idx: np.ndarray, crop: tuple[int, int], focus: float, rng: np.random.Generator):
    """`batch_arrays` as torch tensors (CPU)."""
    import torch

    x, y, tops = batch_arrays(frames, idx, crop, focus, rng)
    return torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(tops)


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
    `device` is the torch device that trains (`cpu`, `cuda`); `workers` spawned processes make the batches
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

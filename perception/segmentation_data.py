"""Fine-tuning inputs of the segmentation trainer: the user's own labelled PNG frames and an ONNX model's weights.

- Labelled PNG frames (`load_png_folder`): a folder of `NAME.png` (the RGB image, 8-bit RGB or RGBA,
  any size; resized to the network's 640 x 480, area filter) and `NAME_labels.png` (8-bit single
  channel, the same size, one class id per pixel: 0 drivable, 1 vertical, 2 other_object,
  3 other_forklift, 4 other_vehicle, 5 forks, 6 cargo, 7 pallet_empty, 8 pallet_full, 9 person;
  255 = ignore: not scored by the loss; resized with the nearest neighbour). Every image needs its
  labels and every labels file its image; any other value, size or format is refused
  (`PerceptionError`, one line naming the file).
- ONNX weights (`import_onnx_weights`): the initialisers of a model written by
  `perception.train_segmentation.export_onnx` loaded into a fresh `build_model` network with the
  widths of the model's `training.channels` metadata. The export folds every batch normalisation
  into the convolution before it, so each Conv node of the graph has a weight and a bias; they (and
  the ConvTranspose of a refinement stage) are matched to the network's convolutions in the order
  the network runs them (`added_tail`: a network with a refinement stage the model lacks), and a
  batch norm after a convolution gets the identity statistics (mean 0, variance 1 - eps) with the
  folded bias as its shift. The network then computes exactly what the ONNX model does, as long as
  its batch norms stay in eval mode (`freeze_batchnorm`; fine-tuning keeps them so by default).
  `thaw_batchnorm` instead gives them the statistics of the new data, still computing the same
  function, so that they can train (`--thaw-norms`). A model of another architecture is refused
  (`PerceptionError`).
"""

from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from palletpilot.perception.errors import PerceptionError

LABELS_SUFFIX = "_labels.png"
"""`NAME_labels.png` holds the class ids of `NAME.png`."""
IGNORE_LABEL = 255
N_CLASSES = 10


def is_png_folder(folder: Path) -> bool:
    """Does `folder` hold labelled PNG frames (`*.png`) rather than frame bundles (`*.npz`)?"""
    return any(Path(folder).glob("*.png")) and not any(Path(folder).glob("*.npz"))


def png_pairs(folder: Path) -> list[tuple[Path, Path]]:
    """(image, labels) file pairs of a labelled PNG folder, sorted by name; a missing partner is an error."""
    folder = Path(folder)
    labels = sorted(folder.glob(f"*{LABELS_SUFFIX}"))
    images = sorted(p for p in folder.glob("*.png") if not p.name.endswith(LABELS_SUFFIX))
    label_stems = {p.name[: -len(LABELS_SUFFIX)] for p in labels}
    for image in images:
        if image.stem not in label_stems:
            raise PerceptionError(f"{image}: no labels file {image.stem}{LABELS_SUFFIX} next to it")
    image_stems = {p.stem for p in images}
    for lab in labels:
        if lab.name[: -len(LABELS_SUFFIX)] not in image_stems:
            raise PerceptionError(f"{lab}: no image {lab.name[: -len(LABELS_SUFFIX)]}.png next to it")
    if not images:
        raise PerceptionError(f"{folder}: no labelled PNG frames (NAME.png with NAME{LABELS_SUFFIX})")
    return [(image, folder / f"{image.stem}{LABELS_SUFFIX}") for image in images]


def read_png_pair(image: Path, labels: Path) -> tuple[np.ndarray, np.ndarray]:
    """RGB (H, W, 3) uint8 and class ids (H, W) uint8 of one labelled frame, checked (module docstring)."""
    bgr = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if bgr is None or bgr.dtype != np.uint8 or bgr.ndim != 3 or bgr.shape[2] not in (3, 4):
        raise PerceptionError(f"{image}: not an 8-bit RGB PNG image")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGRA2RGB if bgr.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    lab = cv2.imread(str(labels), cv2.IMREAD_UNCHANGED)
    if lab is None or lab.dtype != np.uint8 or lab.ndim != 2:
        raise PerceptionError(f"{labels}: not an 8-bit single-channel PNG (class ids 0..9, 255 = ignore)")
    if lab.shape != rgb.shape[:2]:
        raise PerceptionError(
            f"{labels}: {lab.shape[1]} x {lab.shape[0]} px, its image {image.name} is {rgb.shape[1]} x {rgb.shape[0]}"
        )
    bad = (lab >= N_CLASSES) & (lab != IGNORE_LABEL)
    if bad.any():
        values = sorted({int(v) for v in np.unique(lab[bad])})
        shown = ", ".join(map(str, values[:5])) + (", ..." if len(values) > 5 else "")
        raise PerceptionError(
            f"{labels}: label values {shown} in {int(bad.sum())} px; "
            f"allowed 0..{N_CLASSES - 1} and {IGNORE_LABEL} (ignore)"
        )
    return rgb, lab


def load_png_folder(folder: Path, width: int, height: int, threads: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """RGB (N, height, width, 3) and labels (N, height, width) uint8 of every labelled PNG frame in `folder`.

    The frames are decoded by `threads` threads (OpenCV releases the GIL): tens of thousands of frames
    of a generated set load in seconds rather than minutes.
    """
    from concurrent.futures import ThreadPoolExecutor

    pairs = png_pairs(folder)
    rgbs = np.empty((len(pairs), height, width, 3), np.uint8)
    labs = np.empty((len(pairs), height, width), np.uint8)

    def read(i: int) -> None:
        rgb, lab = read_png_pair(*pairs[i])
        if rgb.shape[:2] != (height, width):
            rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
            lab = cv2.resize(lab, (width, height), interpolation=cv2.INTER_NEAREST)
        rgbs[i], labs[i] = rgb, lab

    with ThreadPoolExecutor(max(1, threads)) as pool:
        list(pool.map(read, range(len(pairs))))
    return rgbs, labs


def check_training_inputs(data_dirs: list[Path], init: Path | None) -> None:
    """Refuse (one line) training folders that hold neither bundles nor labelled PNG frames, bad PNG pairs,
    and a missing starting model, before any work starts."""
    for folder in data_dirs:
        folder = Path(folder)
        if not folder.is_dir():
            raise PerceptionError(f"{folder}: not a folder")
        if is_png_folder(folder):
            for image, labels in png_pairs(folder):
                read_png_pair(image, labels)
        elif not any(folder.glob("*.npz")):
            raise PerceptionError(f"{folder}: no frame bundles (.npz) nor labelled PNG frames (NAME{LABELS_SUFFIX})")
    if init is not None and not Path(init).is_file():
        raise PerceptionError(f"{init}: no such model file")


# -- weights from an ONNX model ------------------------------------------------------------------


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file (hex)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def onnx_training_facts(path: Path) -> dict[str, Any]:
    """The `training` metadata of an ONNX model (empty when it has none)."""
    import onnx

    proto = onnx.load(str(path), load_external_data=False)
    meta = {p.key: p.value for p in proto.metadata_props}
    try:
        facts = json.loads(meta.get("training", "{}"))
    except json.JSONDecodeError as exc:
        raise PerceptionError(f"{path}: training metadata is not JSON ({exc.msg})") from None
    return facts if isinstance(facts, dict) else {}


def _conv_weights(path: Path) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """(weight, bias) of every Conv and ConvTranspose node of the ONNX graph, in graph order."""
    import onnx
    from onnx import numpy_helper

    try:
        proto = onnx.load(str(path))
    except Exception as exc:  # onnx raises several types for damaged files
        raise PerceptionError(f"{path}: not an ONNX model ({type(exc).__name__})") from None
    inits = {i.name: numpy_helper.to_array(i) for i in proto.graph.initializer}
    out = []
    for node in proto.graph.node:
        if node.op_type not in ("Conv", "ConvTranspose"):
            continue
        names = list(node.input)
        if len(names) < 2 or names[1] not in inits:
            raise PerceptionError(f"{path}: Conv node {node.name!r} has no stored weight; not a SegNet export")
        bias = inits.get(names[2]) if len(names) > 2 else None
        out.append((inits[names[1]], bias))
    return out


def freeze_batchnorm(model: Any) -> None:
    """Put every batch norm of `model` in eval mode (running statistics, no updates); the rest trains."""
    from torch import nn

    for module in model.modules():
        if isinstance(module, nn.BatchNorm2d):
            module.eval()


def thaw_batchnorm(model: Any, batches: Iterable[Any]) -> None:
    """Make the identity batch norms of an imported model trainable without changing what it computes.

    After `import_onnx_weights` every batch norm has identity statistics, so its running statistics say
    nothing about the data and training it with batch statistics would rescale every channel at once.
    This measures, in eval mode, the mean and variance of each batch norm's input over `batches`
    (normalised (B, 3, H, W) tensors, or `(x, top)` pairs for crops) and re-parameterises the layer so
    that it still computes the same function (running mean and variance the measured ones, scale
    sqrt(var + eps), shift the mean plus the old shift); the model is then left in train mode, its
    batch norms learning from the new data as in training from scratch. For large fine-tuning sets
    (thousands of frames of new looks); a few hundred own frames keep them frozen.
    """
    import torch
    from torch import nn

    norms = [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)]
    sums: dict[int, list[Any]] = {id(m): [0.0, 0.0, 0] for m in norms}

    def record(module: nn.BatchNorm2d, inputs: tuple[Any, ...], _out: Any) -> None:
        z = inputs[0].detach().double()
        acc = sums[id(module)]
        acc[0] = acc[0] + z.sum(dim=(0, 2, 3))
        acc[1] = acc[1] + (z * z).sum(dim=(0, 2, 3))
        acc[2] += z.shape[0] * z.shape[2] * z.shape[3]

    hooks = [m.register_forward_hook(record) for m in norms]
    model.eval()
    with torch.no_grad():
        for batch in batches:
            x, top = batch if isinstance(batch, tuple) else (batch, None)
            model(x, top)
    for h in hooks:
        h.remove()
    with torch.no_grad():
        for m in norms:
            total, squares, n = sums[id(m)]
            if n == 0:
                continue
            mean = total / n
            var = torch.clamp(squares / n - mean * mean, min=0.0)
            assert m.running_mean is not None and m.running_var is not None  # track_running_stats
            scale = torch.sqrt(m.running_var.double() + m.eps)  # what the layer divides by now
            gain = m.weight.double() / scale
            shift = m.bias.double() - gain * m.running_mean.double()  # the layer is z -> gain z + shift
            m.running_mean.copy_(mean.float())
            m.running_var.copy_(var.float())
            m.weight.copy_((gain * torch.sqrt(var + m.eps)).float())
            m.bias.copy_((shift + gain * mean).float())
    model.train()


def import_onnx_weights(model: Any, path: Path, added_tail: bool = False) -> None:
    """Load the weights of the ONNX model at `path` into the torch `model` (a `build_model` network).

    With `added_tail` the network may run more convolutions after the model's: the stored ones fill
    the first, the rest keep their initial weights (a refinement stage added to a trained model).
    Raises `PerceptionError` (one line) when the graph's convolutions do not match the network's in
    number or shapes (another architecture or other widths).
    """
    import torch
    from torch import nn

    convs: list[nn.Conv2d | nn.ConvTranspose2d] = []
    follower: dict[int, nn.BatchNorm2d] = {}
    for module in model.modules():
        children = list(module.children())
        for a, b in itertools.pairwise(children):
            if isinstance(a, nn.Conv2d) and isinstance(b, nn.BatchNorm2d):
                follower[id(a)] = b
    hooks = [
        m.register_forward_hook(lambda mod, _i, _o: convs.append(mod))
        for m in model.modules()
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))
    ]
    was_training = model.training
    model.eval()
    with torch.no_grad():
        model(torch.zeros(1, 3, 64, 64))
    for h in hooks:
        h.remove()
    model.train(was_training)
    stored = _conv_weights(path)
    if added_tail and len(stored) < len(convs):
        convs = convs[: len(stored)]
    if len(stored) != len(convs):
        raise PerceptionError(
            f"{path}: {len(stored)} convolutions, the SegNet of these widths has {len(convs)}; another architecture"
        )
    with torch.no_grad():
        for k, (conv, (weight, bias)) in enumerate(zip(convs, stored, strict=True)):
            if tuple(weight.shape) != tuple(conv.weight.shape):
                raise PerceptionError(
                    f"{path}: convolution {k} has weights {list(weight.shape)}, the SegNet expects "
                    f"{list(conv.weight.shape)}; another architecture or other widths"
                )
            conv.weight.copy_(torch.from_numpy(np.array(weight, np.float32)))
            b = np.zeros(weight.shape[0], np.float32) if bias is None else np.array(bias, np.float32)
            bn = follower.get(id(conv))
            if bn is not None:  # folded into the conv by the export: identity statistics, the bias as shift
                bn.weight.fill_(1.0)
                bn.bias.copy_(torch.from_numpy(b))
                assert bn.running_mean is not None and bn.running_var is not None  # track_running_stats
                bn.running_mean.zero_()
                bn.running_var.fill_(1.0 - bn.eps)
            elif conv.bias is not None:
                conv.bias.copy_(torch.from_numpy(b))
            elif np.any(b):
                raise PerceptionError(f"{path}: convolution {k} has a bias the SegNet has no place for")

"""Training batches for the segmenter: the frames, their crops and augmentation, and the batch workers.

Torch-free (numpy and OpenCV), so that batch workers start light. Public API:
- `load_cached` (a folder of frame bundles as memory-mapped arrays at the input size, cached next to it),
  `Frames` (several data folders as one indexable set of (RGB, labels) frames),
- `sample_crop` (where a training crop lies), `augment` (flip and photometric jitter),
- `batch_arrays` (one normalised batch as numpy), `BatchSource` (batches in order, from this process or
  from worker processes).

Batch workers are *spawned*, never forked: a process forked from one that has used OpenCV's thread pool
(or holds any other library's lock on another thread, as a test process or a trainer with torch does) can
block forever in its first OpenCV call (opencv/opencv#5150). Spawned workers import this module afresh and
map the frames from `.npy` files: a bundle folder's cache as it is, PNG frames written once to a
temporary folder (`/dev/shm` when it has room).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import SemanticClass, load_bundle
from palletpilot.perception.segmentation_data import is_png_folder, load_png_folder

INPUT_WIDTH = 640
INPUT_HEIGHT = 480
CROP = (384, 288)
"""Default training crop (width, height) in pixels of the full-resolution frames."""
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
FOCUS_CLASSES = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))
"""Crops placed around a pixel of one of these classes (`--focus` of them)."""
WORKER_WAIT_S = 300.0
"""How long the trainer waits for a worker's batch before it stops with an error (a batch takes well
under a second; only a stuck worker takes this long)."""


# -- frames ---------------------------------------------------------------------------------------


def cache_paths(data_dir: Path, width: int = INPUT_WIDTH, height: int = INPUT_HEIGHT) -> tuple[Path, Path, Path]:
    """The RGB, labels and file-list paths of `data_dir`'s frame cache at `width` x `height`."""
    stem = f".segcache_{width}x{height}"
    rgb, lab, key = (Path(data_dir) / f"{stem}_{s}" for s in ("rgb.npy", "labels.npy", "files.json"))
    return rgb, lab, key


def load_cached(data_dir: Path, width: int = INPUT_WIDTH, height: int = INPUT_HEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """RGB (N, H, W, 3) uint8 and labels (N, H, W) uint8 of every bundle in `data_dir` at the input size.

    Bundles without RGB or labels are skipped. The arrays are cached next to the data as .npy files
    (rebuilt when the list of bundle files changes) and returned memory-mapped, read-only.
    """
    files = sorted(f for f in data_dir.glob("*.npz") if not f.name.startswith("."))
    rgb_path, lab_path, key_path = cache_paths(data_dir, width, height)
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
        self._set_parts([_load_folder(Path(d)) for d in data_dirs])

    @classmethod
    def from_files(cls, files: list[tuple[Path, Path]]) -> Frames:
        """The frames of (RGB, labels) `.npy` file pairs, memory-mapped read-only (what `files` wrote)."""
        frames = cls.__new__(cls)
        frames._set_parts([(np.load(rgb, mmap_mode="r"), np.load(lab, mmap_mode="r")) for rgb, lab in files])
        return frames

    def _set_parts(self, parts: list[tuple[np.ndarray, np.ndarray]]) -> None:
        self.parts = parts
        self.offsets = np.cumsum([0] + [len(rgb) for rgb, _ in self.parts])

    def files(self, folder: Path) -> list[tuple[Path, Path]]:
        """(RGB, labels) `.npy` files holding these frames, for other processes to map: a part already read
        from files (a bundle folder's cache) names them; a part held in memory (PNG frames) is written into
        `folder` and from then on read from there, so that this process does not hold it twice."""
        out = []
        for k, (rgb, lab) in enumerate(self.parts):
            rgb_file, lab_file = _mapped_file(rgb), _mapped_file(lab)
            if rgb_file is None or lab_file is None:
                rgb_file, lab_file = folder / f"part{k}_rgb.npy", folder / f"part{k}_labels.npy"
                for path, array in ((rgb_file, rgb), (lab_file, lab)):
                    mapped = np.lib.format.open_memmap(path, mode="w+", dtype=array.dtype, shape=array.shape)
                    mapped[:] = array
                    mapped.flush()
                    del mapped
                self.parts[k] = (np.load(rgb_file, mmap_mode="r"), np.load(lab_file, mmap_mode="r"))
            out.append((rgb_file, lab_file))
        return out

    def nbytes_in_memory(self) -> int:
        """Bytes of the parts held in memory (not read from files): what `files` would write."""
        return sum(
            int(rgb.nbytes + lab.nbytes)
            for rgb, lab in self.parts
            if _mapped_file(rgb) is None or _mapped_file(lab) is None
        )

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


def _load_folder(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """A data folder's (RGB, labels) arrays: labelled PNG frames in memory, frame bundles memory-mapped."""
    return load_png_folder(folder, INPUT_WIDTH, INPUT_HEIGHT) if is_png_folder(folder) else load_cached(folder)


def _mapped_file(array: np.ndarray) -> Path | None:
    """The `.npy` file `array` maps as a whole (as `np.load(..., mmap_mode="r")` returns it), else None."""
    if not isinstance(array, np.memmap) or array.filename is None:
        return None
    path = Path(array.filename)
    if not path.is_file():  # a folder of an earlier pool, removed since: still mapped here, written anew
        return None
    whole = np.load(path, mmap_mode="r")
    return path if whole.shape == array.shape and whole.offset == array.offset else None


# -- crops and augmentation -----------------------------------------------------------------------


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


def batch_arrays(
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


# -- batch workers ----------------------------------------------------------------------------------

_WORKER_FRAMES: Frames | None = None
"""The training frames in a batch worker process (mapped from the files its pool was given)."""


def _worker_start(files: list[tuple[Path, Path]]) -> None:
    """A batch worker's start: map the frames, take one OpenCV thread (the workers are the parallelism),
    take the default SIGTERM (die) and ignore SIGINT (the trainer handles Ctrl-C and closes the pool)."""
    import signal

    global _WORKER_FRAMES
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(1)
    _WORKER_FRAMES = Frames.from_files(files)


def _worker_batch(job: tuple[np.ndarray, tuple[int, int], float, int, int]) -> tuple[np.ndarray, ...]:
    """A batch worker's job: the batch of frames `idx` with its own generator seeded by (seed, step)."""
    idx, crop, focus, seed, step = job
    assert _WORKER_FRAMES is not None
    return batch_arrays(_WORKER_FRAMES, idx, crop, focus, np.random.default_rng([seed, step, 11]))


def _share_folder(nbytes: int) -> tempfile.TemporaryDirectory:
    """A temporary folder for `nbytes` of frames: in `/dev/shm` when it has room to spare, else in the
    temporary folder; neither with room is a `PerceptionError`."""
    for base in ("/dev/shm", tempfile.gettempdir()):
        if Path(base).is_dir() and shutil.disk_usage(base).free > 1.25 * nbytes + (64 << 20):
            return tempfile.TemporaryDirectory(prefix="palletpilot-frames-", dir=base)
    raise PerceptionError(
        f"the batch workers need {nbytes / 2**30:.1f} GiB of room for the frames in /dev/shm or "
        f"{tempfile.gettempdir()}; free some, or train with --workers 0"
    )


class BatchSource:
    """Training batches in order: made in this process (`workers` 0: one generator, the historic runs' crops)
    or by `workers` spawned processes ahead of the training loop (each batch seeded by (seed, step), so the
    crops do not depend on the number of workers)."""

    def __init__(self, frames: Frames, batch: int, crop: tuple[int, int], focus: float, seed: int,
                 rng: np.random.Generator, workers: int = 0) -> None:  # fmt: skip
        self.frames, self.batch, self.crop, self.focus, self.seed, self.rng = frames, batch, crop, focus, seed, rng
        self.order, self.cursor = rng.permutation(len(frames)), 0
        self.pool = None
        self.shared: tempfile.TemporaryDirectory | None = None
        self.ahead = 0
        self.pending: list = []
        self.step = 0
        if workers > 0:
            import multiprocessing

            self.shared = _share_folder(frames.nbytes_in_memory())
            files = frames.files(Path(self.shared.name))
            self.pool = multiprocessing.get_context("spawn").Pool(workers, _worker_start, (files,))
            self.ahead = 4 * workers

    def _next_idx(self) -> np.ndarray:
        if self.cursor + self.batch > len(self.frames):
            self.order, self.cursor = self.rng.permutation(len(self.frames)), 0
        idx = self.order[self.cursor : self.cursor + self.batch]
        self.cursor += self.batch
        return idx

    def next(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The next batch (numpy arrays, `batch_arrays`); a worker silent for `WORKER_WAIT_S` is a
        `PerceptionError`."""
        if self.pool is None:
            return batch_arrays(self.frames, self._next_idx(), self.crop, self.focus, self.rng)
        while len(self.pending) < self.ahead:
            job = (self._next_idx(), self.crop, self.focus, self.seed, self.step + len(self.pending))
            self.pending.append(self.pool.apply_async(_worker_batch, (job,)))
        self.step += 1
        import multiprocessing

        try:
            return self.pending.pop(0).get(timeout=WORKER_WAIT_S)
        except multiprocessing.TimeoutError:
            raise PerceptionError(
                f"a batch worker made no batch in {WORKER_WAIT_S:.0f} s; train with --workers 0"
            ) from None

    def close(self) -> None:
        """Stop the workers and remove the frames written for them."""
        if self.pool is not None:
            self.pool.terminate()
            self.pool.join()
            self.pool = None
        if self.shared is not None:
            self.shared.cleanup()
            self.shared = None

"""`palletpilot bench realdata DIR`: the segmentation model on real photos with COCO front-face polygons.

DIR is a folder of splits (`DIR/SPLIT/JPEGImages/*.jpg` and `DIR/SPLIT/pallet_SPLIT_annotations.json`,
the layout of `../shared/realdata/pallet_front_rgb/`; `--split`, default `val`), one split's folder (one
annotations `.json` in it), or the annotations file itself. The annotations are COCO: `images` (`id`,
`file_name` relative to the annotation file's folder, `width`, `height`), `categories` (one named
`front`), `annotations` (`image_id`, `category_id`, `segmentation`: polygons `[[x0, y0, x1, y1, ...],
...]` in pixels, image frame, origin at the top-left corner of the top-left pixel; `bbox`: `[x, y, w, h]`
pixels; either may be a JSON text string of the same, as the source of that folder stores them). Only
`front` annotations count: the face of a pallet the forks enter, blocks and boards. RLE masks are refused.

Each photo goes through the segmenter (`OnnxSegmenter(--model).segment(rgb)`, at the photo's own
size: the model resizes it to its input). A pixel is *pallet* when it gets either pallet class
(`PALLET_EMPTY`, `PALLET_FULL`); the photos have labels for nothing else. A front is the pixels whose
centre lies inside one of its polygons (`front_mask`). Figures (`score_photos`):

- `front_recall`: pallet pixels / front pixels, pooled over all photos (each pixel once, where fronts
  overlap), and `front_recall_mean`, the mean over fronts of each front's own share;
- `box_iou`: IoU of the pallet pixels and the union of the photo's front polygons inside each front's
  `bbox` grown by a quarter of its width / height on each side (clipped to the photo): pooled over fronts
  (summed intersections / summed unions) and `box_iou_mean`; what it adds to recall: pallet labels
  spilling onto the floor, the load or a neighbour lower it;
- `pallet_outside_boxes`: the pallet pixels outside every front's grown box, as a share of all pallet pixels
  and of all photo pixels, pooled: what recall cannot see, pallet labels on shelves, tables and floors (a
  model that calls everything pallet has full recall);
- `fronts_covered`: fronts with at least half their pixels pallet (count, total, share), and per photo:
  `photos_all_covered`, `photos_none_covered` (photos with fronts), `fronts_per_photo`;
- `front_pixels_labelled`: the share of front pixels given each class (what the model calls the pallet
  instead), pooled;
- `front_recall_by_height`: pooled recall by the front's bbox height as a share of the photo's height;
- `segment_ms`: the segmenter's time per photo (median, p95; the photo read excluded).

`--fit tiles` segments a photo wider than the model's input aspect as windows of that aspect
(`AspectTiles`) instead of letting the model squash it (a 1280 x 720 photo into 640 x 480 is 0.5 x
across but 0.67 x down): whether the figures come from the distortion or from the look.

Goals (issue 37): `front_recall` >= 0.80 and `fronts_covered` share >= 0.90. A missing folder or file, a
broken or incomplete annotations file (every problem, one line each naming the file and field), an
unreadable photo or one of another size than its entry says: `RealDataError`, exit 2. The photos stay
where they are; nothing is written. Deterministic: the same photos and model give the same figures
(times aside).

Public API: `RealDataError`, `Front`, `Photo`, `annotations_file`, `load_coco`, `read_rgb`, `front_mask`,
`grown_box`, `score_photos`, `AspectTiles`, `add_arguments`, `run`, the goals.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from palletpilot.executor.apps.cli_args import count
from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.errors import raise_problems
from palletpilot.geometry.fileio import check_size, parse_json, read_text
from palletpilot.perception.frames import SemanticClass
from palletpilot.perception.segmentation import DEFAULT_MODEL, SegmentationService

FRONT_RECALL_GOAL = 0.80
"""Issue 37: the share of front-face pixels labelled pallet (pooled)."""
FRONTS_COVERED_GOAL = 0.90
"""Issue 37: the share of fronts with at least `COVERED_SHARE` of their pixels labelled pallet."""
COVERED_SHARE = 0.5
BOX_GROWTH = 0.25
"""A front's box for `box_iou` is its bbox grown by this share of its width / height on each side."""
FRONT_CATEGORY = "front"
PALLET_CLASSES = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))
HEIGHT_BINS = (0.05, 0.10, 0.20)
"""Edges of `front_recall_by_height`: a front's bbox height as a share of its photo's height."""
MAX_PROBLEMS = 20
"""At most this many problem lines of one annotations file (then how many more)."""
_BBOX_SLACK_PX = 2.0
_EDGE_SLACK_PX = 1.0


class RealDataError(PalletpilotError):
    """A photo folder or annotations file that cannot be scored; one line per problem, naming file and field."""


@dataclass(frozen=True)
class Front:
    """One annotated pallet front face: its polygons ((N, 2) float64 x, y pixels) and bbox (x, y, w, h px)."""

    annotation_id: object
    polygons: tuple[np.ndarray, ...]
    bbox: tuple[float, float, float, float]


@dataclass(frozen=True)
class Photo:
    """One photo of the set: its file, its size as the annotations state it (px) and its fronts."""

    path: Path
    width: int
    height: int
    fronts: tuple[Front, ...]


def annotations_file(folder: str | Path, split: str = "val") -> Path:
    """The COCO annotations file of `folder` (the file itself, a split folder with one `.json`, or a
    folder of splits: `folder/split/`, preferring `pallet_SPLIT_annotations.json`)."""
    root = Path(folder)
    if root.is_file():
        return root
    if not root.is_dir():
        raise RealDataError(f"{root}: no such folder")
    jsons = sorted(p for p in root.glob("*.json") if p.is_file())
    if not jsons:
        splits = sorted(p.name for p in root.iterdir() if p.is_dir() and any(p.glob("*.json")))
        if not (root / split).is_dir():
            known = f"splits here: {', '.join(splits)}" if splits else "no split folders with a .json in them"
            raise RealDataError(f"{root}: no annotations .json and no split folder '{split}' ({known})")
        root = root / split
        jsons = sorted(p for p in root.glob("*.json") if p.is_file())
        if not jsons:
            raise RealDataError(f"{root}: no COCO annotations file (*.json)")
    named = [p for p in jsons if p.name == f"pallet_{root.name}_annotations.json"]
    if len(jsons) > 1 and not named:
        raise RealDataError(f"{root}: several .json files ({', '.join(p.name for p in jsons)}); name one as DIR")
    return named[0] if named else jsons[0]


def _number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _maybe_text(value: object, where: str) -> object:
    """A field that may be stored as JSON text (`"[[1, 2, ...]]"`), parsed; any other value as it is."""
    return parse_json(value, where, RealDataError) if isinstance(value, str) else value


def _polygons(value: object, where: str, width: int, height: int) -> tuple[np.ndarray, ...]:
    """The polygons of a `segmentation` field, checked to lie in the photo (pixels)."""
    value = _maybe_text(value, where)
    if isinstance(value, dict):
        raise RealDataError(f"{where}: an RLE mask; only polygons are supported")
    if isinstance(value, list) and value and all(_number(v) for v in value):
        value = [value]  # one flat polygon
    if not isinstance(value, list) or not value:
        raise RealDataError(f"{where}: expected a list of polygons [[x0, y0, x1, y1, ...], ...]")
    polygons = []
    for k, poly in enumerate(value):
        if not isinstance(poly, list) or len(poly) < 6 or len(poly) % 2 or not all(_number(v) for v in poly):
            raise RealDataError(f"{where}[{k}]: a polygon needs an even number (>= 6) of finite numbers")
        xy = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        if lo.min() < -_EDGE_SLACK_PX or hi[0] > width + _EDGE_SLACK_PX or hi[1] > height + _EDGE_SLACK_PX:
            raise RealDataError(
                f"{where}[{k}]: polygon spans x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f} px, "
                f"outside the {width} x {height} px image"
            )
        polygons.append(xy)
    return tuple(polygons)


def _bbox(value: object, where: str, polygons: tuple[np.ndarray, ...]) -> tuple[float, float, float, float]:
    """The `bbox` field (x, y, w, h px), checked to hold its polygons; the polygons' extent when absent."""
    xy = np.concatenate(polygons)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    if value is None:
        return float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])
    value = _maybe_text(value, where)
    if not isinstance(value, list) or len(value) != 4 or not all(_number(v) for v in value) or min(value[2:]) < 0:
        raise RealDataError(f"{where}: expected [x, y, width, height] with finite numbers, sizes >= 0")
    x, y, w, h = (float(v) for v in value)
    s = _BBOX_SLACK_PX
    if lo[0] < x - s or lo[1] < y - s or hi[0] > x + w + s or hi[1] > y + h + s:
        raise RealDataError(
            f"{where}: [{x:g}, {y:g}, {w:g}, {h:g}] does not hold its segmentation "
            f"(x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f} px)"
        )
    return x, y, w, h


def _list_field(doc: dict, key: str, where: str) -> list:
    value = doc.get(key)
    if not isinstance(value, list):
        raise RealDataError(f"{where}: {key}: expected a list, got {type(value).__name__}")
    return value


def _front_category(doc: dict, where: str) -> object:
    ids = [
        c.get("id")
        for c in _list_field(doc, "categories", where)
        if isinstance(c, dict) and c.get("name") == FRONT_CATEGORY
    ]
    if len(ids) != 1:
        raise RealDataError(f"{where}: categories: expected one category named '{FRONT_CATEGORY}', found {len(ids)}")
    return ids[0]


def _images(doc: dict, where: str, folder: Path, problems: list[str]) -> dict[object, tuple[Path, int, int]]:
    """Image id -> (file, width, height px) of every valid `images` entry; a problem line for each other."""
    images: dict[object, tuple[Path, int, int]] = {}
    for i, entry in enumerate(_list_field(doc, "images", where)):
        at = f"{where}: images[{i}]"
        if not isinstance(entry, dict):
            problems.append(f"{at}: expected an object")
            continue
        name, w, h, key = entry.get("file_name"), entry.get("width"), entry.get("height"), entry.get("id")
        if not isinstance(name, str) or not name:
            problems.append(f"{at}: file_name: expected a file name")
        elif not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (w, h)):
            problems.append(f"{at} ({name}): width, height: expected positive integers, got {w!r}, {h!r}")
        elif not isinstance(key, (int, str)) or isinstance(key, bool) or key in images:
            problems.append(f"{at} ({name}): id: {key!r} is not a unique integer or string")
        else:
            path = folder / name
            if not path.is_file() and (folder / "JPEGImages" / name).is_file():
                path = folder / "JPEGImages" / name  # bare file names next to a JPEGImages folder
            if not path.is_file():
                problems.append(f"{at}: file_name: {path} not found")
            elif not cv2.haveImageReader(str(path)):  # the file's signature only; decoding comes later
                problems.append(f"{at}: file_name: {path} is not an image OpenCV can read")
            else:
                images[key] = (path, int(w), int(h))  # type: ignore[arg-type]
    return images


def _fronts(
    doc: dict, where: str, images: dict[object, tuple[Path, int, int]], problems: list[str]
) -> dict[object, list[Front]]:
    """Image id -> its fronts, from every `front` annotation; a problem line for each bad one."""
    front_id = _front_category(doc, where)
    listed = {e.get("id") for e in doc["images"] if isinstance(e, dict) and isinstance(e.get("id"), (int, str))}
    fronts: dict[object, list[Front]] = {key: [] for key in images}
    for i, ann in enumerate(_list_field(doc, "annotations", where)):
        at = f"{where}: annotations[{i}]"
        if not isinstance(ann, dict):
            problems.append(f"{at}: expected an object")
            continue
        if ann.get("category_id") != front_id:
            continue
        key = ann.get("image_id")
        if not isinstance(key, (int, str)) or key not in fronts:
            if not isinstance(key, (int, str)) or key not in listed:  # a bad entry's id: reported there
                problems.append(f"{at}: image_id: {key!r} is not the id of an entry of images")
            continue
        _, w, h = images[key]
        try:
            polygons = _polygons(ann.get("segmentation"), f"{at}.segmentation", w, h)
            box = _bbox(ann.get("bbox"), f"{at}.bbox", polygons)
        except RealDataError as exc:
            problems.extend(exc.problems)
            continue
        fronts[key].append(Front(ann.get("id", i), polygons, box))
    return fronts


def load_coco(path: str | Path) -> list[Photo]:
    """The photos of a COCO annotations file (module docstring), in the order of its `images`, each with
    its `front` annotations. Every problem of the file: `RealDataError`, one line each (at most
    `MAX_PROBLEMS`), naming the file and the field."""
    path = Path(path)
    where = str(path)
    doc = parse_json(read_text(path, RealDataError), where, RealDataError)
    check_size(doc, where, RealDataError)
    if not isinstance(doc, dict):
        raise RealDataError(f"{where}: expected a COCO object with images, annotations, categories")
    problems: list[str] = []
    images = _images(doc, where, path.parent, problems)
    fronts = _fronts(doc, where, images, problems)
    if problems:
        shown = problems[:MAX_PROBLEMS]
        if len(problems) > MAX_PROBLEMS:
            shown.append(f"{where}: ... and {len(problems) - MAX_PROBLEMS} more problems")
        raise_problems(shown, RealDataError)
    if not images:
        raise RealDataError(f"{where}: images: no photos")
    return [Photo(p, w, h, tuple(fronts[key])) for key, (p, w, h) in images.items()]


def read_rgb(photo: Photo) -> np.ndarray:
    """The photo as an RGB (H, W, 3) uint8 array; unreadable or another size than its entry: `RealDataError`."""
    bgr = cv2.imread(str(photo.path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise RealDataError(f"{photo.path}: not a readable image")
    if bgr.shape[:2] != (photo.height, photo.width):
        raise RealDataError(
            f"{photo.path}: {bgr.shape[1]} x {bgr.shape[0]} px, its annotation entry says "
            f"width {photo.width}, height {photo.height}"
        )
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _inside(poly: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Which pixel centres (row + 0.5, col + 0.5) of the grid `rows` x `cols` lie inside `poly` (even-odd rule)."""
    py, px = rows + 0.5, cols + 0.5
    inside = np.zeros((len(rows), len(cols)), bool)
    for (x1, y1), (x2, y2) in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        crosses = (y1 > py) != (y2 > py)
        if not crosses.any():
            continue
        x_at = x1 + (py[crosses] - y1) * (x2 - x1) / (y2 - y1)
        inside[crosses] ^= px[None, :] < x_at[:, None]
    return inside


def front_mask(front: Front, shape: tuple[int, int]) -> np.ndarray:
    """A front's polygons filled as an (H, W) bool mask: the pixels whose centre (col + 0.5, row + 0.5)
    lies inside a polygon (its area to 0.1 %; `cv2.fillPoly` adds its whole outline, about 10 % more on
    these thin faces)."""
    mask = np.zeros(shape, bool)
    for poly in front.polygons:
        lo = np.clip(np.floor(poly.min(axis=0)).astype(int), 0, None)
        hi = np.minimum(np.ceil(poly.max(axis=0)).astype(int), (shape[1], shape[0]))
        if (hi > lo).all():
            rows, cols = np.arange(lo[1], hi[1]), np.arange(lo[0], hi[0])
            mask[lo[1] : hi[1], lo[0] : hi[0]] |= _inside(poly, rows, cols)
    return mask


def grown_box(front: Front, shape: tuple[int, int], growth: float = BOX_GROWTH) -> tuple[slice, slice]:
    """The (rows, cols) slices of a front's bbox grown by `growth` x its size on each side, in the image."""
    x, y, w, h = front.bbox
    x0, x1 = max(0, math.floor(x - growth * w)), min(shape[1], math.ceil(x + w + growth * w))
    y0, y1 = max(0, math.floor(y - growth * h)), min(shape[0], math.ceil(y + h + growth * h))
    return slice(y0, y1), slice(x0, x1)


class _Tally:
    """The pooled and per-front counts of `score_photos`."""

    def __init__(self) -> None:
        self.front_px = self.front_hits = 0
        self.labels = np.zeros(256, np.int64)
        self.recalls: list[float] = []
        self.ious: list[float] = []
        self.box_inter = self.box_union = 0
        self.photo_px = self.pallet_px = self.pallet_outside = 0
        self.heights: list[tuple[float, int, int]] = []  # (height share, pixels, pallet pixels) per front
        self.per_photo: list[dict[str, Any]] = []

    def add(self, photo: Photo, labels: np.ndarray) -> None:
        """Score one photo's labels against its fronts."""
        pallet = np.isin(labels, PALLET_CLASSES)
        masks = [front_mask(f, labels.shape) for f in photo.fronts]
        union = np.logical_or.reduce(masks) if masks else np.zeros(labels.shape, bool)
        self.front_px += int(union.sum())
        self.front_hits += int((union & pallet).sum())
        self.labels += np.bincount(labels[union], minlength=256)
        covered = 0
        boxes = [grown_box(front, labels.shape) for front in photo.fronts]
        near = np.zeros(labels.shape, bool)  # inside some front's grown box
        for box in boxes:
            near[box] = True
        self.photo_px += labels.size
        self.pallet_px += int(pallet.sum())
        self.pallet_outside += int((pallet & ~near).sum())
        for front, mask, box in zip(photo.fronts, masks, boxes, strict=True):
            n, hits = int(mask.sum()), int((mask & pallet).sum())
            self.recalls.append(hits / n)
            covered += hits >= COVERED_SHARE * n
            self.heights.append((front.bbox[3] / photo.height, n, hits))
            inter, either = int((pallet[box] & union[box]).sum()), int((pallet[box] | union[box]).sum())
            self.box_inter += inter
            self.box_union += either
            self.ious.append(inter / either if either else 0.0)
        self.per_photo.append({"photo": photo.path.name, "fronts": len(photo.fronts), "covered": covered})


def _share(num: float, den: float) -> float | None:
    return round(num / den, 4) if den else None


def _by_height(heights: list[tuple[float, int, int]]) -> dict[str, dict[str, Any]]:
    edges = (0.0, *HEIGHT_BINS, math.inf)
    out = {}
    for lo, hi in itertools.pairwise(edges):
        rows = [(n, k) for share, n, k in heights if lo <= share < hi]
        name = f"<{hi:g}" if lo == 0 else (f">={lo:g}" if hi == math.inf else f"{lo:g}-{hi:g}")
        out[name] = {"fronts": len(rows), "recall": _share(sum(k for _, k in rows), sum(n for n, _ in rows))}
    return out


def score_photos(photos: Sequence[Photo], segmenter: SegmentationService, per_photo: bool = False) -> dict[str, Any]:
    """Segment every photo with `segmenter` and score its pallet pixels against the front polygons (the
    figures of the module docstring, as a dict); `per_photo` adds each photo's fronts and covered count.
    A labels image of another size than its photo: `RealDataError`."""
    tally, times = _Tally(), []
    for photo in photos:
        rgb = read_rgb(photo)
        t0 = time.perf_counter()
        labels = np.asarray(segmenter.segment(rgb))
        times.append(1000.0 * (time.perf_counter() - t0))
        if labels.shape != rgb.shape[:2]:
            raise RealDataError(f"{photo.path}: the segmenter gave labels of shape {labels.shape}, not {rgb.shape[:2]}")
        tally.add(photo, labels.astype(np.uint8, copy=False))
    n_fronts = len(tally.recalls)
    covered = sum(r >= COVERED_SHARE for r in tally.recalls)
    with_fronts = [p for p in tally.per_photo if p["fronts"]]
    recall = _share(tally.front_hits, tally.front_px)
    covered_share = _share(covered, n_fronts)
    names = {int(c): c.name.lower() for c in SemanticClass}
    result: dict[str, Any] = {
        "photos": len(photos),
        "fronts": n_fronts,
        "front_recall": recall,
        "front_recall_mean": round(float(np.mean(tally.recalls)), 4) if n_fronts else None,
        "box_iou": _share(tally.box_inter, tally.box_union),
        "box_iou_mean": round(float(np.mean(tally.ious)), 4) if n_fronts else None,
        "fronts_covered": {"count": covered, "total": n_fronts, "share": covered_share},
        "pallet_outside_boxes": {
            "of_pallet_px": _share(tally.pallet_outside, tally.pallet_px),
            "of_photo_px": _share(tally.pallet_outside, tally.photo_px),
        },
        "goals": {
            "front_recall": {"goal": FRONT_RECALL_GOAL, "met": recall is not None and recall >= FRONT_RECALL_GOAL},
            "fronts_covered_share": {
                "goal": FRONTS_COVERED_GOAL,
                "met": covered_share is not None and covered_share >= FRONTS_COVERED_GOAL,
            },
        },
        "photos_all_covered": sum(p["covered"] == p["fronts"] for p in with_fronts),
        "photos_none_covered": sum(p["covered"] == 0 for p in with_fronts),
        "photos_without_fronts": len(photos) - len(with_fronts),
        "fronts_per_photo": _spread([p["fronts"] for p in with_fronts]),
        "front_pixels_labelled": {
            names.get(c, str(c)): _share(int(n), tally.front_px) for c, n in enumerate(tally.labels) if n
        },
        "front_recall_by_height": _by_height(tally.heights),
        "segment_ms": {
            "median": round(float(np.median(times)), 1) if times else None,
            "p95": round(float(np.percentile(times, 95)), 1) if times else None,
        },
    }
    if per_photo:
        result["per_photo"] = tally.per_photo
    return result


class AspectTiles:
    """A `SegmentationService` that segments a photo wider than `aspect` (width / height) as the fewest
    full-height windows of that aspect that cover it, evenly spaced, each pixel labelled by the window
    whose centre is nearest; narrower photos go to `inner` whole. So a 16:9 photo reaches a 4:3 model
    undistorted (two 960 x 720 windows of a 1280 x 720 photo), at twice the model's time."""

    def __init__(self, inner: SegmentationService, aspect: float) -> None:
        self.inner, self.aspect = inner, float(aspect)

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        """Labels (H x W uint8) of an H x W x 3 uint8 RGB image."""
        height, width = rgb.shape[:2]
        win = round(height * self.aspect)
        if win >= width:
            return self.inner.segment(rgb)
        starts = np.round(np.linspace(0, width - win, math.ceil(width / win))).astype(int)
        centres = starts + win / 2
        cuts = [0, *(round((a + b) / 2) for a, b in itertools.pairwise(centres)), width]
        labels = np.empty((height, width), np.uint8)
        for k, x0 in enumerate(starts):
            part = self.inner.segment(np.ascontiguousarray(rgb[:, x0 : x0 + win]))
            labels[:, cuts[k] : cuts[k + 1]] = part[:, cuts[k] - x0 : cuts[k + 1] - x0]
        return labels


def _spread(values: list[int]) -> dict[str, float] | None:
    if not values:
        return None
    return {"min": min(values), "median": float(np.median(values)), "max": max(values)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """DIR, `--split`, `--model`, `--limit`, `--threads`, `--per-photo`, `--fit`."""
    parser.add_argument("dir", metavar="DIR", help="folder of splits, one split's folder, or a COCO .json")
    parser.add_argument("--split", default="val", help="split folder under DIR (default val)")
    parser.add_argument("--model", default=str(DEFAULT_MODEL), help="ONNX segmentation model (default: shipped)")
    parser.add_argument("--limit", type=count(1), help="score only the first N photos")
    parser.add_argument("--threads", type=count(1, 256), help="onnxruntime intra-op threads (default: all cores)")
    parser.add_argument("--per-photo", action="store_true", help="add each photo's fronts and covered count")
    parser.add_argument(
        "--fit",
        choices=("squash", "tiles"),
        default="squash",
        help="squash: the model resizes each photo to its input (default); tiles: windows of the input's "
        "aspect (AspectTiles), so that wide photos are not squashed",
    )


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Load the annotations and the model, score the photos; the figures of the module docstring."""
    from palletpilot.perception.segmentation import OnnxSegmenter

    annotations = annotations_file(args.dir, args.split)
    photos = load_coco(annotations)[: args.limit]
    model = OnnxSegmenter(args.model, threads=args.threads)
    width, height = model.input_size
    segmenter = model if args.fit == "squash" else AspectTiles(model, width / height)
    digest = hashlib.sha256(Path(args.model).read_bytes()).hexdigest()
    sizes: dict[str, int] = {}
    for p in photos:
        sizes[f"{p.width}x{p.height}"] = sizes.get(f"{p.width}x{p.height}", 0) + 1
    head = {
        "annotations": str(annotations),
        "model": f"{args.model} (SHA-256 {digest[:12]}, input {width} x {height})",
        "fit": args.fit,
        "image_sizes": sizes,
    }
    return {**head, **score_photos(photos, segmenter, per_photo=args.per_photo)}

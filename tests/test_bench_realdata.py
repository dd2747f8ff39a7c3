"""`palletpilot bench realdata`: scoring a segmenter on photos with COCO front-face polygons."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from palletpilot.bench.realdata import (
    Front,
    RealDataError,
    annotations_file,
    front_mask,
    load_coco,
    score_photos,
)
from palletpilot.cli import main
from palletpilot.perception.frames import SemanticClass

W, H = 160, 100
FRONT_A = [10, 10, 50, 10, 50, 30, 10, 30]  # x 10..50, y 10..30: 40 x 20 = 800 px
FRONT_B = [100, 50, 140, 50, 140, 60, 100, 60]  # x 100..140, y 50..60: 40 x 10 = 400 px


class KnownLabeller:
    """Drivable everywhere but three rectangles: half of front A and a 60 px patch beside it pallet_empty,
    a quarter of front B pallet_full."""

    def __init__(self) -> None:
        self.calls = 0

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        self.calls += 1
        labels = np.full(rgb.shape[:2], SemanticClass.DRIVABLE, np.uint8)
        labels[10:30, 10:30] = SemanticClass.PALLET_EMPTY  # 400 px of front A
        labels[12:22, 52:58] = SemanticClass.PALLET_EMPTY  # 60 px beside A, inside its grown box
        labels[50:60, 100:110] = SemanticClass.PALLET_FULL  # 100 px of front B
        return labels


def _image(path: Path, width: int = W, height: int = H) -> None:
    img = np.full((height, width, 3), 90, np.uint8)
    cv2.rectangle(img, (10, 10), (50, 30), (40, 120, 200), -1)
    cv2.imwrite(str(path), img)


def _coco(as_text: bool) -> dict:
    def field(value: object) -> object:
        return json.dumps(value) if as_text else value

    def ann(i: int, image_id: int, poly: list[float], bbox: list[float], category: int = 1) -> dict:
        seg = [poly]
        return {"id": i, "image_id": image_id, "category_id": category, "segmentation": field(seg), "bbox": field(bbox)}

    return {
        "images": [
            {"id": 0, "file_name": "JPEGImages/a.jpg", "width": W, "height": H},
            {"id": 1, "file_name": "JPEGImages/b.jpg", "width": W, "height": H},  # no fronts
        ],
        "categories": [{"id": 0, "name": "_background_"}, {"id": 1, "name": "front"}],
        "annotations": [
            ann(0, 0, FRONT_A, [10, 10, 40, 20]),
            ann(1, 0, FRONT_B, [100, 50, 40, 10]),
            ann(2, 0, [0, 0, 5, 0, 5, 5], [0, 0, 5, 5], category=0),  # another category: ignored
        ],
    }


def make_set(root: Path, as_text: bool = False, split: str = "val") -> Path:
    """A tiny COCO folder like ../shared/realdata/pallet_front_rgb/: root/split/JPEGImages, one json."""
    folder = root / split / "JPEGImages"
    folder.mkdir(parents=True)
    _image(folder / "a.jpg")
    _image(folder / "b.jpg")
    (root / split / f"pallet_{split}_annotations.json").write_text(json.dumps(_coco(as_text)))
    return root


def test_front_mask_is_the_pixels_whose_centre_is_inside():
    rect = Front(0, (np.array(FRONT_A, float).reshape(-1, 2),), (10, 10, 40, 20))
    mask = front_mask(rect, (H, W))
    rows, cols = np.nonzero(mask)
    assert mask.sum() == 800 and (rows.min(), rows.max(), cols.min(), cols.max()) == (10, 29, 10, 49)
    triangle = Front(1, (np.array([10, 10, 50, 10, 10, 30], float).reshape(-1, 2),), (10, 10, 40, 20))
    assert front_mask(triangle, (H, W)).sum() == 400


def test_known_labeller_gives_known_figures(tmp_path):
    photos = load_coco(annotations_file(make_set(tmp_path), "val"))
    labeller = KnownLabeller()
    r = score_photos(photos, labeller, per_photo=True)
    assert labeller.calls == 2
    assert (r["photos"], r["fronts"], r["photos_without_fronts"]) == (2, 2, 1)
    assert r["front_recall"] == round(500 / 1200, 4)  # pooled: (400 + 100) / (800 + 400)
    assert r["front_recall_mean"] == 0.375  # (0.5 + 0.25) / 2
    # A's grown box x 0..60, y 5..35 holds A and the 60 px patch: 400 / 860; B's: 100 / 400.
    assert r["box_iou"] == round(500 / 1260, 4)
    assert r["box_iou_mean"] == round((400 / 860 + 0.25) / 2, 4)
    assert r["fronts_covered"] == {"count": 1, "total": 2, "share": 0.5}  # A exactly half: covered
    # photo a's 560 pallet px lie in the grown boxes; photo b has no fronts, so its 560 px are all outside
    assert r["pallet_outside_boxes"] == {"of_pallet_px": 0.5, "of_photo_px": round(560 / (2 * W * H), 4)}
    assert r["goals"]["front_recall"] == {"goal": 0.8, "met": False}
    assert r["goals"]["fronts_covered_share"] == {"goal": 0.9, "met": False}
    assert (r["photos_all_covered"], r["photos_none_covered"]) == (0, 0)
    assert r["front_pixels_labelled"] == {
        "drivable": round(700 / 1200, 4),
        "pallet_empty": round(400 / 1200, 4),
        "pallet_full": round(100 / 1200, 4),
    }
    by_height = r["front_recall_by_height"]
    assert by_height[">=0.2"] == {"fronts": 1, "recall": 0.5} and by_height["0.1-0.2"] == {"fronts": 1, "recall": 0.25}
    assert r["per_photo"] == [
        {"photo": "a.jpg", "fronts": 2, "covered": 1},
        {"photo": "b.jpg", "fronts": 0, "covered": 0},
    ]


def test_json_text_fields_and_every_folder_form_give_the_same_figures(tmp_path):
    lists = score_photos(load_coco(annotations_file(make_set(tmp_path / "l"), "val")), KnownLabeller())
    text_root = make_set(tmp_path / "t", as_text=True)
    for where in (text_root, text_root / "val", text_root / "val" / "pallet_val_annotations.json"):
        photos = load_coco(annotations_file(where, "val"))
        r = score_photos(photos, KnownLabeller())
        assert {k: v for k, v in r.items() if k != "segment_ms"} == {
            k: v for k, v in lists.items() if k != "segment_ms"
        }


def test_a_labeller_that_finds_every_front_meets_the_goals(tmp_path):
    class Perfect:
        def segment(self, rgb: np.ndarray) -> np.ndarray:
            labels = np.zeros(rgb.shape[:2], np.uint8)
            labels[10:30, 10:50] = SemanticClass.PALLET_FULL
            labels[50:60, 100:140] = SemanticClass.PALLET_EMPTY
            return labels

    r = score_photos(load_coco(annotations_file(make_set(tmp_path))), Perfect())
    assert r["front_recall"] == 1.0 and r["box_iou"] == 1.0 and r["fronts_covered"]["share"] == 1.0
    assert r["goals"]["front_recall"]["met"] and r["goals"]["fronts_covered_share"]["met"]
    assert r["photos_all_covered"] == 1


@pytest.mark.parametrize("fit", ["squash", "tiles"])
def test_the_command_runs_the_shipped_model(tmp_path, capsys, fit):
    root = make_set(tmp_path)
    assert main(["bench", "--json", "realdata", str(root), "--limit", "1", "--threads", "1", "--fit", fit]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["photos"] == 1 and r["fronts"] == 2 and r["image_sizes"] == {f"{W}x{H}": 1} and r["fit"] == fit
    assert 0.0 <= r["front_recall"] <= 1.0 and "SHA-256" in r["model"]


def _break(root: Path, how: str) -> tuple[list[str], str]:
    """Damage the set at `root` one way; the extra argv and what the one error line must say."""
    ann = root / "val" / "pallet_val_annotations.json"
    doc = json.loads(ann.read_text())
    if how == "no_folder":
        shutil.rmtree(root)
        return [], f"{root}: no such folder"
    if how == "no_split":
        return ["--split", "test"], "no split folder 'test' (splits here: val)"
    if how == "no_annotations":
        ann.unlink()
        return [], "val: no COCO annotations file"
    if how == "broken_json":
        ann.write_text(ann.read_text()[:-20])
        return [], f"{ann}: not valid JSON: line 1"
    if how == "missing_image":
        (root / "val" / "JPEGImages" / "b.jpg").unlink()
        return [], f"{ann}: images[1]: file_name: {root / 'val' / 'JPEGImages' / 'b.jpg'} not found"
    if how == "not_an_image":
        (root / "val" / "JPEGImages" / "a.jpg").write_bytes(b"not a jpeg")
        return [], f"{ann}: images[0]: file_name: {root / 'val' / 'JPEGImages' / 'a.jpg'} is not an image OpenCV can"
    if how == "truncated_image":
        path = root / "val" / "JPEGImages" / "a.jpg"
        path.write_bytes(path.read_bytes()[:200])
        return [], f"{path}: not a readable image"
    if how == "wrong_size":
        _image(root / "val" / "JPEGImages" / "a.jpg", width=120)
        return [], "a.jpg: 120 x 100 px, its annotation entry says width 160, height 100"
    if how == "outside":
        doc["annotations"][1]["segmentation"] = json.dumps([[100, 50, 170, 50, 170, 60, 100, 60]])
        ann.write_text(json.dumps(doc))
        return [], f"{ann}: annotations[1].segmentation[0]: polygon spans x 100.0..170.0"
    if how == "rle":
        doc["annotations"][0]["segmentation"] = {"counts": "abc", "size": [H, W]}
        ann.write_text(json.dumps(doc))
        return [], f"{ann}: annotations[0].segmentation: an RLE mask; only polygons are supported"
    if how == "bad_text_field":
        doc["annotations"][0]["bbox"] = "[10, 10, 40"
        ann.write_text(json.dumps(doc))
        return [], f"{ann}: annotations[0].bbox: not valid JSON"
    if how == "no_front_category":
        doc["categories"] = [{"id": 1, "name": "pallet"}]
        ann.write_text(json.dumps(doc))
        return [], "categories: expected one category named 'front', found 0"
    assert how == "unknown_image_id"
    doc["annotations"][0]["image_id"] = 7
    ann.write_text(json.dumps(doc))
    return [], f"{ann}: annotations[0]: image_id: 7 is not the id of an entry of images"


BREAKS = (
    "no_folder no_split no_annotations broken_json missing_image not_an_image truncated_image wrong_size outside rle "
    "bad_text_field no_front_category unknown_image_id"
).split()


@pytest.mark.parametrize("how", BREAKS)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, how):
    root = make_set(tmp_path / "set")
    extra, says = _break(root, how)
    assert main(["bench", "realdata", str(root), "--threads", "1", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert says in err
    assert "Traceback" not in err


def test_every_problem_of_a_file_is_listed(tmp_path):
    root = make_set(tmp_path)
    ann = root / "val" / "pallet_val_annotations.json"
    doc = json.loads(ann.read_text())
    doc["annotations"][0]["segmentation"] = [[1, 2, 3]]
    doc["annotations"][1]["bbox"] = [0, 0, 1, 1]
    ann.write_text(json.dumps(doc))
    with pytest.raises(RealDataError) as info:
        load_coco(ann)
    assert [p.split(": ", 1)[1] for p in info.value.problems] == [
        "annotations[0].segmentation[0]: a polygon needs an even number (>= 6) of finite numbers",
        "annotations[1].bbox: [0, 0, 1, 1] does not hold its segmentation (x 100.0..140.0, y 50.0..60.0 px)",
    ]


def test_aspect_tiles_give_a_pointwise_labeller_the_whole_photo_in_windows_of_the_aspect():
    from palletpilot.bench.realdata import AspectTiles

    class Pointwise:
        def __init__(self) -> None:
            self.shapes: list[tuple[int, ...]] = []

        def segment(self, rgb: np.ndarray) -> np.ndarray:
            self.shapes.append(rgb.shape)
            return np.where(rgb[:, :, 0] > 127, SemanticClass.PALLET_EMPTY, SemanticClass.DRIVABLE).astype(np.uint8)

    rgb = np.random.default_rng(4).integers(0, 256, (100, 300, 3), dtype=np.uint8)
    inner = Pointwise()
    labels = AspectTiles(inner, 4 / 3).segment(rgb)
    assert inner.shapes == [(100, 133, 3)] * 3  # ceil(300 / 133) windows of the aspect, full height
    np.testing.assert_array_equal(labels, Pointwise().segment(rgb))  # every column from one window
    narrow = rgb[:, :120]
    np.testing.assert_array_equal(AspectTiles(inner, 4 / 3).segment(narrow), Pointwise().segment(narrow))
    assert inner.shapes[-1] == (100, 120, 3)  # narrower than the aspect: whole

"""`palletpilot segment train`: fine-tuning the shipped model on a user's own labelled PNG frames."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from palletpilot.cli import main
from palletpilot.perception.segmentation import DEFAULT_MODEL, OnnxSegmenter

EXAMPLE = Path(__file__).parent / "data" / "seg_finetune"


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run(argv: list[str]) -> int:
    try:
        return int(main(argv) or 0)
    except SystemExit as exc:
        return int(exc.code or 0)


def test_the_example_has_the_documented_format():
    images = sorted(p for p in EXAMPLE.glob("*.png") if not p.name.endswith("_labels.png"))
    assert len(images) >= 3
    for image in images:
        rgb = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
        lab = cv2.imread(str(image.with_name(f"{image.stem}_labels.png")), cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (480, 640, 3) and lab.shape == (480, 640) and lab.dtype == np.uint8
        values = set(np.unique(lab).tolist())
        assert values <= set(range(10)) | {255} and 255 in values and values & {7, 8}
    assert sum(p.stat().st_size for p in EXAMPLE.iterdir()) < 400_000


def test_two_step_fine_tune_writes_a_fine_tuned_model(tmp_path, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    before = _sha(DEFAULT_MODEL)
    out = tmp_path / "tuned.onnx"
    argv = ["segment", "train", str(EXAMPLE), "--out", str(out), "--steps", "2", "--threads", "1", "--quiet"]
    assert _run(argv) == 0
    assert "wrote" in capsys.readouterr().out
    assert _sha(DEFAULT_MODEL) == before  # the shipped model is never touched
    seg = OnnxSegmenter(out)
    labels = seg.segment(cv2.cvtColor(cv2.imread(str(EXAMPLE / "warehouse_00.png")), cv2.COLOR_BGR2RGB))
    assert labels.shape == (480, 640) and labels.dtype == np.uint8
    import onnx

    meta = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    facts = json.loads(meta["training"])
    assert facts["fine_tuned"] is True and facts["steps"] == 2 and facts["frames"] == 3
    assert facts["init"]["sha256"] == before and facts["init"]["file"] == DEFAULT_MODEL.name
    assert facts["data"] == ["seg_finetune"]


def test_thawed_batch_norms_compute_what_the_imported_model_computes():
    torch = pytest.importorskip("torch")
    from palletpilot.perception.segmentation_data import import_onnx_weights, onnx_training_facts, thaw_batchnorm
    from palletpilot.perception.train_segmentation import CROP, Frames, _batch, build_model

    facts = onnx_training_facts(DEFAULT_MODEL)
    model = build_model(tuple(facts["channels"]), int(facts.get("refine", 0)))
    import_onnx_weights(model, DEFAULT_MODEL)
    model.eval()
    x = torch.randn(1, 3, 96, 128, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        before = model(x)
    frames, rng = Frames([EXAMPLE]), np.random.default_rng(0)
    thaw_batchnorm(model, [_batch(frames, np.arange(len(frames)), CROP, 0.75, rng)[::2] for _ in range(2)])
    assert model.training  # left to train, batch norms included
    norm = next(m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d))
    assert float(norm.running_var.min()) > 0.0 and not torch.allclose(
        norm.running_var, torch.ones_like(norm.running_var)
    )
    model.eval()
    with torch.no_grad():
        after = model(x)
    assert float((after - before).abs().max()) < 1e-4 * float(before.abs().max())


def test_batches_made_by_workers_do_not_depend_on_how_many():
    from palletpilot.perception.training_batches import CROP, BatchSource, Frames

    frames = Frames([EXAMPLE])
    shared: list[Path] = []

    def batches(workers: int) -> list[tuple[np.ndarray, ...]]:
        source = BatchSource(frames, 2, CROP, 0.75, seed=4, rng=np.random.default_rng(4), workers=workers)
        shared.append(Path(source.shared.name))  # the PNG frames, written for the spawned workers to map
        try:
            return [source.next() for _ in range(5)]
        finally:
            source.close()

    one, three = batches(1), batches(3)
    assert shared[0] != shared[1] and not any(folder.exists() for folder in shared)  # removed on close
    for a, b in zip(one, three, strict=True):
        assert all(np.array_equal(u, v) for u, v in zip(a, b, strict=True))
    x, y, tops = one[0]
    assert x.shape == (2, 3, CROP[1], CROP[0]) and x.dtype == np.float32 and y.dtype == np.int64 and tops.shape == (2,)
    assert not all(np.array_equal(one[0][0], other[0]) for other in one[1:])  # each step its own crops


def test_an_added_refinement_stage_starts_from_the_model_and_survives_export(tmp_path):
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from palletpilot.perception.errors import PerceptionError
    from palletpilot.perception.segmentation_data import import_onnx_weights
    from palletpilot.perception.train_segmentation import build_model, export_onnx

    torch.manual_seed(0)
    plain = build_model()
    base = tmp_path / "base.onnx"
    export_onnx(plain, base, {"refine": 0}, log=False)
    x = torch.randn(1, 3, 480, 640, generator=torch.Generator().manual_seed(1))
    before = OnnxSegmenter(base).session.run(None, {"rgb": x.numpy()})[0]

    with pytest.raises(PerceptionError, match="another architecture"):
        import_onnx_weights(build_model(refine=16), base)  # only when told that a stage was added
    refined = build_model(refine=16)
    import_onnx_weights(refined, base, added_tail=True)
    refined.eval()
    with torch.no_grad():
        assert float((refined(x) - torch.from_numpy(before)).abs().max()) < 1e-4
        for p in [*refined.refine.parameters(), *refined.detail.parameters()]:
            p.add_(0.1 * torch.randn_like(p))
        changed = refined(x)
    assert float((changed - torch.from_numpy(before)).abs().max()) > 0.1  # the stage does act

    out = tmp_path / "refined.onnx"
    export_onnx(refined, out, {"refine": 16}, log=False)
    run = OnnxSegmenter(out).session.run(None, {"rgb": x.numpy()})[0]
    assert float(np.abs(run - changed.numpy()).max()) < 1e-3 * float(np.abs(run).max())
    again = build_model(refine=16)
    import_onnx_weights(again, out)
    again.eval()
    with torch.no_grad():
        assert torch.equal(again(x), changed)


def _copy_example(tmp_path: Path) -> Path:
    folder = tmp_path / "frames"
    shutil.copytree(EXAMPLE, folder)
    return folder


def _one_line_error(capsys, exit_code: int, *words: str) -> None:
    err = capsys.readouterr().err.strip()
    assert exit_code == 2
    assert len(err.splitlines()) == 1, err
    for word in words:
        assert word in err


def test_bad_label_values_are_one_line(tmp_path, capsys):
    folder = _copy_example(tmp_path)
    lab = cv2.imread(str(folder / "warehouse_01_labels.png"), cv2.IMREAD_UNCHANGED)
    lab[10:20, 10:20] = 42
    cv2.imwrite(str(folder / "warehouse_01_labels.png"), lab)
    code = _run(["segment", "train", str(folder), "--out", str(tmp_path / "x.onnx"), "--steps", "1"])
    _one_line_error(capsys, code, "warehouse_01_labels.png", "42", "255 (ignore)")
    assert not (tmp_path / "x.onnx").exists()


def test_a_missing_pair_is_one_line(tmp_path, capsys):
    folder = _copy_example(tmp_path)
    (folder / "warehouse_02_labels.png").unlink()
    code = _run(["segment", "train", str(folder), "--out", str(tmp_path / "x.onnx"), "--steps", "1"])
    _one_line_error(capsys, code, "warehouse_02.png", "warehouse_02_labels.png")
    folder2 = _copy_example(tmp_path / "b")
    (folder2 / "warehouse_00.png").unlink()
    code = _run(["segment", "train", str(folder2), "--out", str(tmp_path / "x.onnx"), "--steps", "1"])
    _one_line_error(capsys, code, "warehouse_00_labels.png", "no image")


def test_labels_of_another_size_are_one_line(tmp_path, capsys):
    folder = _copy_example(tmp_path)
    cv2.imwrite(str(folder / "warehouse_00_labels.png"), np.zeros((240, 320), np.uint8))
    code = _run(["segment", "train", str(folder), "--out", str(tmp_path / "x.onnx"), "--steps", "1"])
    _one_line_error(capsys, code, "320 x 240", "640 x 480")


def test_a_model_of_another_architecture_is_refused(tmp_path, capsys):
    pytest.importorskip("torch")
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("rgb", TensorProto.FLOAT, [1, 3, 480, 640])
    y = helper.make_tensor_value_info("logits", TensorProto.FLOAT, [1, 10, 480, 640])
    w = helper.make_tensor("w", TensorProto.FLOAT, [10, 3, 1, 1], np.zeros(30, np.float32).tolist())
    graph = helper.make_graph([helper.make_node("Conv", ["rgb", "w"], ["logits"])], "tiny", [x], [y], [w])
    other = tmp_path / "other.onnx"
    onnx.save(helper.make_model(graph), str(other))
    code = _run(["segment", "train", str(EXAMPLE), "--init", str(other), "--out", str(tmp_path / "x.onnx")])
    _one_line_error(capsys, code, "other.onnx", "another architecture")


def test_without_torch_names_the_train_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch now raises ImportError
    code = _run(["segment", "train", str(EXAMPLE), "--out", str(tmp_path / "x.onnx")])
    _one_line_error(capsys, code, "pip install '.[train]'")

"""Evaluation: the 11-point VOC AP, agreement with faster-coco-eval, COCO and SARD-style VOC sets."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from backend.detectors.yolox import YoloxDetector
from backend.pipeline import Pipeline
from backend.verifiers.attributes import AttributeVerifier
from backend_tools.evaluation import (
    DatasetError,
    EvalImage,
    EvalSet,
    EvalTask,
    average_precision_voc11,
    coco_ap50,
    evaluate,
    load_coco,
    load_sard_voc,
    markdown_table,
)
from behaviors.geometry import Box

A, B = Box(0, 0, 10, 10), Box(50, 50, 10, 10)


def test_ap_perfect_missing_and_false_positives() -> None:
    truth = {1: (A,), 2: (B,)}
    assert average_precision_voc11([(1, 0.9, A), (2, 0.8, B)], truth) == pytest.approx(1.0)
    assert average_precision_voc11([], truth) == 0.0
    # Half the objects found, no false positive: precision 1 up to recall 0.5 -> 6 of 11 points.
    assert average_precision_voc11([(1, 0.9, A)], truth) == pytest.approx(6 / 11)
    # A confident false positive first: precision 1/2 then 2/3 -> mean over 11 points of 2/3.
    ranked = [(1, 0.99, B), (1, 0.9, A), (2, 0.8, B)]
    assert average_precision_voc11(ranked, truth) == pytest.approx(2 / 3)
    # A duplicate of a matched box is a false positive; IoU must exceed 0.5.
    assert average_precision_voc11([(1, 0.9, A), (1, 0.8, A)], {1: (A,)}) == pytest.approx(1.0)
    assert average_precision_voc11([(1, 0.9, Box(5, 0, 10, 10))], {1: (A,)}) == 0.0


def test_coco_library_agrees_on_clear_cases() -> None:
    tasks = [EvalTask("T1", "a", "person"), EvalTask("T2", "b", "person")]
    images = [EvalImage(1, Path("1.jpg"), {"T1": (A,)}), EvalImage(2, Path("2.jpg"), {"T2": (B,)})]
    evalset = EvalSet(tasks, images)
    scores = coco_ap50(evalset, {"T1": [(1, 0.9, A)], "T2": [(1, 0.9, B)]})
    assert scores["T1"] == pytest.approx(1.0) and scores["T2"] == pytest.approx(0.0)
    assert coco_ap50(evalset, {"T1": [], "T2": []}) == {"T1": 0.0, "T2": 0.0}


# One described person per sequence, each alone in view: every other sequence's people are the distractors.
# Named rather than globbed so that new shared sequences (several people in view) do not change what the AP
# assertions below measure.
SINGLE_PERSON_SEQUENCES = ("dtb70_Surfing06", "otb_Crossing", "uav123_person12_1", "uav123_wakeboard7")


def _coco_set(sequences_dir: Path, path: Path, step: int = 25) -> Path:
    """A tiny COCO set from the real sequences: their ground truth and referring.txt as the task."""
    images: list[dict[str, object]] = []
    annotations: list[dict[str, object]] = []
    for seq in (sequences_dir / name for name in SINGLE_PERSON_SEQUENCES):
        referring = (seq / "referring.txt").read_text().strip()
        lines = (seq / "groundtruth.txt").read_text().split()
        for i in range(0, len(lines), step):
            x, y, w, h = (float(v) for v in lines[i].split(","))
            image_id = len(images) + 1
            images.append({"id": image_id, "file_name": f"{seq.name}/frames/{i + 1:06d}.jpg"})
            annotations.append(
                {
                    "id": image_id,
                    "image_id": image_id,
                    "category_id": 1,
                    "bbox": [x, y, w, h],
                    "referring": referring,
                }
            )
    path.write_text(
        json.dumps(
            {"images": images, "annotations": annotations, "categories": [{"id": 1, "name": "person"}]}
        )
    )
    return path


def test_evaluate_on_real_sequences(models_dir: Path, sequences_dir: Path, tmp_path: Path) -> None:
    evalset = load_coco(_coco_set(sequences_dir, tmp_path / "set.json"), sequences_dir)
    # One task per distinct description, whatever sequences the shared data holds.
    prompts = {a["referring"] for a in json.loads((tmp_path / "set.json").read_text())["annotations"]}
    assert {t.prompt for t in evalset.tasks} == prompts and all(t.superset == "person" for t in evalset.tasks)
    detector = YoloxDetector(models_dir / "yolox_nano" / "yolox_nano.onnx", threads=1)
    with ThreadPoolExecutor(4) as pool:
        pipelines = {
            "local:colours": Pipeline(detector, AttributeVerifier(), pool),
            "none": Pipeline(detector, None, pool),
        }
        results = evaluate(evalset, detector, pipelines)
    by_name = {r.verifier: r for r in results}
    crossing = next(t.name for t in evalset.tasks if "crossing" in t.prompt)
    # Every person is a detection for "none", so other sequences' people are false positives for each task;
    # the colour verifier removes some of them and must not lose the target.
    assert by_name["none"].ap[crossing] > 0.2
    assert by_name["local:colours"].ap[crossing] >= by_name["none"].ap[crossing]
    assert by_name["local:colours"].objects > 0 and by_name["none"].objects == 0
    for r in results:
        assert all(0 <= v <= 1 for v in (*r.ap.values(), *r.ap50.values()))
        assert abs(r.mean_ap - r.mean_ap50) < 0.15  # 11-point and 101-point interpolation of the same curve
    table = markdown_table(evalset, results, detector.name)
    print(table)
    task_columns = " | ".join(t.name for t in evalset.tasks)
    assert table.startswith(f"| Verifier | {task_columns} | mAP | AP50 (coco) | t_f [s] | t_obj [s] |")
    assert "the person in dark clothes crossing the street" in table


def test_coco_set_errors_are_named(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(DatasetError, match="bad.json"):
        load_coco(bad, tmp_path)
    plain = tmp_path / "plain.json"
    plain.write_text(
        json.dumps({"images": [], "annotations": [{"image_id": 1, "bbox": [0, 0, 1, 1]}], "categories": []})
    )
    with pytest.raises(DatasetError, match="referring"):
        load_coco(plain, tmp_path)


def test_sard_style_voc_folder(sequences_dir: Path, tmp_path: Path) -> None:
    (tmp_path / "Annotations").mkdir()
    (tmp_path / "JPEGImages").mkdir()
    rows = ["image,xmin,ymin,xmax,ymax,attribute"]
    for i, (seq, index) in enumerate([("otb_Crossing", 1), ("uav123_person12_1", 1)]):
        name = f"img{i}.jpg"
        (tmp_path / "JPEGImages" / name).symlink_to(sequences_dir / seq / "frames" / f"{index:06d}.jpg")
        x, y, w, h = (
            float(v)
            for v in (sequences_dir / seq / "groundtruth.txt").read_text().split()[index - 1].split(",")
        )
        (tmp_path / "Annotations" / f"img{i}.xml").write_text(
            f"<annotation><filename>{name}</filename><object><name>person</name><bndbox><xmin>{x}</xmin>"
            f"<ymin>{y}</ymin><xmax>{x + w}</xmax><ymax>{y + h}</ymax></bndbox></object></annotation>"
        )
        rows.append(
            f"{name},{x},{y},{x + w},{y + h},{'a person in dark clothes' if i == 0 else 'a person in a striped shirt'}"
        )
    (tmp_path / "attributes.csv").write_text("\n".join(rows) + "\n")
    evalset = load_sard_voc(tmp_path, tmp_path / "attributes.csv")
    assert [t.prompt for t in evalset.tasks] == ["a person in dark clothes", "a person in a striped shirt"]
    assert [sorted(img.truth) for img in evalset.images] == [["T1"], ["T2"]]
    with pytest.raises(DatasetError, match="image,xmin"):
        (tmp_path / "broken.csv").write_text("a,b\n1,2\n")
        load_sard_voc(tmp_path, tmp_path / "broken.csv")

"""Per-task Average Precision of detector + verifier, the paper's way (11-point VOC, IoU > 0.5).

A *task* is one description ("the man in the green-and-white striped shirt"); its ground truth is the
boxes of objects matching it. Every task is evaluated on every image of the set, so images of other
tasks supply the negatives the verifier must reject. A candidate counts as a detection of the task
when the verifier says yes (and, with `count_uncertain`, uncertain - the paper's "if in doubt, yes");
its confidence is the detector score. AP50 from faster-coco-eval (COCO's 101-point interpolation) is
reported beside our 11-point AP as a cross-check. t_f is the time per frame (detection + verifying all
its candidates concurrently), t_obj the time per verified object.

Inputs: tracking sequences with a referring.txt each (one task per sequence), a COCO file whose annotations carry `"referring": "text"` and/or `"attributes": ["text", ...]`
(each distinct text is a task, its category the superset), or a SARD-style VOC folder
(`JPEGImages/`, `Annotations/*.xml`) with an attribute CSV `image,xmin,ymin,xmax,ymax,attribute`.
"""

from __future__ import annotations

import csv
import json
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from backend.detectors.interface import SupersetDetector
from backend.pipeline import Pipeline
from backend.supersets import superset_from_prompt
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou

Scored = tuple[int, float, Box]  # image id, confidence, box


@dataclass(frozen=True)
class EvalTask:
    name: str  # short column name, T1, T2, ...
    prompt: str
    superset: str


@dataclass(frozen=True)
class EvalImage:
    image_id: int
    path: Path
    truth: dict[str, tuple[Box, ...]]  # task name -> boxes


@dataclass(frozen=True)
class EvalSet:
    tasks: list[EvalTask]
    images: list[EvalImage]


@dataclass(frozen=True)
class VerifierScores:
    verifier: str
    ap: dict[str, float]  # 11-point VOC, ours
    ap50: dict[str, float]  # faster-coco-eval
    t_f: float
    t_obj: float
    frames: int
    objects: int

    @property
    def mean_ap(self) -> float:
        return float(np.mean(list(self.ap.values()))) if self.ap else 0.0

    @property
    def mean_ap50(self) -> float:
        return float(np.mean(list(self.ap50.values()))) if self.ap50 else 0.0


class DatasetError(ValueError):
    """An evaluation set that cannot be read; the message names the file and the problem."""


def _tasks_from(texts: Iterable[tuple[str, str]]) -> list[EvalTask]:
    tasks: list[EvalTask] = []
    seen: set[str] = set()
    for prompt, category in texts:
        if prompt in seen:
            continue
        seen.add(prompt)
        superset = category or superset_from_prompt(prompt) or ""
        if not superset:
            raise DatasetError(f"task {prompt!r} has no category and names no known class")
        tasks.append(EvalTask(f"T{len(tasks) + 1}", prompt, superset))
    return tasks


def load_coco(coco_file: Path, images_dir: Path) -> EvalSet:
    try:
        data = json.loads(coco_file.read_text())
        categories = {c["id"]: c["name"] for c in data.get("categories", [])}
        annotations = data["annotations"]
        images = data["images"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{coco_file}: not a readable COCO file: {exc}") from exc
    labelled: list[tuple[int, str, str, Box]] = []
    for ann in annotations:
        texts = ([ann["referring"]] if ann.get("referring") else []) + list(ann.get("attributes") or [])
        x, y, w, h = (float(v) for v in ann["bbox"])
        for text in texts:
            labelled.append(
                (ann["image_id"], str(text), categories.get(ann.get("category_id"), ""), Box(x, y, w, h))
            )
    if not labelled:
        raise DatasetError(f"{coco_file}: no annotation carries 'referring' or 'attributes'")
    tasks = _tasks_from((text, category) for _, text, category, _ in labelled)
    by_prompt = {t.prompt: t.name for t in tasks}
    eval_images = []
    for image in images:
        truth: dict[str, list[Box]] = {}
        for image_id, text, _, box in labelled:
            if image_id == image["id"]:
                truth.setdefault(by_prompt[text], []).append(box)
        path = images_dir / image["file_name"]
        if not path.is_file():
            raise DatasetError(f"{coco_file}: image {path} does not exist")
        eval_images.append(EvalImage(int(image["id"]), path, {k: tuple(v) for k, v in truth.items()}))
    return EvalSet(tasks, eval_images)


def load_sequences(sequences_dir: Path, step: int = 5) -> EvalSet:
    """Tracking sequences (frames/, groundtruth.txt, referring.txt) as a set: one task per sequence."""
    folders = sorted(
        p
        for p in sequences_dir.iterdir()
        if (p / "groundtruth.txt").is_file() and (p / "referring.txt").is_file()
    )
    if not folders:
        raise DatasetError(f"{sequences_dir}: no sequence folders with groundtruth.txt and referring.txt")
    tasks: list[EvalTask] = []
    images: list[EvalImage] = []
    for folder in folders:
        prompt = (folder / "referring.txt").read_text().strip()
        superset = superset_from_prompt(prompt)
        if superset is None:
            raise DatasetError(f"{folder}/referring.txt names no known class: {prompt!r}")
        task = EvalTask(f"T{len(tasks) + 1}", prompt, superset)
        tasks.append(task)
        lines = (folder / "groundtruth.txt").read_text().split()
        for index in range(0, len(lines), step):
            values = [float(v) for v in lines[index].split(",")]
            truth: dict[str, tuple[Box, ...]] = {} if any(np.isnan(values)) else {task.name: (Box(*values),)}
            images.append(EvalImage(len(images) + 1, folder / "frames" / f"{index + 1:06d}.jpg", truth))
    return EvalSet(tasks, images)


def load_sard_voc(folder: Path, attribute_file: Path, superset: str = "person") -> EvalSet:
    """A SARD-style VOC folder: JPEGImages/ and Annotations/, plus attribute rows naming the tasks."""
    annotations = sorted((folder / "Annotations").glob("*.xml"))
    if not annotations:
        raise DatasetError(f"{folder}/Annotations: no VOC .xml files")
    names: list[str] = []
    for xml_path in annotations:
        try:
            root = ET.parse(xml_path).getroot()
        except ET.ParseError as exc:
            raise DatasetError(f"{xml_path}: not valid VOC XML: {exc}") from exc
        names.append(root.findtext("filename") or xml_path.with_suffix(".jpg").name)
    rows: list[tuple[str, str, Box]] = []
    try:
        with open(attribute_file, newline="") as f:
            for row in csv.DictReader(f):
                box = Box.from_xyxy(
                    float(row["xmin"]), float(row["ymin"]), float(row["xmax"]), float(row["ymax"])
                )
                rows.append((row["image"], row["attribute"].strip(), box))
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(
            f"{attribute_file}: expected CSV columns image,xmin,ymin,xmax,ymax,attribute: {exc}"
        ) from exc
    tasks = _tasks_from((text, superset) for _, text, _ in rows)
    by_prompt = {t.prompt: t.name for t in tasks}
    images = []
    for image_id, name in enumerate(names, start=1):
        truth: dict[str, list[Box]] = {}
        for image_name, text, box in rows:
            if image_name == name:
                truth.setdefault(by_prompt[text], []).append(box)
        images.append(
            EvalImage(image_id, folder / "JPEGImages" / name, {k: tuple(v) for k, v in truth.items()})
        )
    return EvalSet(tasks, images)


def average_precision_voc11(
    detections: list[Scored], truth: Mapping[int, tuple[Box, ...]], iou_threshold: float = 0.5
) -> float:
    """11-point interpolated AP (PASCAL VOC 2007): mean over recall r in 0, 0.1, ..., 1 of max precision at recall >= r.

    A detection is a true positive when its IoU with a not yet matched ground-truth box exceeds the
    threshold (highest-IoU box first), in order of decreasing confidence.
    """
    total = sum(len(boxes) for boxes in truth.values())
    if total == 0:
        return 0.0
    matched = {image_id: [False] * len(boxes) for image_id, boxes in truth.items()}
    hits = []
    for image_id, _, box in sorted(detections, key=lambda d: -d[1]):
        boxes = truth.get(image_id, ())
        overlaps = [iou(box, t) for t in boxes]
        best = int(np.argmax(overlaps)) if overlaps else -1
        if best >= 0 and overlaps[best] > iou_threshold and not matched[image_id][best]:
            matched[image_id][best] = True
            hits.append(1.0)
        else:
            hits.append(0.0)
    if not hits:
        return 0.0
    tp = np.cumsum(hits)
    recall = tp / total
    precision = tp / np.arange(1, len(hits) + 1)
    return float(
        np.mean([precision[recall >= r].max() if (recall >= r).any() else 0.0 for r in np.linspace(0, 1, 11)])
    )


def _quiet(*_: object) -> None:
    """faster-coco-eval's progress lines would drown the table."""


def coco_ap50(evalset: EvalSet, detections: dict[str, list[Scored]]) -> dict[str, float]:
    """AP at IoU 0.5 per task from faster-coco-eval (tasks as categories)."""
    from faster_coco_eval import COCO, COCOeval_faster

    category = {t.name: i + 1 for i, t in enumerate(evalset.tasks)}
    images: list[dict[str, object]] = []
    annotations: list[dict[str, object]] = []
    for image in evalset.images:
        images.append({"id": image.image_id, "file_name": image.path.name, "width": 1, "height": 1})
        for task_name, boxes in image.truth.items():
            for box in boxes:
                annotations.append(
                    {
                        "id": len(annotations) + 1,
                        "image_id": image.image_id,
                        "category_id": category[task_name],
                        "bbox": list(box.xywh()),
                        "area": box.area,
                        "iscrowd": 0,
                    }
                )
    ground = COCO(
        print_function=_quiet,
        annotation_file={
            "images": images,
            "annotations": annotations,
            "categories": [{"id": i, "name": n} for n, i in category.items()],
        },
    )
    results = [
        {"image_id": image_id, "category_id": category[task], "bbox": list(box.xywh()), "score": score}
        for task, scored in detections.items()
        for image_id, score, box in scored
    ]
    if not results:
        return {t.name: 0.0 for t in evalset.tasks}
    evaluator = COCOeval_faster(ground, ground.loadRes(results), "bbox", print_function=_quiet)
    evaluator.evaluate()
    evaluator.accumulate()
    precision = np.asarray(evaluator.eval["precision"])  # [iou, recall, category, area, max dets]
    iou_index = int(np.argmin(np.abs(np.asarray(evaluator.params.iouThrs) - 0.5)))
    category_ids = list(evaluator.params.catIds)
    scores = {}
    for task in evalset.tasks:
        curve = precision[iou_index, :, category_ids.index(category[task.name]), 0, -1]
        scores[task.name] = float(curve[curve > -1].mean()) if (curve > -1).any() else 0.0
    return scores


def evaluate(
    evalset: EvalSet,
    detector: SupersetDetector,
    pipelines: dict[str, Pipeline],
    count_uncertain: bool = True,
    progress: Callable[[Iterable[EvalImage]], Iterable[EvalImage]] = lambda images: images,
) -> list[VerifierScores]:
    """Scores per verifier (one Pipeline each, sharing the detector's output per image)."""
    accepted = {Verdict.YES, Verdict.UNCERTAIN} if count_uncertain else {Verdict.YES}
    found: dict[str, dict[str, list[Scored]]] = {
        name: {t.name: [] for t in evalset.tasks} for name in pipelines
    }
    frame_times: dict[str, list[float]] = {name: [] for name in pipelines}
    object_times: dict[str, list[float]] = {name: [] for name in pipelines}
    for image in progress(evalset.images):
        frame = cv2.imread(str(image.path))
        if frame is None:
            raise DatasetError(f"{image.path}: cannot read the image")
        detected: dict[str, tuple[list[Detection], float]] = {}
        for task in evalset.tasks:
            if task.superset not in detected:
                start = time.perf_counter()
                first = next(iter(pipelines.values()))
                detected[task.superset] = (first.detect(frame, task.superset), time.perf_counter() - start)
            detections, t_detect = detected[task.superset]
            for name, pipeline in pipelines.items():
                start = time.perf_counter()
                candidates = pipeline.verify(frame, detections, task.prompt, task.superset)
                frame_times[name].append(t_detect + time.perf_counter() - start)
                if pipeline.verifier is not None:
                    object_times[name].extend(c.t_verify for c in candidates)
                found[name][task.name].extend(
                    (image.image_id, c.detection.score, c.detection.box)
                    for c in candidates
                    if c.detection.verdict in accepted
                )
    results = []
    for name in pipelines:
        ap = {}
        for task in evalset.tasks:
            truth = {img.image_id: img.truth.get(task.name, ()) for img in evalset.images}
            ap[task.name] = average_precision_voc11(found[name][task.name], truth)
        results.append(VerifierScores(
            name, ap, coco_ap50(evalset, found[name]), float(np.mean(frame_times[name])) if frame_times[name] else 0.0,
            float(np.mean(object_times[name])) if object_times[name] else 0.0, len(frame_times[name]), len(object_times[name]),
        ))  # fmt: skip
    return results


def markdown_table(evalset: EvalSet, results: list[VerifierScores], detector: str) -> str:
    """The paper's layout: one row per verifier, AP per task, mean, and timings; the tasks listed below."""
    head = ["Verifier", *(t.name for t in evalset.tasks), "mAP", "AP50 (coco)", "t_f [s]", "t_obj [s]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        cells = [
            r.verifier,
            *(f"{100 * r.ap[t.name]:.1f}" for t in evalset.tasks),
            f"{100 * r.mean_ap:.1f}",
            f"{100 * r.mean_ap50:.1f}",
            f"{r.t_f:.3f}",
            f"{r.t_obj:.4f}" if r.objects else "-",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(
        f"AP in %, 11-point VOC, IoU > 0.5; detector {detector}; {len(evalset.images)} images, every task on every image."
    )
    lines.extend(f"- {t.name} ({t.superset}): {t.prompt}" for t in evalset.tasks)
    return "\n".join(lines)

"""The verifier table: the person-model verifier (`local`) beside the box-fraction HSV one (`local-hsv`).

    python -m backend_tools.verifier_eval --sequences ../shared/data/sequences

Both judge the same 50 px margin crops the pipeline makes, of every labelled person in
tests/data/verifier_crops.json. Per attribute (upper garment colour, lower garment colour, posture) every
crop is asked about every colour word ("a person in a red shirt", "... in dark trousers") and every
posture; the truth comes from the labels. A lying person is the same crop turned by 90 degrees (the
dev sequences have nobody lying down). The colour prototypes of the new verifier are calibrated
leave-one-sequence-out: a sequence's crops are judged with prototypes learnt on the other sequences.
Yes/no F1 count `uncertain` as a miss; "F1" is the mean of the yes and the no F1.
`--write-prototypes` stores the prototypes calibrated on all crops (what the verifier ships with).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from backend.crops import margin_crop
from backend.scene import SceneQuery
from backend.supersets import superset_from_prompt
from backend.verifiers.attributes import REGIONS, AttributeVerifier
from backend.verifiers.colour_names import (
    BASIC_SRGB,
    PROTOTYPES_PATH,
    ColourNamer,
    calibrate,
    srgb_to_lab,
    subsample,
    white_gains,
)
from backend.verifiers.person_verifier import Observation, PersonVerifier
from backend_tools.crop_set import LabelledCrop, ObjectCrop, load_crops, load_objects, read_frame
from behaviors.candidate_selection import select_first_acquisition
from behaviors.detection import Verdict
from behaviors.geometry import Box

DEFAULT_CROPS = Path(__file__).resolve().parents[1] / "tests" / "data" / "verifier_crops.json"
COLOURS = (*BASIC_SRGB, "dark")
POSTURE_PROMPTS = {
    "standing": "a person standing",
    "sitting": "a person sitting",
    "lying": "a person lying on the ground",
}
MARGIN_PX = 50  # as the pipeline crops candidates


def has_colour(labels: tuple[str, ...], colour: str) -> bool:
    return colour in labels or (colour == "dark" and "black" in labels)


@dataclass(frozen=True)
class Sample:
    crop: LabelledCrop
    image: np.ndarray  # the margin crop, turned when `lying`
    box: tuple[float, float, float, float]
    lying: bool  # the turned copy: labelled lying


def _turn(
    image: np.ndarray, box: tuple[float, float, float, float]
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    x, y, w, h = box
    return cv2.rotate(image, cv2.ROTATE_90_CLOCKWISE), (image.shape[0] - y - h, x, h, w)


def samples(crops: list[LabelledCrop], sequences_dir: Path) -> list[Sample]:
    out = []
    for crop in crops:
        if not crop.posture:
            continue
        image, inner = margin_crop(read_frame(sequences_dir, crop), Box(*crop.box), MARGIN_PX)
        out.append(Sample(crop, image, inner.xywh(), False))
        turned, box = _turn(image, inner.xywh())
        out.append(Sample(crop, turned, box, True))
    return out


# Descriptions: each dev sequence's referring.txt and a few others a searcher would say, with the truth
# read from the labels.
Truth = Callable[[Sample], bool]
DESCRIPTIONS: list[tuple[str, Truth]] = [
    (
        "the person in the grey-blue striped shirt and dark trousers walking between the man in the red shirt "
        "and the man in the green-and-white striped shirt",
        lambda s: {"gray", "blue"} <= set(s.crop.upper) and has_colour(s.crop.lower, "dark"),
    ),
    ("the man in the green-and-white striped shirt", lambda s: {"green", "white"} <= set(s.crop.upper)),
    ("the person in dark clothes crossing the street", lambda s: has_colour(s.crop.upper, "dark")),
    (
        "the surfer in a black wetsuit riding the wave",
        lambda s: "black" in s.crop.upper and "black" in s.crop.lower,
    ),
    ("the man in the red shirt", lambda s: "red" in s.crop.upper),
    ("a man in a red shirt and blue jeans", lambda s: "red" in s.crop.upper and "blue" in s.crop.lower),
    ("a person in a yellow shirt", lambda s: "yellow" in s.crop.upper),
    ("someone in a white top", lambda s: "white" in s.crop.upper),
    ("a person in black trousers", lambda s: "black" in s.crop.lower),
    ("a person lying on the ground", lambda s: s.lying),
]


@dataclass
class Score:
    tp: int = 0  # yes, truly yes
    fp: int = 0  # yes, truly no
    tn: int = 0  # no, truly no
    fn: int = 0  # no, truly yes
    unsure_pos: int = 0
    unsure_neg: int = 0

    def add(self, verdict: Verdict, truth: bool) -> None:
        if verdict is Verdict.YES:
            self.tp += truth
            self.fp += not truth
        elif verdict is Verdict.NO:
            self.fn += truth
            self.tn += not truth
        else:
            self.unsure_pos += truth
            self.unsure_neg += not truth

    @property
    def total(self) -> int:
        return self.tp + self.fp + self.tn + self.fn + self.unsure_pos + self.unsure_neg

    def yes_pr(self) -> tuple[float, float]:
        positives = self.tp + self.fn + self.unsure_pos
        return self.tp / max(self.tp + self.fp, 1), self.tp / max(positives, 1)

    def no_pr(self) -> tuple[float, float]:
        negatives = self.tn + self.fp + self.unsure_neg
        return self.tn / max(self.tn + self.fn, 1), self.tn / max(negatives, 1)

    @staticmethod
    def _f1(p: float, r: float) -> float:
        return 2 * p * r / max(p + r, 1e-9)

    def f1(self) -> float:
        return (self._f1(*self.yes_pr()) + self._f1(*self.no_pr())) / 2

    def accuracy(self) -> float:
        return (self.tp + self.tn) / max(self.total, 1)

    def answered(self) -> float:
        return (self.total - self.unsure_pos - self.unsure_neg) / max(self.total, 1)


def attribute_questions(sample: Sample) -> list[tuple[str, str, bool]]:
    """(attribute, prompt, truth) asked of one sample."""
    questions = [
        (
            "posture",
            prompt,
            (posture == "lying") == sample.lying and (sample.lying or posture == sample.crop.posture),
        )
        for posture, prompt in POSTURE_PROMPTS.items()
    ]
    if not sample.lying:
        for colour in COLOURS:
            questions.append(
                ("upper colour", f"a person in a {colour} shirt", has_colour(sample.crop.upper, colour))
            )
            questions.append(
                ("lower colour", f"a person in {colour} trousers", has_colour(sample.crop.lower, colour))
            )
    return questions


def evaluate(crops: list[LabelledCrop], sequences_dir: Path) -> dict[str, object]:
    data = samples(crops, sequences_dir)
    new, old = PersonVerifier(), AttributeVerifier()
    observations: list[Observation] = []
    times = []
    for s in data:
        start = time.perf_counter()
        observations.append(new.observe(s.image, s.box))
        times.append(time.perf_counter() - start)
    garments = [
        (s.crop.sequence, labels, obs.regions[part])
        for s, obs in zip(data, observations, strict=True)
        if not s.lying
        for part, labels in (("upper", s.crop.upper), ("lower", s.crop.lower))
        if part in obs.regions
    ]
    namers = {
        seq: ColourNamer(calibrate((labels, lab) for other, labels, lab in garments if other != seq))
        for seq in sorted({s.crop.sequence for s in data})
    }
    attributes: dict[str, dict[str, Score]] = {}
    descriptions: dict[str, dict[str, Score]] = {}
    for s, obs in zip(data, observations, strict=True):

        def hsv(prompt: str, s: Sample = s) -> Verdict:
            return old.verify(s.image, s.box, prompt, "person").verdict

        def person(prompt: str, s: Sample = s, obs: Observation = obs) -> Verdict:
            return new.judge(obs, prompt, "person", namers[s.crop.sequence]).verdict

        answers = {"local-hsv": hsv, "local": person}
        for attribute, prompt, truth in attribute_questions(s):
            for name, answer in answers.items():
                attributes.setdefault(attribute, {}).setdefault(name, Score()).add(answer(prompt), truth)
        for prompt, is_true in DESCRIPTIONS:
            if s.lying and "lying" not in prompt:
                continue
            for name, answer in answers.items():
                descriptions.setdefault(prompt, {}).setdefault(name, Score()).add(answer(prompt), is_true(s))
    upright = [t for t, s in zip(times, data, strict=True) if not s.lying]
    seen = sum(1 for s, o in zip(data, observations, strict=True) if not s.lying and not o.reason)
    return {
        "samples": len(data),
        "persons": len(upright),
        "body_found": seen,
        "attributes": attributes,
        "descriptions": descriptions,
        "ms_per_crop": 1000 * float(np.mean(upright)),
        "ms_per_crop_p90": 1000 * float(np.percentile(upright, 90)),
        "ms_per_turned_crop": 1000 * float(np.mean([t for t, s in zip(times, data, strict=True) if s.lying])),
    }


def _row(label: str, scores: dict[str, Score]) -> str:
    cells = [label]
    for name in ("local-hsv", "local"):
        sc = scores[name]
        (yp, yr), (np_, nr) = sc.yes_pr(), sc.no_pr()
        cells += [
            f"{sc.answered():.0%}",
            f"{sc.accuracy():.0%}",
            f"{yp:.2f}/{yr:.2f}",
            f"{np_:.2f}/{nr:.2f}",
            f"{sc.f1():.2f}",
        ]
    return "| " + " | ".join(cells) + " |"


def report(result: dict[str, object]) -> str:
    head = (
        "| {} | old answered | old accuracy | old yes P/R | old no P/R | old F1 | new answered | new accuracy "
        "| new yes P/R | new no P/R | new F1 |\n|---" + "|---" * 10 + "|"
    )
    lines = [
        f"{result['persons']} labelled persons (+ as many turned 90 degrees as lying); body found on "
        f"{result['body_found']}; new verifier {result['ms_per_crop']:.0f} ms per crop (p90 "
        f"{result['ms_per_crop_p90']:.0f} ms), {result['ms_per_turned_crop']:.0f} ms per turned crop",
        "",
        head.format("attribute"),
    ]
    attributes = result["attributes"]
    assert isinstance(attributes, dict)
    lines += [_row(a, s) for a, s in attributes.items()]
    lines += ["", head.format("description")]
    descriptions = result["descriptions"]
    assert isinstance(descriptions, dict)
    lines += [_row(d, s) for d, s in descriptions.items()]
    return "\n".join(lines)


def timing(crops: list[LabelledCrop], sequences_dir: Path, count: int) -> str:
    """Time per `verify` call (whole verdict: model, garments, colours) of both verifiers, one thread."""
    people = [s for s in samples(crops, sequences_dir) if not s.lying]
    chosen = people[:: max(len(people) // count, 1)][:count]
    prompt = "the person in the grey-blue striped shirt and dark trousers walking"
    lines = [f"{len(chosen)} crops, load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"]
    for name, verifier in (("local-hsv", AttributeVerifier()), ("local", PersonVerifier())):
        verifier.verify(chosen[0].image, chosen[0].box, prompt, "person")  # warm-up (model load)
        times = []
        for s in chosen:
            start = time.perf_counter()
            verifier.verify(s.image, s.box, prompt, "person")
            times.append(1000 * (time.perf_counter() - start))
        lines.append(
            f"{name}: median {np.median(times):.1f} ms, mean {np.mean(times):.1f} ms, "
            f"p90 {np.percentile(times, 90):.1f} ms per crop"
        )
    return "\n".join(lines)


def write_prototypes(crops: list[LabelledCrop], sequences_dir: Path, path: Path) -> None:
    verifier = PersonVerifier()
    garments = []
    for s in samples(crops, sequences_dir):
        if s.lying:
            continue
        obs = verifier.observe(s.image, s.box)
        garments += [
            (labels, obs.regions[part])
            for part, labels in (("upper", s.crop.upper), ("lower", s.crop.lower))
            if part in obs.regions
        ]
    table = {
        "source": "python -m backend_tools.verifier_eval --write-prototypes (tests/data/verifier_crops.json)",
        "calibrated": calibrate(garments),
    }
    path.write_text(json.dumps(table, indent=1) + "\n")


# ---- objects that are not people: colour per class, and where things are ----------------------------

DEFAULT_OBJECTS = DEFAULT_CROPS.with_name("object_crops.json")
KEYFRAME_WIDTH = 640  # as the companion sends keyframes ([backend] max_keyframe_width)


def keyframe(sequences_dir: Path, sequence: str, frame: int) -> tuple[np.ndarray, float]:
    """A frame as flight sends it (downscaled to KEYFRAME_WIDTH and JPEG-encoded) and its scale."""
    from cloudtrack.api_client import encode_keyframe

    image = cv2.imread(str(sequences_dir / sequence / "frames" / f"{frame:06d}.jpg"))
    if image is None:
        raise FileNotFoundError(sequences_dir / sequence / "frames" / f"{frame:06d}.jpg")
    jpeg, scale = encode_keyframe(image, KEYFRAME_WIDTH, 80)
    return np.asarray(cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)), scale


class BoxMiddleVerifier(PersonVerifier):
    """The `local` verifier as it judged objects before issue 30: the middle of the box (background
    included) with the garment rules; people as today."""

    def observe_object(
        self, crop_bgr: np.ndarray, target_box: tuple[float, float, float, float]
    ) -> Observation:
        x, y, w, h = target_box
        top, bottom, left, right = REGIONS["whole"]
        patch = crop_bgr[
            max(int(y + top * h), 0) : max(int(y + bottom * h), 1),
            max(int(x + left * w), 0) : max(int(x + right * w), 1),
        ]
        pixels = patch.reshape(-1, 3)
        if len(pixels) < self.min_region_px:
            return Observation("box too small to judge colours")
        return Observation(regions={"upper": srgb_to_lab(subsample(pixels), white_gains(crop_bgr))})


def object_colours(objects: list[ObjectCrop], sequences_dir: Path) -> dict[str, dict[str, Score]]:
    """Per class (cars by day and at night apart), every labelled object asked every colour word ("the
    red car") by the old and the new verifier, on the 50 px margin crop of the 640 px keyframe."""
    new, old = PersonVerifier(), BoxMiddleVerifier()
    scores: dict[str, dict[str, Score]] = {}
    for crop in objects:
        if not crop.colours:
            continue
        sent, scale = keyframe(sequences_dir, crop.sequence, crop.frame)
        image, inner = margin_crop(sent, Box(*crop.box).scaled(scale, scale), MARGIN_PX)
        seen = {
            "local (box middle)": old.observe_object(image, inner.xywh()),
            "local": new.observe_object(image, inner.xywh()),
        }
        label = crop.kind + (" (night)" if "night" in crop.note else "")
        for colour in COLOURS:
            truth = has_colour(crop.colours, colour)
            for name, observation in seen.items():
                verdict = new.judge(observation, f"the {colour} {crop.kind}", crop.kind).verdict
                for row in (label, "all objects"):
                    scores.setdefault(row, {}).setdefault(name, Score()).add(verdict, truth)
    return scores


def _old_scene(query: SceneQuery) -> SceneQuery:
    """The relations the back-end judged before issue 30: "between" among the others in view, and a
    vehicle the target is in or apart from (containment)."""
    kept = tuple(r for r in query.description.relations if r.kind in ("between", "inside", "outside"))
    return replace(query, description=replace(query.description, relations=kept), size_word="")


def first_choices(
    sequences_dir: Path, models_dir: Path, step_s: float = 1.0
) -> dict[str, dict[str, list[int]]]:
    """Per dev sequence where some keyframe holds two or more of the target's class: on keyframes every
    `step_s` of sequence time where the detector finds the target, how often the search's first choice is
    the target, someone else, or nobody; before issue 30 (box-middle colours, "between" and vehicles only)
    and now. -> {sequence: {"old"|"new": [target, other, none, keyframes]}}."""
    from concurrent.futures import ThreadPoolExecutor

    from backend.config import load_backend_config
    from backend.detectors.factory import build_detector
    from backend.pipeline import Pipeline
    from backend_tools.crop_set import _iou
    from backend_tools.detector_recall import _groundtruth

    # The back-end's pipeline as its configuration builds it (tiled YOLOX), on the weights in `models_dir`.
    detector = build_detector(
        load_backend_config().detector.model_copy(update={"model_dir": str(models_dir)})
    )
    pipeline = Pipeline(detector, PersonVerifier(), ThreadPoolExecutor(max_workers=2))
    old = copy.copy(pipeline)
    old.verifier = BoxMiddleVerifier()
    result: dict[str, dict[str, list[int]]] = {}
    for path in sorted(p for p in sequences_dir.iterdir() if (p / "referring.txt").is_file()):
        referring = (path / "referring.txt").read_text().strip()
        superset = superset_from_prompt(referring) or "person"
        source = json.loads((path / "source.json").read_text()) if (path / "source.json").is_file() else {}
        fps = 10.0 if "10fps" in str(source.get("dataset", "")).lower() else 30.0  # as eval reads them
        ground_truth = _groundtruth(path)
        counts = {"old": [0, 0, 0, 0], "new": [0, 0, 0, 0]}
        crowded = False  # two or more of its kind seen on some keyframe
        for index in range(0, len(ground_truth), max(1, round(step_s * fps))):
            truth = ground_truth[index]
            if truth is None:
                continue
            sent, scale = keyframe(sequences_dir, path.name, index + 1)
            truth = truth.scaled(scale, scale)
            sighting = pipeline.look(sent, superset, prompt=referring)
            crowded = crowded or len(sighting.context) >= 2
            if not any(_iou(d.box.xywh(), truth.xywh()) >= 0.5 for d in sighting.candidates):
                continue
            assert sighting.query is not None
            for name, (runner, query) in {
                "old": (old, _old_scene(sighting.query)),
                "new": (pipeline, sighting.query),
            }.items():
                seen = replace(sighting, query=query)
                found = [
                    c.detection
                    for c in runner.verify(sent, sighting.candidates, referring, superset, sighting=seen)
                ]
                if name == "old":
                    found = [replace(d, singled_out=False) for d in found]
                chosen = select_first_acquisition(found, False)
                slot = 2 if chosen is None else 0 if _iou(chosen.start_box.xywh(), truth.xywh()) >= 0.5 else 1
                counts[name][slot] += 1
                counts[name][3] += 1
        if crowded and counts["new"][3]:
            result[path.name] = counts
    return result


def object_report(colours: dict[str, dict[str, Score]], choices: dict[str, dict[str, list[int]]]) -> str:
    head = (
        "| {} | old answered | old accuracy | old yes P/R | old no P/R | old F1 | new answered | new accuracy "
        "| new yes P/R | new no P/R | new F1 |\n|---" + "|---" * 10 + "|"
    )
    lines = [head.format("object colour")]
    for row, scores in colours.items():
        lines.append(_row(row, {"local-hsv": scores["local (box middle)"], "local": scores["local"]}))
    lines += [
        "",
        "| first choice on keyframes where the target is detected | keyframes | old: target / other / none "
        "| new: target / other / none |",
        "|---|---|---|---|",
    ]
    for name, counts in choices.items():
        o, n = counts["old"], counts["new"]
        lines.append(f"| {name} | {n[3]} | {o[0]} / {o[1]} / {o[2]} | {n[0]} / {n[1]} / {n[2]} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m backend_tools.verifier_eval",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--sequences", type=Path, required=True, help="folder of the dev sequences (frames/)")
    parser.add_argument(
        "--crops",
        type=Path,
        default=DEFAULT_CROPS,
        help="labelled crops (default: tests/data/verifier_crops.json)",
    )
    parser.add_argument("--json", type=Path, help="also write the scores as JSON here")
    parser.add_argument(
        "--objects",
        type=Path,
        nargs="?",
        const=DEFAULT_OBJECTS,
        help="instead of the person table: object colour per class from these labelled objects (default "
        "tests/data/object_crops.json) and the search's first choice on the dev keyframes, old and new "
        "(needs --models)",
    )
    parser.add_argument("--models", type=Path, help="the weights folder (for --objects: the detector)")
    parser.add_argument(
        "--timing",
        type=int,
        metavar="N",
        help="instead of the table: time per crop of both verifiers on N crops",
    )
    parser.add_argument(
        "--write-prototypes",
        action="store_true",
        help=f"calibrate on all crops and write {PROTOTYPES_PATH.name} instead of the table",
    )
    args = parser.parse_args(argv)
    if args.objects is not None:
        if args.models is None:
            parser.error("--objects needs --models (the detector's weights)")
        print(
            object_report(
                object_colours(load_objects(args.objects), args.sequences),
                first_choices(args.sequences, args.models),
            )
        )
        return 0
    crops = load_crops(args.crops)
    if args.timing:
        print(timing(crops, args.sequences, args.timing))
        return 0
    if args.write_prototypes:
        write_prototypes(crops, args.sequences, PROTOTYPES_PATH)
        print(PROTOTYPES_PATH)
        return 0
    result = evaluate(crops, args.sequences)
    print(report(result))
    if args.json:
        plain = {
            k: (
                {a: {n: vars(sc) | {"f1": sc.f1()} for n, sc in s.items()} for a, s in v.items()}
                if isinstance(v, dict)
                else v
            )
            for k, v in result.items()
        }
        args.json.write_text(json.dumps(plain, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

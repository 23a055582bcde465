"""What the whole keyframe says about a candidate (backend.scene, Pipeline.place): the objects a description
names besides the target, where each candidate stands and its size among the others, and the words nothing
judged; then real keyframes of the dev set through the back-end's configured pipeline."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from backend.scene import Reference, judge_scene, judge_size, read_description, unjudged_words
from behaviors.candidate_selection import select_first_acquisition
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou
from cloudtrack.api_client import encode_keyframe
from companion_tools.eval_command import _pipeline
from companion_tools.tracking_eval import load_sequence


@pytest.mark.parametrize(
    ("prompt", "superset", "references", "classes"),
    [
        (
            "the pink ball at the feet of the man in the green hoodie",
            "sports ball",
            {"the man in the green hoodie": ("person", True)},
            ["person"],
        ),
        ("the red boat next to the pier", "boat", {"the pier": ("pier", False)}, ["pier"]),
        ("a man in a red shirt behind the red car", "person", {"the red car": ("car", True)}, ["car"]),
        ("the white car behind the red car", "car", {"the red car": ("car", True)}, []),  # its own kind
        (
            "the wakeboarder being towed to the left of the boat's wake",
            "person",
            {"the boat's wake": ("wake", False), "the boat": ("boat", False)},  # the possessor is named too
            ["wake", "boat"],
        ),
        ("the cyclist in the blue shirt closest to the camera", "person", {}, []),
        (
            "the grey car crossing the zebra stripes",
            "car",
            {"the zebra stripes": ("stripes", False)},
            ["stripes"],
        ),
        ("the woman in the red car", "person", {"the red car": ("car", True)}, ["car"]),
        ("a man with the dog", "person", {"the dog": ("dog", False)}, ["dog"]),
    ],
)
def test_read_description_names_the_other_objects(
    prompt: str, superset: str, references: dict[str, tuple[str, bool]], classes: list[str]
) -> None:
    query = read_description(prompt, superset)
    assert {p: (r.detector_class, r.described) for p, r in query.references.items()} == references
    assert query.detector_classes() == classes


@pytest.mark.parametrize(
    ("own", "superset", "judged", "unjudged"),
    [
        ("the white motorboat", "boat", {"white"}, ("motorboat",)),
        ("the white suv", "car", {"white"}, ("suv",)),
        ("the dark sedan", "car", {"dark"}, ("sedan",)),
        ("the bmx rider in a maroon shirt", "person", {"maroon", "shirt"}, ("bmx rider",)),
        ("the white plastic bag", "bag", {"white"}, ("plastic bag",)),  # a bag is searched as any thing
        ("a man in a red shirt", "person", {"red", "shirt"}, ("man",)),  # neither age nor sex is judged
        ("the person in the grey-blue striped shirt", "person", {"grey-blue", "shirt"}, ("striped",)),
        ("the car", "car", set(), ()),
        ("a truck", "car", set(), ()),  # a class the search covers
    ],
)
def test_unjudged_words_table(own: str, superset: str, judged: set[str], unjudged: tuple[str, ...]) -> None:
    assert unjudged_words(own, superset, judged) == unjudged


def test_size_words_against_the_others_of_its_kind() -> None:
    others = [Box(0, 0, 40, 20), Box(100, 0, 42, 22), Box(200, 0, 38, 20)]
    small, big = Box(300, 0, 20, 10), Box(300, 0, 80, 40)
    assert judge_size("small", small, others)[0] is True and judge_size("small", big, others)[0] is False
    assert judge_size("large", big, others)[0] is True and judge_size("big", small, others)[0] is False
    assert judge_size("small", Box(300, 0, 36, 18), others)[0] is None  # a little smaller: cannot tell
    verdict, note = judge_size("small", small, [])
    assert verdict is None and "no other" in note


def test_judge_scene_ranks_by_every_relation_and_reports_what_it_could_not_judge() -> None:
    query = read_description("the second white llama from the left next to the pier", "animal")
    llamas = [Box(10, 100, 30, 30), Box(60, 100, 30, 30), Box(110, 100, 30, 30), Box(160, 100, 30, 30)]
    # The second llama is brown (the verifier rules it out): the second white one is the third.
    placements = judge_scene(query, llamas, [True, False, True, True], {}, (640.0, 360.0), True)
    assert [p.ok for p in placements] == [False, False, True, False]
    assert placements[2].unjudged == ("next to the pier (the pier: not located)",)
    assert "second from the left: yes" in placements[2].notes
    # A region of the keyframe does not show every llama: the ordinal is not judged there.
    region = judge_scene(query, llamas, [True] * 4, {}, (640.0, 360.0), False)
    assert {p.ok for p in region} == {None} and any("not every one in view" in u for u in region[0].unjudged)


def test_judge_scene_uses_the_located_boxes_of_the_named_object() -> None:
    query = read_description("the pink ball at the feet of the man in the green hoodie", "sports ball")
    balls = [Box(305, 170, 12, 12), Box(505, 170, 12, 12)]
    man, other_man = Box(300, 100, 30, 80), Box(500, 100, 30, 80)
    located = {"the man in the green hoodie": [man]}  # the other man's hoodie is not green
    placements = judge_scene(query, balls, [True, True], located, (640.0, 360.0), True)
    assert [p.ok for p in placements] == [True, False]
    both = {"the man in the green hoodie": [man, other_man]}
    assert [p.ok for p in judge_scene(query, balls, [True, True], both, (640.0, 360.0), True)] == [True, True]
    unlocated = judge_scene(query, balls, [True, True], {}, (640.0, 360.0), True)
    assert [p.ok for p in unlocated] == [None, None] and "not located" in unlocated[0].unjudged[0]


def test_a_lane_is_never_judged() -> None:
    query = read_description("the white suv in the same lane", "car")
    placements = judge_scene(
        query, [Box(0, 0, 10, 10), Box(50, 0, 10, 10)], [True, True], {}, (640.0, 360.0), True
    )
    assert [p.ok for p in placements] == [None, None] and placements[0].unjudged == ("in the same lane",)
    assert query.references == {} or all(isinstance(r, Reference) for r in query.references.values())


# ---- real keyframes, as flight sends them (640 px JPEG) through the back-end's configured pipeline ------


def _first_keyframe(sequences_dir: Path, name: str) -> tuple[np.ndarray, Box, str]:
    seq = load_sequence(sequences_dir / name)
    image = cv2.imread(
        str(
            sequences_dir
            / name
            / "frames"
            / sorted(p.name for p in (sequences_dir / name / "frames").iterdir())[0]
        )
    )
    assert image is not None and seq.ground_truth[0] is not None
    jpeg, scale = encode_keyframe(image, 640, 80)
    sent = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    return sent, seq.ground_truth[0].scaled(scale, scale), seq.referring


def _found(models_dir: Path, sent: np.ndarray, prompt: str, superset: str) -> list[Detection]:
    pipeline = _pipeline(models_dir.resolve(), "local")
    return [c.detection for c in pipeline.run(sent, prompt, superset).candidates]


def test_wakeboard_first_keyframe_chooses_the_towed_person(models_dir: Path, sequences_dir: Path) -> None:
    """uav123_wakeboard7, frame 1: YOLOX finds three "persons", a box around the boat's people first, and
    the boat. The description names nothing the local verifier can check (all "uncertain"), but the boat
    whose wake he rides is named apart from him, which rules its occupants out."""
    sent, truth, prompt = _first_keyframe(sequences_dir, "uav123_wakeboard7")
    found = _found(models_dir, sent, prompt, "person")
    pipeline = _pipeline(models_dir.resolve(), "local")
    plain = pipeline.detect(sent, "person")  # without the prompt: nothing placed
    assert len(found) >= 3 and all(d.verdict is Verdict.UNCERTAIN and not d.judged for d in found)
    assert [d.placement_ok for d in found].count(True) == 1
    assert all(d.label == "person" for d in found)  # the boat is context, not a candidate
    assert {d.placement_ok for d in plain} == {None}
    assert iou(max(found, key=lambda d: d.score).box, truth) < 0.5  # the detector's best is not him
    chosen = select_first_acquisition(found, False)
    assert chosen is not None and iou(chosen.box, truth) >= 0.5
    assert "to the left of the boat's wake (the boat's wake: not located)" in chosen.unjudged


@pytest.mark.parametrize(
    ("name", "superset", "unjudged"),
    [
        ("uav123_bike1", "person", "cyclist"),  # blue shirt and closest to the camera among 7 people
        ("uavdt_S1606", "car", "sedan"),  # dark and first in the queue among 10 cars
    ],
)
def test_first_keyframe_chooses_the_described_object(
    models_dir: Path, sequences_dir: Path, name: str, superset: str, unjudged: str
) -> None:
    sent, truth, prompt = _first_keyframe(sequences_dir, name)
    found = _found(models_dir, sent, prompt, superset)
    assert len(found) >= 5
    chosen = select_first_acquisition(found, False)
    assert chosen is not None and iou(chosen.box, truth) >= 0.5
    assert (
        [d.placement_ok for d in found].count(True) == 1
        and chosen.placement_ok is True
        and chosen.singled_out
    )
    assert unjudged in chosen.unjudged

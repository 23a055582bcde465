"""The local person verifier (`local`): pose model, garments, colour names, posture, the labelled crop set.

Select with `pytest -k verifier`; the whole-crop-set table is marked slow.
"""

from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from backend.config import VerifierConfig, VlmConfig
from backend.crops import margin_crop
from backend.verifiers.attributes import AttributeVerifier
from backend.verifiers.colour_names import BASIC_SRGB, ColourNamer, calibrate, srgb_to_lab
from backend.verifiers.factory import build_verifier
from backend.verifiers.person_model import (
    L_HIP,
    L_SHOULDER,
    R_HIP,
    R_SHOULDER,
    PersonModel,
    PersonModelUnavailable,
)
from backend.verifiers.person_verifier import PersonVerifier, compound_colours, own_description
from backend_tools.crop_set import COLOUR_NAMES, POSTURES, LabelledCrop, load_crops, read_frame
from backend_tools.verifier_eval import DEFAULT_CROPS, evaluate, report
from behaviors.detection import Verdict
from behaviors.geometry import Box

YES, NO, UNC = Verdict.YES, Verdict.NO, Verdict.UNCERTAIN
GROUP = "uav123_group1_1"


@pytest.fixture(scope="module")
def crops() -> list[LabelledCrop]:
    return load_crops(DEFAULT_CROPS)


@pytest.fixture(scope="module")
def verifier() -> PersonVerifier:
    return PersonVerifier()


def _margin(sequences_dir: Path, crop: LabelledCrop) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    image, inner = margin_crop(read_frame(sequences_dir, crop), Box(*crop.box), 50)
    return image, inner.xywh()


def _first(crops: list[LabelledCrop], upper: set[str], sequence: str = GROUP) -> list[LabelledCrop]:
    return [c for c in crops if c.sequence == sequence and set(c.upper) == upper]


def test_verifier_crop_set_is_labelled_and_points_into_real_frames(
    crops: list[LabelledCrop], sequences_dir: Path
) -> None:
    people = [c for c in crops if c.posture]
    assert len(people) >= 200
    assert {c.sequence for c in people} >= {GROUP, "uav123_person12_1", "otb_Crossing", "dtb70_Surfing06"}
    for crop in crops:
        assert set(crop.upper) | set(crop.lower) <= set(COLOUR_NAMES) | {"dark"}
        assert crop.posture in (*POSTURES, "")
        assert bool(crop.posture) == bool(crop.upper) or crop.note  # unlabelled boxes say why
    for crop in crops[::25]:
        height, width = read_frame(sequences_dir, crop).shape[:2]
        x, y, w, h = crop.box
        assert 0 <= x + w / 2 <= width and 0 <= y + h / 2 <= height


def test_verifier_pose_model_finds_the_body_on_a_real_aerial_crop(
    crops: list[LabelledCrop], sequences_dir: Path
) -> None:
    image, box = _margin(sequences_dir, _first(crops, {"gray", "blue", "white"})[0])
    pose = PersonModel().estimate(image, box)
    assert pose.presence > 0.9 and pose.rotation == 0
    shoulders, hips = (
        pose.keypoints[[L_SHOULDER, R_SHOULDER], 1].mean(),
        pose.keypoints[[L_HIP, R_HIP], 1].mean(),
    )
    assert box[1] < shoulders < hips < box[1] + box[3]  # head up, inside the box
    x, y, w, h = (int(v) for v in box)
    inside = pose.mask[y : y + h, x : x + w].mean()
    assert 0.15 < inside < 0.8 and pose.mask.sum() < 1.5 * pose.mask[y : y + h, x : x + w].sum()


def test_verifier_group_dev_case_grey_blue_yes_red_and_green_white_not(
    crops: list[LabelledCrop], sequences_dir: Path, verifier: PersonVerifier
) -> None:
    """The first four labelled crops of each of the three men (frames 1-17 and 1-73)."""
    prompt = (sequences_dir / GROUP / "referring.txt").read_text().strip()
    answers = {}
    for who, upper in (
        ("grey-blue", {"gray", "blue", "white"}),
        ("red", {"red"}),
        ("green-white", {"green", "white"}),
    ):
        answers[who] = [
            verifier.verify(*_margin(sequences_dir, c), prompt, "person", 5) for c in _first(crops, upper)[:4]
        ]
    assert [a.verdict for a in answers["grey-blue"]].count(YES) >= 3, [
        a.justification for a in answers["grey-blue"]
    ]
    assert all(a.verdict is NO for a in answers["red"] + answers["green-white"])
    assert not any(re.search(r"\bred \d", a.justification) for a in answers["red"])  # the other men's shirts
    assert all("blue-gray" in a.justification and "dark" in a.justification for a in answers["grey-blue"])


def test_verifier_interpreters_in_parallel_answer_as_one_does(
    crops: list[LabelledCrop], sequences_dir: Path
) -> None:
    """`[verifier] local_instances`: candidates judged at once, each as a lone interpreter judges it."""
    cases = [_margin(sequences_dir, c) for c in crops[:6]]
    alone = [PersonModel().estimate(image, box) for image, box in cases]
    pooled = PersonModel(instances=2)
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda case: pooled.estimate(*case), cases))
    assert [p.presence for p in together] == [p.presence for p in alone]
    assert all(np.array_equal(a.keypoints, b.keypoints) for a, b in zip(alone, together, strict=True))


def test_verifier_is_deterministic_and_names_what_it_saw(
    crops: list[LabelledCrop], sequences_dir: Path, verifier: PersonVerifier
) -> None:
    image, box = _margin(sequences_dir, _first(crops, {"red"})[0])
    first = verifier.verify(image, box, "a man in a red shirt", "person")
    again = PersonVerifier().verify(image.copy(), box, "a man in a red shirt", "person")
    assert first == again and first.verdict is YES and first.verifier == "local:person"
    assert verifier.verify(image, box, "a man in a green shirt", "person").verdict is NO


def test_verifier_says_uncertain_when_it_cannot_see_the_person(
    crops: list[LabelledCrop], sequences_dir: Path, verifier: PersonVerifier
) -> None:
    image, box = _margin(sequences_dir, _first(crops, {"red"})[0])
    tiny = cv2.resize(image, None, fx=0.1, fy=0.1, interpolation=cv2.INTER_AREA)  # a 12 px person
    answer = verifier.verify(tiny, tuple(v * 0.1 for v in box), "a man in a green shirt", "person")  # type: ignore[arg-type]
    assert answer.verdict is UNC
    ground = np.full((200, 200, 3), (120, 130, 140), np.uint8)  # nobody there
    blank = verifier.verify(ground, (80, 50, 40, 100), "a man in a green shirt lying on the ground", "person")
    assert blank.verdict is UNC and "no body found" in blank.justification
    assert answer.judged and blank.judged  # it could judge the description, not these pixels
    unnamed = verifier.verify(image, box, "the injured man", "person")  # nothing visible named
    assert unnamed.verdict is UNC and not unnamed.judged


def test_verifier_posture_from_keypoints_on_a_turned_crop(
    crops: list[LabelledCrop], sequences_dir: Path, verifier: PersonVerifier
) -> None:
    image, box = _margin(sequences_dir, _first(crops, {"green", "white"}, "uav123_person12_1")[0])
    assert verifier.verify(image, box, "a man walking", "person").verdict is YES
    assert verifier.verify(image, box, "a man lying on the ground", "person").verdict is NO
    lying = cv2.rotate(image, cv2.ROTATE_90_CLOCKWISE)  # the same body on the ground, seen from above
    x, y, w, h = box
    turned = (image.shape[0] - y - h, x, h, w)
    answer = verifier.verify(lying, turned, "a man lying on the ground", "person")
    assert answer.verdict is YES and "torso" in answer.justification
    assert verifier.verify(lying, turned, "a man standing", "person").verdict is NO


def test_verifier_reads_only_the_targets_own_description() -> None:
    prompt = "the person in the grey-blue striped shirt walking between the man in the red shirt and a woman"
    assert own_description(prompt) == "the person in the grey-blue striped shirt walking"
    assert own_description("a surfer in a black wetsuit") == "a surfer in a black wetsuit"
    assert compound_colours("a grey-blue shirt and green-and-white shorts") == [{"gray", "blue"}]


def test_verifier_colour_names_in_lab() -> None:
    namer = ColourNamer()
    for name, rgb in BASIC_SRGB.items():
        assert namer.shares(srgb_to_lab(np.array([rgb[::-1]], np.uint8)))[name] == 1.0
    maroon = srgb_to_lab(np.full((10, 3), (30, 20, 70), np.uint8))  # BGR: dark red in shade
    assert namer.shares(maroon)["red"] == 1.0 and namer.shares(maroon)["dark"] == 1.0
    teal = srgb_to_lab(np.full((10, 3), (110, 120, 100), np.uint8))  # a green stripe gone grey in the haze
    assert namer.shares(teal)["gray"] == 1.0
    assert ColourNamer(calibrate([(("green",), teal)])).shares(teal)["green"] == 1.0
    assert (
        calibrate([(("red",), srgb_to_lab(np.full((10, 3), (128, 128, 128), np.uint8)))]) == {}
    )  # keeps its hue
    # A striped garment gives each of its colours the pixels nearest to it.
    stripes = np.concatenate([teal, srgb_to_lab(np.full((10, 3), (235, 235, 235), np.uint8))])
    table = calibrate([(("green", "white"), stripes)])
    assert set(table) == {"green", "white"} and table["white"][0][0] > 90 > 60 > table["green"][0][0]


def test_verifier_objects_other_than_people_use_the_box(
    sequences_dir: Path, verifier: PersonVerifier
) -> None:
    crop = LabelledCrop("vot2015_bag", 1, (292, 125, 150, 140), "target")
    image, box = _margin(sequences_dir, crop)
    assert verifier.verify(image, box, "the white plastic bag", "bag").verdict is YES
    assert verifier.verify(image, box, "a red bag", "bag").verdict is NO


def test_verifier_factory_local_is_the_person_model_and_hsv_stays(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    local = build_verifier(VerifierConfig(kind="local"), VlmConfig())
    assert isinstance(local, PersonVerifier)
    assert isinstance(build_verifier(VerifierConfig(kind="local-hsv"), VlmConfig()), AttributeVerifier)
    monkeypatch.setenv("CLOUDTRACK_PERSON_MODELS", str(tmp_path))
    with pytest.raises(PersonModelUnavailable, match="person_model install"):
        build_verifier(VerifierConfig(kind="local"), VlmConfig())


@pytest.mark.slow
def test_verifier_table_new_ahead_of_hsv_on_every_attribute(
    crops: list[LabelledCrop], sequences_dir: Path
) -> None:
    result = evaluate(crops, sequences_dir)
    print(report(result))
    attributes = result["attributes"]
    assert isinstance(attributes, dict) and set(attributes) == {"posture", "upper colour", "lower colour"}
    for attribute, scores in attributes.items():
        assert scores["local"].f1() > scores["local-hsv"].f1(), attribute
    assert int(result["body_found"]) >= 0.8 * int(result["persons"])  # type: ignore[call-overload]


def test_colour_namer_remembers_a_region_boundedly_and_hands_out_copies(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from backend.verifiers import colour_names

    monkeypatch.setattr(colour_names, "SHARES_CACHE", 2)
    namer = ColourNamer()
    calls: list[int] = []
    name_pixels = namer._name_pixels
    monkeypatch.setattr(namer, "_name_pixels", lambda lab: calls.append(len(lab)) or name_pixels(lab))
    red = srgb_to_lab(np.full((10, 3), (35, 30, 200), np.uint8))
    first = namer.shares(red)
    first["red"] = 0.0  # the caller's copy, not the remembered one
    assert namer.shares(red)["red"] == 1.0 and calls == [10]
    assert namer.shares(red[:5])["red"] == 1.0 and calls == [10, 5]  # same pixels, another region
    namer.shares(
        srgb_to_lab(np.full((10, 3), (200, 30, 35), np.uint8))
    )  # blue: the least recent (ten red) goes
    assert namer.shares(red[:5])["red"] == 1.0 and len(calls) == 3
    assert namer.shares(red)["red"] == 1.0 and len(calls) == 4

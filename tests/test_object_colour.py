"""The colour of any object (backend.verifiers.person_verifier: object_mask, object_colour) on the labelled
objects of the dev set (tests/data/object_crops.json), and the verifier table's object rows."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from backend.crops import margin_crop
from backend.verifiers.person_verifier import PersonVerifier, object_colour, object_mask
from backend_tools.crop_set import ObjectCrop, load_objects
from backend_tools.verifier_eval import (
    DEFAULT_OBJECTS,
    first_choices,
    keyframe,
    object_colours,
    object_report,
)
from behaviors.detection import Verdict
from behaviors.geometry import Box

YES, NO, UNSURE = Verdict.YES, Verdict.NO, Verdict.UNCERTAIN


@pytest.fixture(scope="module")
def objects() -> list[ObjectCrop]:
    return load_objects(DEFAULT_OBJECTS)


@pytest.fixture(scope="module")
def verifier() -> PersonVerifier:
    return PersonVerifier()


def test_object_set_is_labelled_and_points_into_real_frames(
    objects: list[ObjectCrop], sequences_dir: Path
) -> None:
    assert len({o.key for o in objects}) == len(objects) >= 150
    labelled = [o for o in objects if o.colours]
    assert len(labelled) >= 100 and {o.kind for o in labelled} == {"car", "boat", "bag"}
    assert all(o.note for o in objects if not o.colours)  # why a box is left out
    for o in objects[:: max(1, len(objects) // 12)]:
        image = cv2.imread(str(sequences_dir / o.sequence / "frames" / f"{o.frame:06d}.jpg"))
        assert image is not None
        x, y, w, h = o.box
        assert 0 <= x < image.shape[1] and 0 <= y < image.shape[0] and w > 0 and h > 0


def test_object_mask_keeps_the_object_and_leaves_the_road() -> None:
    rng = np.random.default_rng(1)
    road = np.clip(rng.normal(90, 6, (120, 140, 3)), 0, 255).astype(np.uint8)
    road[50:70, 50:90] = (235, 235, 240)  # a white car, 40 x 20
    box = (46.0, 46.0, 48.0, 28.0)  # the detector's box, some road at its edges
    mask = object_mask(road, box)
    car = np.zeros(mask.shape, bool)
    car[50:70, 50:90] = True
    assert (mask & car).sum() >= 0.9 * car.sum() and (mask & ~car).sum() <= 0.1 * car.sum()
    assert not mask[:46].any() and not mask[:, :46].any()  # never outside the box
    assert (object_mask(road, box) == mask).all()  # deterministic
    flat = np.full((60, 60, 3), 90, np.uint8)  # nothing to tell apart: the box's middle instead
    middle = object_mask(flat, (20.0, 20.0, 20.0, 20.0))
    assert 0 < middle.sum() < 400 and middle[30, 30]


@pytest.mark.parametrize(
    ("shares", "named", "verdict"),
    [
        ({"white": 0.5, "gray": 0.3, "black": 0.2}, "white", YES),  # a white car, its glass black
        ({"black": 0.65, "white": 0.2, "gray": 0.15}, "white", NO),  # a black car's highlights
        ({"gray": 0.5, "white": 0.3, "black": 0.2}, "white", UNSURE),  # white paint in shade reads grey
        ({"gray": 0.5, "white": 0.3, "black": 0.2}, "gray", YES),
        ({"blue": 0.45, "black": 0.35, "white": 0.2}, "blue", YES),
        ({"blue": 0.45, "black": 0.35, "white": 0.2}, "red", NO),
        ({"white": 0.7, "gray": 0.2, "blue": 0.1}, "blue", NO),  # a tint is not the object's colour
    ],
)
def test_object_colour_is_its_dominant_colour(shares: dict[str, float], named: str, verdict: Verdict) -> None:
    assert object_colour(shares | {"dark": 0.0}, {named}, {named}, 0.2, 0.05)[0] is verdict


def test_object_dark_keeps_its_lightness_rule() -> None:
    assert object_colour({"black": 0.7, "dark": 0.8}, {"dark"}, {"dark"}, 0.2, 0.05)[0] is YES
    assert object_colour({"white": 0.7, "dark": 0.1}, {"dark"}, {"dark"}, 0.2, 0.05)[0] is NO


@pytest.mark.parametrize(
    ("sequence", "frame", "box", "prompt", "kind", "verdict"),
    [
        ("uavdt_S1606", 1, (248, 182, 53, 27), "the dark sedan", "car", YES),  # the described target
        ("uavdt_S1606", 1, (248, 182, 53, 27), "a white car", "car", NO),
        ("uav123_boat5", 1, (541, 296, 188, 130), "the white motorboat", "boat", YES),
        ("uav123_boat5", 1, (541, 296, 188, 130), "a red boat", "boat", NO),
    ],
)
def test_object_colour_on_real_keyframes(
    verifier: PersonVerifier,
    sequences_dir: Path,
    sequence: str,
    frame: int,
    box: tuple[int, int, int, int],
    prompt: str,
    kind: str,
    verdict: Verdict,
) -> None:
    sent, scale = keyframe(sequences_dir, sequence, frame)
    crop, inner = margin_crop(sent, Box(*box).scaled(scale, scale), 50)
    answer = verifier.verify(crop, inner.xywh(), prompt, kind)
    assert answer.verdict is verdict, answer.justification
    assert "of the object (most:" in answer.justification
    unjudged = {"the dark sedan": ("sedan",), "the white motorboat": ("motorboat",)}.get(prompt, ())
    assert answer.unjudged == unjudged


@pytest.mark.slow
def test_object_table_new_ahead_of_the_box_middle_and_first_choices_no_worse(
    objects: list[ObjectCrop], sequences_dir: Path, models_dir: Path
) -> None:
    """The verifier table's object rows (`python -m backend_tools.verifier_eval --objects`, about 3 min
    here): colour F1 per class above the box-middle verifier's, and the first choice on the dev keyframes
    on the target at least as often as before, on the two dev queues of cars always."""
    colours = object_colours(objects, sequences_dir)
    choices = first_choices(sequences_dir, models_dir)
    print(object_report(colours, choices))
    for row, scores in colours.items():
        assert scores["local"].f1() >= scores["local (box middle)"].f1(), row
    assert sum(c["new"][0] for c in choices.values()) > sum(c["old"][0] for c in choices.values())
    assert choices["uavdt_S1606"]["new"][0] == choices["uavdt_S1606"]["new"][3]

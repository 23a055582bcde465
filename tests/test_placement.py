"""Where a description places the target relative to a vehicle it names (backend.placement), and its use
in the first choice: the wakeboarder, not the people in the boat that tows him."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from backend.placement import NamedVehicle, inside, named_vehicles, placement_ok
from behaviors.candidate_selection import select_first_acquisition
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou
from cloudtrack.api_client import encode_keyframe
from companion_tools.eval_command import _pipeline
from companion_tools.tracking_eval import load_sequence

BOAT_APART = NamedVehicle("boat", holds_target=False)
CAR_HOLDS = NamedVehicle("car", holds_target=True)


@pytest.mark.parametrize(
    ("prompt", "superset", "named"),
    [
        ("the wakeboarder being towed to the left of the boat's wake", "person", [BOAT_APART]),
        ("a swimmer beside the canoe", "person", [BOAT_APART]),  # a canoe is a boat
        ("the person in the water near the kayak", "person", [BOAT_APART]),  # nearest preposition decides
        ("a man who fell off the boat", "person", [BOAT_APART]),
        ("the man in the green shirt next to the car", "person", [NamedVehicle("car", False)]),
        ("the woman in the red car", "person", [CAR_HOLDS]),
        ("the man on the deck of the boat", "person", [NamedVehicle("boat", True)]),  # "of" decides nothing
        ("a dog in a car", "dog", [CAR_HOLDS]),
        ("the red car next to the bus", "car", [NamedVehicle("bus", False)]),
        ("waving from the boat", "person", []),  # "from" reads both ways (waving from, fell from)
        ("the boat behind the jet ski", "boat", []),  # the target's own class is no context
        ("the cyclist riding a bike", "person", []),  # a rider's box is not inside a bicycle's
        ("the man in the green-and-white striped shirt", "person", []),
        ("the white plastic bag on the ground", "bag", []),
        ("the driver of the truck", "person", []),  # no preposition that says
        ("a life buoy next to a boat", "life buoy", [BOAT_APART]),  # an open-vocabulary target
    ],
)
def test_named_vehicles_table(prompt: str, superset: str, named: list[NamedVehicle]) -> None:
    assert list(named_vehicles(prompt, superset)) == named


BOAT = Box(627, 422, 144, 197)


@pytest.mark.parametrize(
    ("box", "expected"),
    [
        (Box(686, 482, 43, 104), True),  # an occupant
        (Box(633, 401, 129, 198), True),  # a box around the boat's people: 89 % inside
        (Box(621, 300, 14, 35), False),  # the wakeboarder behind it
        (Box(600, 500, 40, 100), False),  # half over the side
        (Box(700, 500, 0, 10), False),  # empty
    ],
)
def test_inside_a_vehicle_table(box: Box, expected: bool) -> None:
    assert inside(box, BOAT) is expected


def test_placement_ok_checks_only_vehicles_in_view() -> None:
    occupant, towed = Box(686, 482, 43, 104), Box(621, 300, 14, 35)
    seen = [("boat", BOAT), ("car", Box(0, 0, 50, 30))]
    assert placement_ok(occupant, [BOAT_APART], seen) is False
    assert placement_ok(towed, [BOAT_APART], seen) is True
    assert placement_ok(occupant, [NamedVehicle("boat", True)], seen) is True
    assert placement_ok(towed, [CAR_HOLDS], seen) is False  # outside every car in view
    assert placement_ok(towed, [NamedVehicle("bus", False)], seen) is None  # no bus in view: unchecked
    assert placement_ok(towed, [], seen) is None


def test_first_choice_passes_over_candidates_placed_against_the_description() -> None:
    occupant = Detection(Box(0, 0, 10, 20), 0.9, verdict=Verdict.UNCERTAIN, judged=False, placement_ok=False)
    towed = Detection(Box(50, 0, 10, 20), 0.4, verdict=Verdict.UNCERTAIN, judged=False, placement_ok=True)
    unseen = Detection(Box(90, 0, 10, 20), 0.5, verdict=Verdict.UNCERTAIN, judged=False)
    assert select_first_acquisition([occupant, towed], False, None) is towed
    assert select_first_acquisition([occupant, unseen], False, None) is unseen  # unchecked beats contradicted
    assert select_first_acquisition([occupant], False, None) is occupant  # ranks, never rejects
    yes = Detection(Box(0, 0, 10, 20), 0.3, verdict=Verdict.YES, placement_ok=False)
    assert select_first_acquisition([yes, towed], False, None) is yes  # the verdict comes first


def test_wakeboard_first_keyframe_chooses_the_towed_person(models_dir: Path, sequences_dir: Path) -> None:
    """uav123_wakeboard7, frame 1 as flight sends it (640 px JPEG) through the back-end's configured
    pipeline: YOLOX finds three "persons", a box around the boat's people first, and the boat. The
    description names nothing the local verifier can check (all "uncertain"), but the boat it names apart
    from the target rules its occupants out."""
    seq = load_sequence(sequences_dir / "uav123_wakeboard7")
    image = cv2.imread(str(sequences_dir / "uav123_wakeboard7" / "frames" / "000001.jpg"))
    assert image is not None and seq.ground_truth[0] is not None
    jpeg, scale = encode_keyframe(image, 640, 80)
    sent = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    pipeline = _pipeline(models_dir.resolve(), "local")
    found = [c.detection for c in pipeline.run(sent, seq.referring, "person").candidates]
    plain = pipeline.detect(sent, "person")  # without the prompt: nothing placed
    truth = seq.ground_truth[0].scaled(scale, scale)
    assert len(found) >= 3 and all(d.verdict is Verdict.UNCERTAIN and not d.judged for d in found)
    assert [d.placement_ok for d in found].count(True) == 1
    assert all(d.label == "person" for d in found)  # the boat is context, not a candidate
    assert {d.placement_ok for d in plain} == {None}
    assert iou(max(found, key=lambda d: d.score).box, truth) < 0.5  # the detector's best is not him
    chosen = select_first_acquisition(found, False, None)
    assert chosen is not None and iou(chosen.box, truth) >= 0.5

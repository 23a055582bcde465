"""Prompt to track (issue 12): reading the description, the verifier's verdict and box per candidate, the
first candidate chosen on real keyframes of uav123_group1_1, and the ceiling `eval --init prompt` prints.

Select with `pytest -k prompt` (about 12 s: the test over every keyframe of uav123_group1_1 takes 8).
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from backend.detectors.yolox import YoloxDetector
from backend.pipeline import Pipeline, refined_box
from backend.verifiers.attributes import ColourClaim, colour_claims
from backend.verifiers.colour_names import BASIC_SRGB, ColourNamer, srgb_to_lab
from backend.verifiers.person_verifier import (
    Observation,
    PersonVerifier,
    compound_colours,
    own_description,
    patterned_regions,
)
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou
from cloudtrack.model_store import require
from companion_tools.eval_command import _print_acquisition
from companion_tools.tracking_eval import (
    AcquisitionKeyframe,
    SequenceResult,
    acquisition_ceiling,
    first_candidate,
    load_sequence,
)

GROUP = "uav123_group1_1"
YES, NO, UNC = Verdict.YES, Verdict.NO, Verdict.UNCERTAIN


# --- reading the description ------------------------------------------------------------------------

GROUP_PROMPT = (
    "the person in the grey-blue striped shirt and dark trousers walking between the man in the red shirt "
    "and the man in the green-and-white striped shirt"
)


def _up(colour: str) -> ColourClaim:
    return ColourClaim(colour, "upper")


def _low(colour: str) -> ColourClaim:
    return ColourClaim(colour, "lower")


@pytest.mark.parametrize(
    ("prompt", "claims", "compounds"),
    [
        # The relation's people are not the target: their shirts are not judged; "striped" is a pattern.
        (GROUP_PROMPT, [_up("gray"), _up("blue"), _low("dark")], [{"gray", "blue"}]),
        ("the man in the green-and-white striped shirt", [_up("green"), _up("white")], []),
        (
            "a woman in a blue-green jacket next to a red car",
            [_up("green"), _up("blue")],
            [{"green", "blue"}],
        ),
        ("a man in a navy hoodie with the dog in a brown coat", [_up("blue")], []),
        ("a person in a checked shirt behind the white van", [], []),
        ("a hiker in a grey jacket and black trousers", [_up("gray"), _low("black")], []),
        ("the surfer in a black wetsuit riding the wave", [ColourClaim("black", "whole")], []),
        ("someone in dark clothes", [ColourClaim("dark", "whole")], []),
    ],
)
def test_prompt_words_table(prompt: str, claims: list[ColourClaim], compounds: list[set[str]]) -> None:
    own = own_description(prompt)
    assert sorted(colour_claims(own), key=repr) == sorted(claims, key=repr)
    assert compound_colours(own) == compounds


@pytest.mark.parametrize(
    ("prompt", "regions"),
    [
        ("the person in the grey-blue striped shirt and dark trousers", {"upper"}),
        ("a man in a checked jacket and plaid shorts", {"upper", "lower"}),
        ("a woman in a floral dress", {"whole"}),
        ("a man in a red shirt", set()),
    ],
)
def test_prompt_pattern_words_table(prompt: str, regions: set[str]) -> None:
    assert patterned_regions(prompt) == regions


# --- verdict per garment: a colour that only tints a garment of another colour is not that colour -----


def _pixels(parts: dict[str, float], count: int = 400) -> np.ndarray:
    """Lab pixels of a garment made of basic colours in the given shares."""
    rows: list[tuple[int, int, int]] = []
    for name, share in parts.items():
        rows += [BASIC_SRGB[name][::-1]] * round(share * count)
    return srgb_to_lab(np.array(rows, np.uint8))


def _judge(upper: dict[str, float], prompt: str, lower: dict[str, float] | None = None) -> Verdict:
    regions = {"upper": _pixels(upper)}
    if lower is not None:
        regions["lower"] = _pixels(lower)
    observation = Observation(regions=regions, posture="standing")
    return PersonVerifier.judge(_bare_verifier(), observation, prompt).verdict


def _bare_verifier() -> PersonVerifier:
    verifier = PersonVerifier.__new__(PersonVerifier)  # judge() needs no body model
    verifier.namer = ColourNamer()  # the basic prototypes: the pixels above are their centres
    verifier.present_share, verifier.absent_share = 0.2, 0.05
    verifier.name = "local:person"
    return verifier


@pytest.mark.parametrize(
    ("upper", "prompt", "verdict"),
    [
        # grey-blue stripes on white: the named colours are most of it
        ({"gray": 0.25, "blue": 0.3, "white": 0.45}, "a man in a grey-blue striped shirt", YES),
        # a red shirt with grey shade in its folds is not grey-blue (the named colours under half of red)
        ({"red": 0.7, "gray": 0.22, "black": 0.08}, "a man in a grey-blue shirt", NO),
        ({"white": 0.6, "blue": 0.2, "green": 0.2}, "a man in a blue shirt", NO),
        # ...but a striped one may be mostly its unnamed stripes: the pattern is not judged, only allowed for
        ({"white": 0.6, "blue": 0.2, "green": 0.2}, "a man in a blue striped shirt", YES),
        ({"white": 0.6, "blue": 0.2, "green": 0.2}, "a man in a blue-and-white striped shirt", YES),
        # both named colours of a two-colour shirt count together against a third
        ({"white": 0.5, "green": 0.2, "gray": 0.3}, "the man in the green-and-white striped shirt", YES),
        # shade (black) is never "another colour"
        ({"blue": 0.3, "black": 0.7}, "a man in a blue shirt", YES),
        # too little of the named colour, nothing else dominant: uncertain, not a guess
        ({"blue": 0.1, "white": 0.3, "gray": 0.3, "black": 0.3}, "a man in a blue shirt", UNC),
    ],
)
def test_prompt_verdict_when_another_colour_outweighs_the_named_one(
    upper: dict[str, float], prompt: str, verdict: Verdict
) -> None:
    assert _judge(upper, prompt) is verdict


def test_prompt_relation_garments_are_not_the_targets() -> None:
    """The described man's shirt is grey-blue; the red and green-and-white shirts belong to the others."""
    grey_blue = {"gray": 0.3, "blue": 0.35, "white": 0.35}
    assert _judge(grey_blue, GROUP_PROMPT, lower={"black": 1.0}) is YES
    assert _judge({"red": 0.8, "black": 0.2}, GROUP_PROMPT, lower={"black": 1.0}) is NO


# --- the box reported for a candidate ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("extent", "origin", "expected"),
    [
        (None, (0, 0), None),  # the verifier measured nothing: the detector's box stays
        ((60.0, 55.0, 40.0, 100.0), (700, 400), Box(760, 455, 40, 100)),  # crop pixels -> image pixels
        ((0.0, 0.0, 30.0, 30.0), (700, 400), None),  # centre outside the detector's box: someone else
        ((60.0, 55.0, 0.0, 100.0), (700, 400), None),  # empty
    ],
)
def test_prompt_refined_box_table(
    extent: tuple[float, float, float, float] | None, origin: tuple[int, int], expected: Box | None
) -> None:
    assert refined_box(Box(750, 450, 80, 120), extent, origin) == expected


@pytest.fixture(scope="module")
def pipeline(models_dir: Path) -> Iterator[Pipeline]:
    pool = ThreadPoolExecutor(max_workers=2)
    yield Pipeline(YoloxDetector(require("yolox", models_dir)["yolox_nano.onnx"]), PersonVerifier(), pool)
    pool.shutdown()


def _keyframe(sequences_dir: Path, frame_id: int) -> tuple[np.ndarray, Box, str]:
    seq = load_sequence(sequences_dir / GROUP)
    image = cv2.imread(str(sequences_dir / GROUP / "frames" / f"{frame_id:06d}.jpg"))
    truth = seq.ground_truth[frame_id - 1]
    assert image is not None and truth is not None
    return image, truth, seq.referring


def test_prompt_first_keyframe_of_group_chooses_the_described_man_by_his_body(
    pipeline: Pipeline, sequences_dir: Path
) -> None:
    """uav123_group1_1, frame 1 (what `eval --init prompt` asks first): YOLOX's box on the described man
    takes in his shadow; the local verifier says yes to him alone and reports his body's extent, which is
    the ground truth's person (IoU >= 0.5), where the detector's own box is not."""
    image, truth, prompt = _keyframe(sequences_dir, 1)
    sighting = pipeline.look(image, "person", prompt=prompt)
    detected = sighting.candidates
    candidates = [c.detection for c in pipeline.verify(image, detected, prompt, "person", sighting=sighting)]
    yes = [d for d in candidates if d.verdict is YES]
    assert len(yes) == 1, [d.justification for d in candidates]
    chosen = first_candidate(candidates, accept_uncertain=False)
    assert chosen is yes[0] and iou(chosen.start_box, truth) >= 0.5
    raw = max(detected, key=lambda d: iou(d.box, truth))
    assert chosen.box == raw.box  # re-detection keeps judging the detector's box
    assert iou(chosen.start_box, truth) > iou(raw.box, truth)
    assert "blue-gray" in chosen.justification and "dark" in chosen.justification


def test_prompt_group_keyframes_choose_the_described_man(pipeline: Pipeline, sequences_dir: Path) -> None:
    """Every keyframe (1 s) of uav123_group1_1 (45, about 8 s here): where anyone is chosen, the described
    man is chosen at least three times as often as anyone else (measured: 27 times him, 7 someone else,
    11 keyframes nobody; the others are mostly keyframes where YOLOX boxes two men as one)."""
    seq = load_sequence(sequences_dir / GROUP)
    right = wrong = 0
    for frame_id in range(1, len(seq.ground_truth) + 1, round(seq.fps)):
        image, truth, prompt = _keyframe(sequences_dir, frame_id)
        candidates = [c.detection for c in pipeline.run(image, prompt, "person").candidates]
        chosen = first_candidate(candidates, accept_uncertain=False)
        if chosen is not None:
            right += iou(chosen.start_box, truth) >= 0.5
            wrong += iou(chosen.start_box, truth) < 0.5
    assert right >= 3 * wrong and right >= 20, (right, wrong)


# --- the ceiling eval prints ------------------------------------------------------------------------


def _result(name: str, ious: list[float | None], first: float | None = None) -> SequenceResult:
    frames = sum(v is not None for v in ious)
    total = sum(v or 0.0 for v in ious)
    return SequenceResult(
        name, "nano", len(ious), total / frames, total / frames, 30.0, 30.0, 0, 0, 0, 0, 0,
        ious=ious, gt_frames=frames, iou_sum=total, first_box_s=first,
    )  # fmt: skip


def test_prompt_ceiling_counts_frames_from_the_first_possible_answer() -> None:
    reference = _result("a", [1.0, 1.0, None, 0.5, 0.5])
    ceiling = acquisition_ceiling(reference, 2)
    assert ceiling.gt_frames == 4 and ceiling.iou_sum == pytest.approx(1.0) and ceiling.miou == 0.25
    assert acquisition_ceiling(reference, 0).miou == reference.miou


def test_prompt_table_prints_ratio_ceiling_and_first_choice(capsys: pytest.CaptureFixture[str]) -> None:
    reference = [_result("seq_a", [0.8] * 10), _result("seq_b", [0.6] * 30)]
    prompted = [_result("seq_a", [0.0] * 4 + [0.8] * 6, 0.4), _result("seq_b", [0.0] * 30)]
    prompted[0].acquisition = [
        AcquisitionKeyframe(1, 3, 2, 1, True, 0.7, True, "yes", "dark 85% of the object", True, ("sedan",))
    ]
    # seq_b: the fast stage's early answer chose the target, the final verdicts someone else.
    prompted[1].acquisition = [
        AcquisitionKeyframe(1, 2, 3, 1, True, 0.9, final=False),
        AcquisitionKeyframe(1, 3, 3, 1, True, 0.1, alike=2),
    ]
    figures = _print_acquisition(prompted, reference, {"seq_a": 2, "seq_b": 2}, 0.2)
    out = capsys.readouterr().out
    line_a = next(line for line in out.splitlines() if line.startswith("seq_a"))
    line_b = next(line for line in out.splitlines() if line.startswith("seq_b"))
    assert " target " in line_a and "0.640" in line_a  # ceiling: 8 x 0.8 / 10
    assert " OTHER " in line_b and "0.560" in line_b and "e1:3/1T=target" in line_b  # 28 x 0.6 / 30
    assert figures["ceiling_miou"] == pytest.approx((6.4 + 16.8) / 40)
    assert figures["ratio"] == pytest.approx((4.8 / 40) / (26.0 / 40))
    assert "first verified boxes on the described target: 1 of 2" in out
    assert "first early starts on the described target: 1 of 1" in out
    # What was chosen, what was judged and what was not, per sequence.
    assert (
        "seq_a (keyframe 1, target): yes, placement fits: dark 85% of the object; 0 others alike; "
        "not judged: sedan" in out
    )
    assert "seq_b (keyframe 1, OTHER): -, placement not judged: -; 2 others alike; not judged: -" in out


def test_prompt_detection_keeps_the_detector_box_without_a_verifier_extent() -> None:
    """A verifier that measures no extent (VLM, HSV rules) gives no body box: a track starts on the detector's."""
    from backend.verifiers.attributes import AttributeVerifier

    image = np.full((240, 320, 3), 120, np.uint8)
    pool = ThreadPoolExecutor(max_workers=1)
    try:
        found = Pipeline(None, AttributeVerifier(), pool).verify(  # type: ignore[arg-type]
            image, [Detection(Box(100, 60, 40, 100), 0.9)], "a man in a red shirt", "person"
        )
    finally:
        pool.shutdown()
    assert found[0].detection.box == Box(100, 60, 40, 100) and found[0].detection.body_box is None


@pytest.mark.parametrize(
    ("verifier", "prompt", "judged"),
    [
        ("none", "a man in a red shirt", False),  # no verifier: the detector's class is the whole check
        ("hsv", "the wakeboarder being towed", False),  # names nothing the verifier can check
        ("hsv", "a dog", False),
        ("hsv", "a man in a red shirt", True),  # judged, even where it cannot tell ("uncertain")
        ("cascade", "a dog", False),  # the final stage says what was judged
    ],
)
def test_pipeline_says_whether_anything_judged_the_description(
    verifier: str, prompt: str, judged: bool
) -> None:
    """`judged` false lets a search start on "uncertain" (behaviors.candidate_selection): only when no
    answer could ever say more than the detector's class."""
    from backend.verifiers.attributes import AttributeVerifier
    from backend.verifiers.cascade import CascadeVerifier

    chosen = {
        "none": None,
        "hsv": AttributeVerifier(),
        "cascade": CascadeVerifier(AttributeVerifier(), AttributeVerifier()),
    }[verifier]
    image = np.full((240, 320, 3), 120, np.uint8)
    pool = ThreadPoolExecutor(max_workers=1)
    try:
        found = Pipeline(None, chosen, pool).verify(  # type: ignore[arg-type]
            image, [Detection(Box(100, 60, 40, 100), 0.9)], prompt, "person"
        )
    finally:
        pool.shutdown()
    assert found[0].detection.judged is judged
    if not judged:
        assert found[0].detection.verdict is UNC


def test_prompt_red_shirt_is_not_grey_blue_on_real_crops(sequences_dir: Path) -> None:
    """Labelled crops of uav123_group1_1 (every 4th of each man): the red shirt's shade reads partly grey or
    blue, but a red shirt is never "grey-blue"; the grey-blue striped shirt is, with or without the
    pattern word. (The shipped colour prototypes were calibrated on these crops: optimistic for them.)"""
    from backend.crops import margin_crop
    from backend_tools.crop_set import load_crops, read_frame
    from backend_tools.verifier_eval import DEFAULT_CROPS

    verifier = PersonVerifier()
    crops = [c for c in load_crops(DEFAULT_CROPS) if c.sequence == GROUP and c.posture]

    def verdicts(upper: set[str], prompt: str) -> list[Verdict]:
        out = []
        for crop in [c for c in crops if set(c.upper) == upper][::4]:
            image, inner = margin_crop(read_frame(sequences_dir, crop), Box(*crop.box), 50)
            out.append(verifier.verify(image, inner.xywh(), prompt, "person").verdict)
        return out

    red = verdicts({"red"}, "a man in a grey-blue shirt")
    grey_blue = verdicts({"gray", "blue", "white"}, "a man in a grey-blue shirt")
    assert len(red) >= 10 and YES not in red and red.count(NO) >= len(red) - 1
    assert len(grey_blue) >= 10 and grey_blue.count(YES) >= 0.9 * len(grey_blue)

"""Verifiers: the VLM answer parser, the chat-completions client against the emulator, the colour check."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest
import requests

from backend.crops import crop_box, margin_crop
from backend.detectors.yolox import YoloxDetector
from backend.pipeline import Pipeline
from backend.verifiers.answer_parser import parse_answer
from backend.verifiers.attributes import AttributeVerifier, colour_claims
from backend.verifiers.cascade import CascadeVerifier
from backend.verifiers.interface import VerifierError, VerifierTimeout
from backend.verifiers.openai_chat import OpenAIChatVerifier
from backend.verifiers.prompts import family_for, render
from backend_tools.bench_command import mosaic
from backend_tools.vlm_emulator import MODEL_NAME, VlmEmulator
from behaviors.detection import Verdict
from behaviors.geometry import Box

YES, NO, UNC = Verdict.YES, Verdict.NO, Verdict.UNCERTAIN


@pytest.mark.parametrize(
    ("reply", "verdict"),
    [
        ("Answer: Yes.", YES),
        ("answer: no", NO),
        ("The person wears a gray shirt and lies on the ground.\nAnswer: Yes", YES),
        ("**Answer:** No.", NO),
        ("Final answer - YES", YES),
        ("I first thought yes, but the shirt is red.\nAnswer: No.", NO),
        ("Answer: yes\n...on reflection...\nAnswer: no", NO),
        ("Yes", YES),
        ("no.", NO),
        ("Yes, the jacket is clearly blue.", YES),
        ('{"answer": "yes", "justification": "gray shirt visible"}', YES),
        ('```json\n{"verdict": false, "reason": "red shirt"}\n```', NO),
        ('{"match": true}', YES),
        ('{"answer": "maybe"}', UNC),
        ("Answer: uncertain", UNC),
        ("I cannot tell whether this is yes or no.", UNC),
        ("", UNC),
        ("The quick brown fox.", UNC),
        ("{not json", UNC),
        ("Answer: Perhaps", UNC),
    ],
)
def test_answer_parser_table(reply: str, verdict: Verdict) -> None:
    assert parse_answer(reply)[0] is verdict


def test_parser_keeps_the_justification() -> None:
    assert parse_answer("Gray shirt, lying down.\nAnswer: Yes.")[1] == "Gray shirt, lying down."
    assert parse_answer('{"answer": "no", "reason": "red shirt"}')[1] == "red shirt"


def test_prompt_sets_follow_the_strategy() -> None:
    assert family_for("gpt-4o-mini") == "gpt" and family_for("llava:13b") == "llava"
    assert family_for("google/paligemma-3b-mix-224") == "paligemma" and family_for("x", "llava") == "llava"
    from backend.verifiers.prompts import GPT

    system, task = render(GPT, 'an injured man in a "gray" shirt', "person")
    assert "search-and-rescue" in system and "yes" in system
    assert (
        "in doubt, rather say Yes" in task
        and "Answer: Yes" in task
        and "an injured man in a 'gray' shirt" in task
    )


def _crop(sequences_dir: Path, name: str, index: int = 1) -> tuple[np.ndarray, Box]:
    image = cv2.imread(str(sequences_dir / name / "frames" / f"{index:06d}.jpg"))
    assert image is not None
    line = (sequences_dir / name / "groundtruth.txt").read_text().split()[index - 1]
    return margin_crop(image, Box(*(float(v) for v in line.split(","))), 50)


def test_chat_client_speaks_the_protocol_and_reads_the_answer(sequences_dir: Path) -> None:
    crop, inner = _crop(sequences_dir, "dtb70_Surfing06")
    with VlmEmulator() as vlm:
        verifier = OpenAIChatVerifier(vlm.base_url, MODEL_NAME)
        yes = verifier.verify(crop, inner.xywh(), "the surfer in a black wetsuit", "person", 5)
        no = verifier.verify(crop, inner.xywh(), "a surfer in a green wetsuit", "person", 5)
        models = requests.get(vlm.base_url + "/models", timeout=5).json()
    assert yes.verdict is YES and "black" in yes.justification and yes.verifier == f"vlm:{MODEL_NAME}"
    assert no.verdict is NO
    assert models["data"][0]["id"] == MODEL_NAME


def test_chat_client_request_body_has_system_task_and_base64_jpeg() -> None:
    body = OpenAIChatVerifier("http://x/v1", "gpt-4o-mini", crop_max_side=64).request_body(
        np.zeros((300, 100, 3), np.uint8), "a man in a gray shirt", "person"
    )
    messages = body["messages"]
    assert isinstance(messages, list) and messages[0]["role"] == "system"
    parts = messages[1]["content"]
    assert parts[0]["type"] == "text" and '"a man in a gray shirt"' in parts[0]["text"]
    assert parts[1]["image_url"]["url"].startswith("data:image/jpeg;base64,/9j/")


def test_retries_on_503_then_succeeds(sequences_dir: Path) -> None:
    crop, inner = _crop(sequences_dir, "dtb70_Surfing06")
    with VlmEmulator(fail_first=2, fail_status=503) as vlm:
        verifier = OpenAIChatVerifier(vlm.base_url, MODEL_NAME, max_retries=2, backoff_s=0.05)
        answer = verifier.verify(crop, inner.xywh(), "the surfer in a black wetsuit", "person", 10)
        assert answer.verdict is YES and vlm.requests == 3


def test_gives_up_after_retries_and_does_not_retry_400() -> None:
    crop = np.zeros((50, 50, 3), np.uint8)
    with (
        VlmEmulator(fail_first=10, fail_status=429) as vlm,
        pytest.raises(VerifierError, match="gave up after 2 attempts: HTTP 429"),
    ):
        OpenAIChatVerifier(vlm.base_url, MODEL_NAME, max_retries=1, backoff_s=0.01).verify(
            crop, (0, 0, 50, 50), "a man", "person", 10
        )
    with VlmEmulator(fail_first=10, fail_status=400) as vlm:
        with pytest.raises(VerifierError, match="HTTP 400"):
            OpenAIChatVerifier(vlm.base_url, MODEL_NAME, max_retries=3, backoff_s=0.01).verify(
                crop, (0, 0, 50, 50), "a man", "person", 10
            )
        assert vlm.requests == 1


def test_slow_verifier_times_out() -> None:
    with VlmEmulator(latency_s=2.0) as vlm:
        start = time.monotonic()
        with pytest.raises(VerifierTimeout):
            OpenAIChatVerifier(vlm.base_url, MODEL_NAME).verify(
                np.zeros((50, 50, 3), np.uint8), (0, 0, 50, 50), "a man", "person", 0.3
            )
        assert time.monotonic() - start < 1.5


@pytest.fixture(scope="module")
def yolox(models_dir: Path) -> YoloxDetector:
    return YoloxDetector(models_dir / "yolox_nano" / "yolox_nano.onnx", threads=1)


@pytest.fixture(scope="module")
def crowd(sequences_dir: Path) -> np.ndarray:
    """A 640x480 keyframe with five real people cut from the sequences (YOLOX finds at least five)."""
    return mosaic(sequences_dir, 5)


def test_pipeline_verifies_candidates_concurrently(yolox: YoloxDetector, crowd: np.ndarray) -> None:
    with VlmEmulator(latency_s=0.4, mode="yes") as vlm:
        verifier = OpenAIChatVerifier(vlm.base_url, MODEL_NAME)
        with ThreadPoolExecutor(8) as pool:
            result = Pipeline(yolox, verifier, pool, max_candidates=5).run(
                crowd, "a man in a gray shirt", "person"
            )
        assert vlm.max_in_flight == 5
    assert [c.detection.verdict for c in result.candidates] == [YES] * 5
    assert result.t_verify < 5 * 0.4  # five 0.4 s answers overlapped (generous bound for a loaded machine)


def test_pipeline_turns_timeouts_and_garbage_into_the_uncertain_policy(
    yolox: YoloxDetector, crowd: np.ndarray
) -> None:
    image = crowd
    with VlmEmulator(latency_s=1.5, mode="yes") as slow, ThreadPoolExecutor(8) as pool:
        pipeline = Pipeline(
            yolox,
            OpenAIChatVerifier(slow.base_url, MODEL_NAME),
            pool,
            max_candidates=2,
            timeout_s=0.3,
            deadline_s=5,
        )
        start = time.monotonic()
        result = pipeline.run(image, "a man", "person")
        assert time.monotonic() - start < 1.4
    assert [c.detection.verdict for c in result.candidates] == [UNC, UNC]
    assert all("timed out" in c.detection.justification for c in result.candidates)
    with VlmEmulator(mode="garbage") as vlm, ThreadPoolExecutor(4) as pool:
        for policy, expected in (("uncertain", UNC), ("yes", YES), ("no", NO)):
            pipeline = Pipeline(
                yolox,
                OpenAIChatVerifier(vlm.base_url, MODEL_NAME),
                pool,
                max_candidates=1,
                uncertain_policy=policy,
            )
            (candidate,) = pipeline.run(image, "a man", "person").candidates
            assert candidate.detection.verdict is expected
            assert "quick brown fox" in candidate.detection.justification


@pytest.mark.slow
def test_request_deadline_bounds_queued_verifications(yolox: YoloxDetector, crowd: np.ndarray) -> None:
    with VlmEmulator(latency_s=0.5, mode="yes") as vlm, ThreadPoolExecutor(1) as pool:
        pipeline = Pipeline(
            yolox,
            OpenAIChatVerifier(vlm.base_url, MODEL_NAME),
            pool,
            max_candidates=5,
            timeout_s=5,
            deadline_s=1.2,
        )
        start = time.monotonic()
        verdicts = [c.detection.verdict for c in pipeline.run(crowd, "a man", "person").candidates]
        assert time.monotonic() - start < 2.5
    assert verdicts[0] is YES and verdicts[-1] is UNC  # one pool slot: later ones miss the deadline


def test_margin_crop_is_clamped_to_the_image() -> None:
    assert crop_box(Box(10, 20, 30, 40), 50, 640, 480) == (0, 0, 90, 110)
    assert crop_box(Box(600, 450, 30, 20), 50, 640, 480) == (550, 400, 640, 480)
    crop, inner = margin_crop(np.zeros((480, 640, 3), np.uint8), Box(100, 100, 20, 40), 50)
    assert crop.shape == (140, 120, 3) and inner == Box(50, 50, 20, 40)


def test_colour_claims_find_the_garment() -> None:
    claims = colour_claims("a man with a red cap in a green-and-white striped shirt and blue jeans")
    assert [(c.colour, c.region) for c in claims] == [
        ("red", "head"),
        ("green", "upper"),
        ("white", "upper"),
        ("blue", "lower"),
    ]
    assert [(c.colour, c.region) for c in colour_claims("the white plastic bag", "bag")] == [
        ("white", "whole")
    ]


# Every (sequence, true description, false description): measured on ground-truth crops of real frames.
ATTRIBUTE_CASES = [
    ("uav123_person12_1", "the man in the green-and-white striped shirt", "a man in a red shirt"),
    ("otb_Crossing", "the person in dark clothes", "a person in a yellow jacket"),
    ("dtb70_Surfing06", "the surfer in a black wetsuit", "a surfer in an orange wetsuit"),
    ("uav123_wakeboard7", "a wakeboarder in a black top", "a wakeboarder in a white shirt"),
    ("vot2015_bag", "the white plastic bag on the ground", "a red bag"),
]


def test_local_verifier_accuracy_on_real_crops(sequences_dir: Path) -> None:
    verifier = AttributeVerifier()
    rows = []
    for name, true_prompt, false_prompt in ATTRIBUTE_CASES:
        superset = "bag" if "bag" in name else "person"
        truths, falses = [], []
        for index in range(1, 60, 6):
            crop, inner = _crop(sequences_dir, name, index)
            truths.append(verifier.verify(crop, inner.xywh(), true_prompt, superset).verdict)
            falses.append(verifier.verify(crop, inner.xywh(), false_prompt, superset).verdict)
        rows.append(
            (
                name,
                truths.count(YES) / len(truths),
                falses.count(NO) / len(falses),
                truths.count(NO) / len(truths),
            )
        )
    for name, tp, tn, fn in rows:
        print(f"{name}: true description -> yes {tp:.0%}, wrong colour -> no {tn:.0%}, true -> no {fn:.0%}")
    assert np.mean([r[2] for r in rows]) >= 0.8  # wrong colours are ruled out
    assert np.mean([r[3] for r in rows]) <= 0.15  # the true target is rarely ruled out


def test_cascade_skips_the_vlm_on_a_clear_local_no(sequences_dir: Path) -> None:
    crop, inner = _crop(sequences_dir, "dtb70_Surfing06")
    with VlmEmulator(mode="yes") as vlm:
        cascade = CascadeVerifier(AttributeVerifier(), OpenAIChatVerifier(vlm.base_url, MODEL_NAME))
        no = cascade.verify(crop, inner.xywh(), "a surfer in a red wetsuit", "person", 5)
        assert no.verdict is NO and no.verifier == "local:colours" and vlm.requests == 0
        yes = cascade.verify(crop, inner.xywh(), "an injured surfer in a black wetsuit", "person", 5)
        assert yes.verdict is YES and yes.verifier.startswith("vlm:") and vlm.requests == 1
        assert "fast check" in yes.justification


def test_posture_from_the_box_shape_on_real_and_rotated_crops(sequences_dir: Path) -> None:
    verifier = AttributeVerifier()
    crop, inner = _crop(sequences_dir, "otb_Crossing")  # a walking pedestrian, box 17 x 50
    assert verifier.verify(crop, inner.xywh(), "a person lying on the ground", "person").verdict is NO
    assert verifier.verify(crop, inner.xywh(), "a person walking across the street", "person").verdict is YES
    lying = cv2.rotate(crop, cv2.ROTATE_90_CLOCKWISE)  # the same pixels as a person on the ground
    h = crop.shape[0]
    rotated = (h - inner.y - inner.h, inner.x, inner.h, inner.w)
    answer = verifier.verify(lying, rotated, "an injured man lying on the ground in dark clothes", "person")
    assert (
        answer.verdict is YES
        and "height/width 0.3" in answer.justification
        and "dark" in answer.justification
    )
    square = (10.0, 10.0, 30.0, 32.0)  # a person seen from straight above: cannot tell
    assert verifier.verify(crop, square, "a collapsed hiker", "person").verdict is UNC
    assert verifier.verify(crop, inner.xywh(), "a bag lying on the ground", "bag").verdict is UNC

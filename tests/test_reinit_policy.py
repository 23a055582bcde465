"""The "verified" re-initialisation policy (behaviors.reinit_policy), table-tested."""

from __future__ import annotations

import math

import pytest

from behaviors.detection import Verdict
from behaviors.geometry import Box
from behaviors.reinit_policy import (
    CandidateEvidence,
    ReinitAction,
    ReinitSettings,
    ReinitState,
    TrackEvidence,
    decide,
    framing_ratio,
    overgrown,
    same_object,
)

TRACK = Box(100, 100, 20, 50)
ON_TRACK = Box(101, 99, 21, 52)  # the detector's box on the tracked object
NEAR = Box(160, 100, 20, 50)  # a neighbour, inside the gate
FAR = Box(900, 600, 20, 50)  # beyond the gate around the last trusted box

YES, UNSURE, NO = Verdict.YES, Verdict.UNCERTAIN, Verdict.NO


def track(lost: bool = False, appearance: float | None = 0.3, box: Box | None = TRACK) -> TrackEvidence:
    return TrackEvidence(box=box, lost=lost, appearance=appearance, reference=TRACK, gate_px=300.0)


def cand(box: Box, verdict: Verdict = UNSURE, appearance: float | None = 0.3) -> CandidateEvidence:
    return CandidateEvidence(box, verdict, appearance)


@pytest.mark.parametrize(
    ("name", "track_view", "candidates", "action", "index"),
    [
        ("trusted, detector agrees: confirm", track(), [cand(ON_TRACK)], ReinitAction.CONFIRM, 0),
        (
            "lost, detector agrees: the loss is withdrawn",
            track(lost=True),
            [cand(ON_TRACK)],
            ReinitAction.CONFIRM,
            0,
        ),
        ("lost, nothing found: wait", track(lost=True), [], ReinitAction.WAIT, None),
        ("trusted, nothing found: keep", track(), [], ReinitAction.KEEP, None),
        (
            "lost, a 'no' elsewhere never wins",
            track(lost=True),
            [cand(NEAR, NO, 0.0)],
            ReinitAction.WAIT,
            None,
        ),
        (
            "lost, an unlike uncertain candidate has no evidence",
            track(lost=True),
            [cand(NEAR, UNSURE, 0.9)],
            ReinitAction.WAIT,
            None,
        ),
        (
            "the verifier says no to the track's own candidate: no confirmation",
            track(),
            [cand(ON_TRACK, NO)],
            ReinitAction.KEEP,
            None,
        ),
        (
            "far uncertain candidate needs a yes",
            track(lost=True),
            [cand(FAR, UNSURE, 0.0)],
            ReinitAction.WAIT,
            None,
        ),
        (
            "a yes elsewhere leads the streak but one answer is not enough",
            track(),
            [cand(ON_TRACK), cand(NEAR, YES)],
            ReinitAction.KEEP,
            1,
        ),
        ("lost: a far yes leads the streak", track(lost=True), [cand(FAR, YES)], ReinitAction.WAIT, 0),
        (
            "verifier prefers it, appearance contradicts: no",
            track(appearance=0.2),
            [cand(ON_TRACK, UNSURE, 0.2), cand(NEAR, YES, 0.7)],
            ReinitAction.CONFIRM,
            0,
        ),
        (
            "tie in verdicts, clearly more like the target: leads",
            track(appearance=0.6),
            [cand(ON_TRACK, UNSURE, 0.6), cand(NEAR, UNSURE, 0.3)],
            ReinitAction.KEEP,
            1,
        ),
        (
            "tie in verdicts, within the margin: the track stays",
            track(appearance=0.4),
            [cand(ON_TRACK, UNSURE, 0.4), cand(NEAR, UNSURE, 0.35)],
            ReinitAction.CONFIRM,
            0,
        ),
    ],
)
def test_reinit_policy_single_answer(
    name: str,
    track_view: TrackEvidence,
    candidates: list[CandidateEvidence],
    action: ReinitAction,
    index: int | None,
) -> None:
    decision = decide(ReinitState(), track_view, candidates)
    assert (decision.action, decision.index) == (action, index), name


def test_reinit_policy_needs_two_consistent_answers() -> None:
    answer = [cand(ON_TRACK, NO), cand(NEAR, YES)]
    first = decide(ReinitState(), track(), answer)
    assert first.action is ReinitAction.KEEP and first.state.streak == 1
    second = decide(first.state, track(), [cand(ON_TRACK, NO), cand(Box(165, 102, 20, 50), YES)])
    assert second.action is ReinitAction.REINIT and second.index == 1 and second.state == ReinitState()
    # The second winner somewhere else entirely is a new streak, not a confirmation of the first.
    elsewhere = decide(first.state, track(), [cand(ON_TRACK, NO), cand(Box(400, 100, 20, 50), YES)])
    assert elsewhere.action is ReinitAction.KEEP and elsewhere.state.streak == 1
    # An answer with no winner in between resets the streak.
    quiet = decide(first.state, track(), [cand(ON_TRACK)])
    assert quiet.action is ReinitAction.CONFIRM and quiet.state.streak == 0


def test_reinit_policy_never_moves_onto_a_rejected_or_unevidenced_candidate() -> None:
    """Whatever the state and the track, a 'no' or an uncertain candidate unlike the target is never taken."""
    for lost in (False, True):
        for track_box in (TRACK, None):
            state = ReinitState()
            for _ in range(5):
                view = TrackEvidence(track_box, lost, appearance=None, reference=TRACK)
                decision = decide(
                    state, view, [cand(NEAR, NO, 0.0), cand(FAR, UNSURE, 0.95), cand(NEAR, UNSURE, None)]
                )
                assert decision.action is not ReinitAction.REINIT
                state = decision.state


def test_reinit_settings_confirmations_one_moves_at_once_and_bad_settings_fail() -> None:
    once = ReinitSettings(confirmations=1)
    assert decide(ReinitState(), track(lost=True), [cand(NEAR, YES)], once).action is ReinitAction.REINIT
    with pytest.raises(ValueError, match="confirmations"):
        ReinitSettings(confirmations=0)
    with pytest.raises(ValueError, match="agree_iou"):
        ReinitSettings(agree_iou=0.0)
    with pytest.raises(ValueError, match="max_framing_ratio"):
        ReinitSettings(max_framing_ratio=1.0)  # every track would be re-framed on every answer


# A detector frames a person wider (feet, arms) than a tracker: IoU about 0.4 with the track, same centre.
WIDE_ON_TRACK = Box(92, 95, 36, 60)
SHIFTED_NEIGHBOUR = Box(118, 100, 20, 50)  # a neighbour shoulder to shoulder: boxes overlap, centres do not


@pytest.mark.parametrize(
    ("name", "a", "b", "same"),
    [
        ("tight overlap", TRACK, ON_TRACK, True),
        ("wider detector box on the same person", TRACK, WIDE_ON_TRACK, True),
        ("a neighbour whose box overlaps", TRACK, SHIFTED_NEIGHBOUR, False),
        ("a neighbour apart", TRACK, NEAR, False),
    ],
)
def test_reinit_policy_same_object_by_overlap_or_mutual_centres(
    name: str, a: Box, b: Box, same: bool
) -> None:
    assert same_object(a, b, 0.5) is same and same_object(b, a, 0.5) is same, name


@pytest.mark.parametrize(
    ("name", "track_view", "candidates", "action", "index"),
    [
        (
            "a wider detector box on the track confirms it (never a contender)",
            track(),
            [cand(WIDE_ON_TRACK, YES)],
            ReinitAction.CONFIRM,
            0,
        ),
        (
            "lost on a weak signal, candidate on the track: confirm, keep the tracker",
            track(lost=True),
            [cand(WIDE_ON_TRACK)],
            ReinitAction.CONFIRM,
            0,
        ),
        (
            "lost on a geometric signal, candidate holds the track but frames it otherwise: re-frame",
            TrackEvidence(TRACK, True, 0.3, TRACK, 300.0, degraded=True),
            [cand(WIDE_ON_TRACK)],
            ReinitAction.REINIT,
            0,
        ),
        (
            "trusted, a geometric alarm firing, candidate frames it otherwise: re-frame (two signals)",
            TrackEvidence(TRACK, False, 0.3, TRACK, 300.0, degraded=True),
            [cand(WIDE_ON_TRACK)],
            ReinitAction.REINIT,
            0,
        ),
        (
            "lost on a geometric signal, candidate frames it alike: the alarm was false, confirm",
            TrackEvidence(TRACK, True, 0.3, TRACK, 300.0, degraded=True),
            [cand(ON_TRACK)],
            ReinitAction.CONFIRM,
            0,
        ),
        (
            "lost on a geometric signal, a 'no' on the track never re-frames",
            TrackEvidence(TRACK, True, 0.3, TRACK, 300.0, degraded=True),
            [cand(WIDE_ON_TRACK, NO)],
            ReinitAction.WAIT,
            None,
        ),
    ],
)
def test_reinit_policy_reframe_and_wide_boxes(
    name: str,
    track_view: TrackEvidence,
    candidates: list[CandidateEvidence],
    action: ReinitAction,
    index: int | None,
) -> None:
    decision = decide(ReinitState(), track_view, candidates)
    assert (decision.action, decision.index) == (action, index), name


GROWN = Box(80, 80, 60, 110)  # a tracker box that drifted in scale over its object and the background
OBJECT_IN_GROWN = Box(100, 110, 22, 50)  # the detector's box on the object: holds the grown box's centre


@pytest.mark.parametrize(
    ("name", "candidate", "action", "index"),
    [
        (
            "trusted, no alarm, the tracker's box over 1.5x its object's width: re-frame on the object",
            cand(OBJECT_IN_GROWN, YES),
            ReinitAction.REINIT,
            0,
        ),
        (
            "an 'uncertain' object on the track re-frames it too",
            cand(OBJECT_IN_GROWN),
            ReinitAction.REINIT,
            0,
        ),
        ("a 'no' on the track never re-frames", cand(OBJECT_IN_GROWN, NO), ReinitAction.KEEP, None),
        (
            "the detector's own box is what is compared: a conversion that grew with the track hides nothing",
            CandidateEvidence(Box(85, 85, 50, 100), YES, 0.3, detected=OBJECT_IN_GROWN),
            ReinitAction.REINIT,
            0,
        ),
        (
            "a detected object of the track's size is no growth, whatever the conversion made of it",
            CandidateEvidence(Box(105, 115, 12, 40), YES, 0.3, detected=Box(82, 82, 56, 106)),
            ReinitAction.CONFIRM,
            0,
        ),
    ],
)
def test_reinit_policy_reframes_a_track_that_outgrew_its_object(
    name: str, candidate: CandidateEvidence, action: ReinitAction, index: int | None
) -> None:
    first = decide(ReinitState(), track(box=GROWN), [candidate])
    decision = decide(first.state, track(box=GROWN), [candidate])
    assert (decision.action, decision.index) == (action, index), name
    if action is ReinitAction.REINIT:
        # One answer only doubts the track: it confirms it and counts; the same answer again re-frames.
        assert (first.action, first.index, first.state.outgrown) == (ReinitAction.CONFIRM, 0, 1), name
        assert "outgrew" in decision.reason and decision.state == ReinitState()


def test_an_outgrown_track_is_reframed_only_on_answers_in_a_row() -> None:
    """A partial detector box (an upper body) on one keyframe looks like an overgrown track; an answer
    that frames the track within the convention in between starts the count again."""
    outgrown = [cand(OBJECT_IN_GROWN, YES)]
    framed_alike = [cand(GROWN, YES)]
    first = decide(ReinitState(), track(box=GROWN), outgrown)
    between = decide(first.state, track(box=GROWN), framed_alike)
    assert between.action is ReinitAction.CONFIRM and between.state.outgrown == 0
    again = decide(between.state, track(box=GROWN), outgrown)
    assert again.action is ReinitAction.CONFIRM and again.state.outgrown == 1
    assert decide(again.state, track(box=GROWN), outgrown).action is ReinitAction.REINIT
    once = ReinitSettings(confirmations=1)
    assert decide(ReinitState(), track(box=GROWN), outgrown, once).action is ReinitAction.REINIT


@pytest.mark.parametrize(
    ("track_box", "detected", "ratio"),
    [
        (Box(0, 0, 30, 100), Box(0, 0, 20, 100), 1.5),  # the larger of the two ratios
        (Box(0, 0, 20, 150), Box(0, 0, 20, 60), 2.5),
        (Box(0, 0, 20, 50), Box(0, 0, 40, 200), 0.5),  # the detector's box larger on both sides
        (Box(0, 0, 20, 50), Box(0, 0, 0, 50), math.inf),  # no object to compare with
    ],
)
def test_framing_ratio_is_the_larger_of_width_and_height(track_box: Box, detected: Box, ratio: float) -> None:
    assert framing_ratio(track_box, detected) == ratio


@pytest.mark.parametrize(
    ("track_box", "detected", "expected"),
    [
        (Box(0, 0, 31, 100), Box(0, 0, 20, 100), True),  # just over 1.5x as wide
        (Box(0, 0, 30, 100), Box(0, 0, 20, 100), False),  # exactly 1.5x: still a framing convention
        (Box(0, 0, 20, 151), Box(0, 0, 20, 100), True),  # over 1.5x as tall
        (Box(0, 0, 20, 50), Box(0, 0, 60, 150), False),  # the detector's box larger (a group, a shadow)
    ],
)
def test_overgrown_is_a_tracker_box_over_one_and_a_half_times_its_object(
    track_box: Box, detected: Box, expected: bool
) -> None:
    assert ReinitSettings().max_framing_ratio == 1.5
    assert overgrown(track_box, detected, 1.5) is expected


def test_the_framing_bound_is_a_setting() -> None:
    loose = ReinitSettings(max_framing_ratio=3.0)  # GROWN is 2.7x its object's width
    decision = decide(ReinitState(), track(box=GROWN), [cand(OBJECT_IN_GROWN, YES)], loose)
    assert decision.action is ReinitAction.CONFIRM

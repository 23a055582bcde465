"""Flight uses the front-end's re-initialisation policy ([tracker] reinit_policy), like `eval` does.

The real main loop (`MissionRunner`) with the real mission state machine and a real NanoTrack front-end on
real frames; only the vehicle and the back-end's transport are replaced (answers are injected as events).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import cv2
import pytest

from behaviors.actions import QueryPurpose
from behaviors.detection import Detection, Verdict
from behaviors.events import BackendAnswer, GcsCommand, TimerTick
from behaviors.geometry import Box, iou
from behaviors.mission import MissionState
from behaviors.mission_commands import RejectCandidate, StartMission
from behaviors.mission_config import MissionConfig
from behaviors.reinit_policy import ReinitDecision
from companion.cloud.backend_worker import WorkerHealth
from companion.config import TrackerConfig
from companion.mission_runner import MissionRunner
from companion.vision.frame_sources import Frame
from companion.vision.tracking_frontend import TrackingFrontend
from companion_tools.tracking_eval import load_sequence

SEQ = "otb_Crossing"


class _Judged(TrackingFrontend):
    """The real front-end, counting the answers the loop hands to its policy."""

    judged: list[tuple[int, int, tuple[int, ...]]]

    def judge_candidates(
        self, keyframe_id: int, detections: Sequence[Detection], refused: Collection[int] = ()
    ) -> ReinitDecision | None:
        self.judged.append((keyframe_id, len(detections), tuple(refused)))
        return super().judge_candidates(keyframe_id, detections, refused)


class _Vehicle:
    """Accepts everything the loop tells the autopilot (no vehicle in this test)."""

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: None


class _Backend:
    def __init__(self) -> None:
        self.submitted: list[dict[str, Any]] = []

    def submit(self, frame_id: int, image: Any, capture_time: float, **fields: Any) -> bool:
        self.submitted.append({"frame_id": frame_id, **fields})
        return True

    def health(self) -> WorkerHealth:
        return WorkerHealth(None, 0, "", False, 0, 0, 0)


class _Record:
    def __init__(self) -> None:
        self.reinits: list[Any] = []

    def on_event(self, event: Any) -> None: ...

    def on_step(self, event: Any, state: Any, actions: Any) -> None: ...

    def on_health(self, time_s: float, healthy: bool, reasons: Any) -> None: ...

    def on_reinit(self, init: Any, time_s: float) -> None:
        self.reinits.append(init)


@pytest.fixture(scope="module")
def crossing(sequences_dir: Path):  # type: ignore[no-untyped-def]
    seq = load_sequence(sequences_dir / SEQ)
    frames = [
        Frame(i + 1, i / seq.fps, cv2.imread(str(seq.path / "frames" / f"{i + 1:06d}.jpg")))
        for i in range(40)
    ]
    return seq, frames


def _following(models_dir: Path, crossing, policy: str = "verified"):  # type: ignore[no-untyped-def]
    """A runner following the crossing person after a search answer found them on frame 1."""
    seq, frames = crossing
    fe = _Judged.from_config(TrackerConfig(reinit_policy=policy), models_dir, tracker_name="nano")
    assert isinstance(fe, _Judged)
    fe.judged = []
    backend, record = _Backend(), _Record()
    none: Any = None
    # Keyframes every 50 ms so that a few seconds of footage hold many answers.
    runner = MissionRunner(
        MissionConfig(query_interval_s=0.05), none, fe, _Vehicle(), backend, observers=[record]
    )  # type: ignore[arg-type]
    assert runner.mission.verified_reinit is (policy == "verified")

    def feed(frame: Frame) -> None:
        runner._latest = frame
        runner._handle(fe.feed(frame))

    feed(frames[0])
    runner._handle(GcsCommand(0.0, StartMission("the person crossing the road")))
    found = Detection(seq.ground_truth[0], 0.9, verdict=Verdict.YES, candidate_id="p1")
    runner._handle(BackendAnswer(0.05, 1, 1, (found,)))
    for frame in frames[1:10]:
        feed(frame)
    assert runner.state.mode is MissionState.FOLLOWING
    return seq, frames, fe, runner, backend, record, feed


def _check_query(runner: MissionRunner, t: float) -> int:
    """Tick the mission; the id of its newest query about the track (a check while trusted, a re-detection
    while lost)."""
    runner._handle(TimerTick(t))
    wanted = (QueryPurpose.TRACK_CHECK, QueryPurpose.REDETECT)
    checks = [qid for qid, purpose in runner.state.queries if purpose in wanted]
    assert checks, runner.state.queries
    return checks[-1]


def _elsewhere(truth: Box, verdict: Verdict, candidate_id: str) -> Detection:
    """Someone else in the keyframe: next to the target, not on it."""
    return Detection(
        Box(truth.x + 2 * truth.w, truth.y, truth.w, truth.h),
        0.95,
        verdict=verdict,
        candidate_id=candidate_id,
    )


def test_verified_flight_judges_every_answer_and_never_moves_on_an_unverified_candidate(
    models_dir: Path, crossing: Any
) -> None:
    seq, frames, fe, runner, backend, record, feed = _following(models_dir, crossing)
    for frame in frames[10:30:2]:  # an answer every other frame while the track is trusted
        feed(frame)
        truth, t = seq.ground_truth[frame.frame_id - 1], frame.capture_time
        qid = _check_query(runner, t)
        runner._handle(BackendAnswer(t, qid, frame.frame_id, (_elsewhere(truth, Verdict.UNCERTAIN, "p2"),)))
    assert len(fe.judged) == 10  # every answer went to the policy
    assert fe.stats.reinits == 1 and fe.stats.decisions.get("reinit", 0) == 0 and not record.reinits
    assert runner.state.mode is MissionState.FOLLOWING
    feed(frames[30])
    assert iou(fe.box_at(31), seq.ground_truth[30]) > 0.4  # still on the person it started on
    # Checks look at the whole frame: after a switch to a neighbour the target is outside the track's region.
    assert all(q.get("roi") is None for q in backend.submitted[1:])


def _slid_off(seq, frames, fe, feed) -> None:  # type: ignore[no-untyped-def]
    """The tracker slides onto the ground beside the person (a silent switch: it stays "trusted")."""
    truth = seq.ground_truth[9]
    fe._begin(10, _elsewhere(truth, Verdict.UNCERTAIN, "").box, keep_template=False)  # the look model stays
    for frame in frames[10:12]:
        feed(frame)
    assert not fe.catching_up and iou(fe.box_at(12), seq.ground_truth[11]) == 0.0


def _offer_person(seq, frames, runner, feed, frame_slice: slice) -> None:  # type: ignore[no-untyped-def]
    """Answer track checks with the person themself, "yes", as candidate "p2" (the detector missed the track)."""
    for frame in frames[frame_slice]:
        feed(frame)
        qid = _check_query(runner, frame.capture_time)
        person = Detection(seq.ground_truth[frame.frame_id - 1], 0.9, verdict=Verdict.YES, candidate_id="p2")
        runner._handle(BackendAnswer(frame.capture_time, qid, frame.frame_id, (person,)))


def test_verified_flight_never_reinits_on_a_rejected_candidate_but_does_on_the_same_evidence_unrejected(
    models_dir: Path, crossing: Any
) -> None:
    # The control: a "yes" that looks like the target, twice in a row, undoes the switch.
    seq, frames, fe, runner, _, record, feed = _following(models_dir, crossing)
    _slid_off(seq, frames, fe, feed)
    _offer_person(seq, frames, runner, feed, slice(12, 16, 2))
    assert len(fe.judged) == 2 and fe.judged[0][2] == ()
    assert fe.stats.decisions == {"keep": 1, "reinit": 1}, fe.stats.decisions  # one answer is not enough
    assert [r.candidate_id for r in record.reinits] == ["p2"]
    for frame in frames[16:20]:
        feed(frame)
    assert iou(fe.box_at(20), seq.ground_truth[19]) > 0.4

    # The same evidence for a candidate the supervisor rejected: refused, never taken, however often.
    seq, frames, fe, runner, _, record, feed = _following(models_dir, crossing)
    runner._handle(GcsCommand(frames[9].capture_time, RejectCandidate("p2")))  # someone else, remembered
    _slid_off(seq, frames, fe, feed)
    _offer_person(seq, frames, runner, feed, slice(12, 32, 2))  # trusted or lost on the ground: both judged
    assert len(fe.judged) == 10 and all(refused == (0,) for _, _, refused in fe.judged)
    assert fe.stats.decisions.get("reinit", 0) == 0 and not record.reinits and fe.stats.reinits == 2


def test_c_box_flight_is_unchanged_no_answer_goes_to_the_judge(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    _, frames, fe, runner, backend, _, _ = _following(models_dir, crossing, policy="c_box")
    runner._handle(TimerTick(frames[9].capture_time))
    assert not [q for q in runner.state.queries if q[1] is QueryPurpose.TRACK_CHECK]  # no checks
    assert fe.judged == [] and len(backend.submitted) == 1

"""The front-end the main loop calls: start, feed, loss latching, C_box re-initialisation, stop."""

from __future__ import annotations

from pathlib import Path

import cv2
import pytest

from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou
from behaviors.reinit_policy import ReinitAction
from cloudtrack.model_store import ModelError
from companion.config import TrackerConfig
from companion.vision.frame_sources import Frame
from companion.vision.tracking_frontend import TrackingFrontend
from companion_tools.tracking_eval import load_sequence

SEQ = "otb_Crossing"


@pytest.fixture(scope="module")
def crossing(sequences_dir: Path):  # type: ignore[no-untyped-def]
    seq = load_sequence(sequences_dir / SEQ)
    frames = [
        Frame(i + 1, i / seq.fps, cv2.imread(str(seq.path / "frames" / f"{i + 1:06d}.jpg")))
        for i in range(45)
    ]
    return seq, frames


def _frontend(models_dir: Path, **kwargs: object) -> TrackingFrontend:
    return TrackingFrontend.from_config(TrackerConfig(), models_dir, tracker_name="nano", **kwargs)


def test_idle_then_tracks_from_start(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    fe = _frontend(models_dir)
    first = fe.feed(frames[0])
    assert first.lost_reason == "idle" and first.box is None and not first.trusted
    assert fe.start(1, seq.ground_truth[0])
    ious = []
    for frame in frames[1:20]:
        result = fe.feed(frame)
        assert result.frame_id == frame.frame_id and result.trusted, result
        ious.append(iou(result.box, seq.ground_truth[frame.frame_id - 1]))
    assert min(ious) > 0.4
    assert fe.last_trusted_frame_id == 20 and fe.stats.reinits == 1 and fe.stats.loss_events == 0


def test_candidates_are_chosen_by_c_box_not_by_score(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    fe = _frontend(models_dir, policy="c_box")
    fe.feed(frames[0])
    fe.start(1, seq.ground_truth[0])
    for frame in frames[1:10]:
        fe.feed(frame)
    truth = seq.ground_truth[9]
    near = Detection(Box(truth.x + 2, truth.y + 1, truth.w + 1, truth.h - 2), 0.4, candidate_id="near")
    distractor = Detection(Box(truth.x + 60, truth.y - 20, truth.w, truth.h), 0.95, candidate_id="other")
    chosen = fe.apply_candidates(10, [distractor, near])
    assert chosen is not None and chosen.candidate_id == "near"
    assert fe.catching_up
    result = fe.feed(frames[10])
    assert result.trusted and iou(result.box, seq.ground_truth[10]) > 0.4
    assert fe.stats.reinits == 2

    reference = _frontend(models_dir, policy="score")  # the reference code: highest detector score
    reference.feed(frames[0])
    reference.start(1, seq.ground_truth[0])
    chosen = reference.apply_candidates(1, [near, distractor])
    assert chosen is not None and chosen.candidate_id == "other"


def test_far_candidates_are_gated_and_no_trusted_box_means_no_choice(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    fe = _frontend(models_dir, policy="c_box")
    fe.feed(frames[0])
    assert fe.apply_candidates(1, [Detection(seq.ground_truth[0], 0.9)]) is None  # nothing trusted yet
    fe.start(1, seq.ground_truth[0])
    fe.feed(frames[1])
    truth = seq.ground_truth[1]
    far = Detection(Box(truth.x + 250, truth.y + 100, truth.w, truth.h), 0.99)
    assert fe.apply_candidates(2, [far]) is None
    assert fe.stats.rejected_candidates == 1 and not fe.catching_up
    assert fe.apply_candidates(2, []) is None


def test_loss_is_latched_until_reinitialised(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    fe = _frontend(models_dir, policy="c_box")  # the paper's policies latch; "verified" judges each frame
    fe.feed(frames[0])
    fe.start(1, seq.ground_truth[0])
    fe.feed(frames[1])
    # Restart on a patch of road, then make the jump signal hair-trigger: the first loss must latch.
    road = Box(20, 200, 17, 30)
    fe.start(2, road)
    results = [fe.feed(f) for f in frames[2:8]]
    assert results[0].trusted  # a fresh start on a box is trusted at first
    fe.loss.settings = fe.loss.settings.__class__(**{**fe.loss.settings.__dict__, "max_jump_box_sizes": 0.01})
    later = [fe.feed(f) for f in frames[8:14]]
    lost = [r for r in later if r.lost_reason]
    assert lost and all(r.lost_reason == lost[0].lost_reason for r in later[later.index(lost[0]) :])
    assert fe.stats.loss_events == 1
    assert fe.start(14, seq.ground_truth[13])
    assert fe.feed(frames[14]).lost_reason == ""


def test_stop_and_stale_answers(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    fe = TrackingFrontend.from_config(TrackerConfig(ring_buffer_frames=5), models_dir, tracker_name="nano")
    for frame in frames[:10]:
        fe.feed(frame)
    assert not fe.start(1, seq.ground_truth[0])  # keyframe 1 left the 5-frame ring
    assert fe.stats.stale_answers == 1
    assert not fe.start(9, Box(0, 0, 0, 0))  # invalid box refused
    assert fe.start(9, seq.ground_truth[8])
    assert fe.feed(frames[10]).trusted
    fe.stop()
    assert fe.feed(frames[11]).lost_reason == "idle" and fe.last_trusted_box is None


def test_missing_weights_fail_at_construction(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="nanotrack_backbone_sim.onnx"):
        TrackingFrontend.from_config(TrackerConfig(), tmp_path)


def test_verified_policy_never_reinits_onto_an_unverified_candidate(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    """policy "verified": an uncertain candidate off the track, unlike the target, never takes the track,
    however often it is offered; the answers are kept as "keep" decisions."""
    seq, frames = crossing
    fe = _frontend(models_dir, policy="verified")
    fe.feed(frames[0])
    fe.start(1, seq.ground_truth[0])
    for frame in frames[1:10]:
        fe.feed(frame)
    for frame in frames[10:20]:
        fe.feed(frame)
        truth = seq.ground_truth[frame.frame_id - 1]
        elsewhere = Detection(Box(truth.x + 3 * truth.w, truth.y - 30, truth.w, truth.h), 0.99)
        assert fe.apply_candidates(frame.frame_id, [elsewhere]) is None
    assert fe.stats.reinits == 1 and not fe.catching_up  # the first start only
    assert sum(fe.stats.decisions.values()) == 10 and fe.stats.decisions.get("reinit", 0) == 0


def test_verified_policy_withdraws_a_loss_a_candidate_on_the_track_confirms(
    models_dir: Path, crossing
) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    # An appearance threshold of 0 makes the appearance signal fire on every frame: a false alarm. Alone it
    # untrusts the track only once it has lasted loss_persistence_s (0.5 s: 15 frames at 30 fps).
    fe = TrackingFrontend.from_config(
        TrackerConfig(appearance_drift_threshold=0.0, loss_persistence_s=0.5),
        models_dir,
        tracker_name="nano",
        policy="verified",
    )
    fe.feed(frames[0])
    fe.start(1, seq.ground_truth[0])
    results = [fe.feed(frame) for frame in frames[1:25]]
    assert all(r.trusted for r in results[:12]), [r.lost_reason for r in results]
    assert results[-1].lost_reason == "appearance" and not results[-1].trusted
    assert fe.stats.loss_events == 1  # one loss, no flicker
    on_track = fe.box_at(25)
    assert on_track is not None
    detector_box = Box(
        on_track.x - 2, on_track.y - 3, on_track.w + 4, on_track.h + 5
    )  # wider, as detectors frame
    assert fe.apply_candidates(25, [Detection(detector_box, 0.8)]) is None  # confirmed, not re-initialised
    assert fe.stats.confirmations == 1 and fe.stats.decisions == {"confirm": 1}
    after = fe.feed(frames[25])
    assert after.trusted, after  # the answer's evidence outweighs the appearance alarm until the next answer
    assert fe.stats.reinits == 1
    # The detector's extent is learnt from the confirmation: a later detector box is converted to the tracker's.
    converted = fe.to_tracker_convention(detector_box)
    assert converted.w == pytest.approx(on_track.w) and converted.h == pytest.approx(on_track.h)
    # The next answer found nothing on the track: the confirmation no longer holds, and the alarm that still
    # fires untrusts the track once it has lasted loss_persistence_s again.
    assert fe.apply_candidates(26, []) is None and fe.stats.decisions == {"confirm": 1, "keep": 1}
    later = [fe.feed(frame) for frame in frames[26:45]]
    assert not later[-1].trusted and later[-1].lost_reason == "appearance", [r.lost_reason for r in later]


def test_a_track_outgrowing_its_detected_object_is_reframed_on_it(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    fe = TrackingFrontend.from_config(TrackerConfig(), models_dir, tracker_name="nano", policy="verified")
    fe.feed(frames[0])
    fe.start(1, seq.ground_truth[0])
    for frame in frames[1:10]:
        fe.feed(frame)
    first = fe.box_at(10)
    assert first is not None
    # A detector that frames the tracked person smaller than the tracker does (IoU 0.6): the same object,
    # it confirms, and the front-end learns that its boxes are 0.75 x 0.8 of the tracker's.
    tight = Box.from_center(first.cx, first.cy, first.w * 0.75, first.h * 0.8)
    assert fe.apply_candidates(10, [Detection(tight, 0.8)]) is None
    assert fe.stats.decisions == {"confirm": 1}
    for frame in frames[10:20]:
        fe.feed(frame)
    track = fe.box_at(20)
    assert track is not None
    # Now the detector finds the object at 0.6 of the tracker's width and height. In the learnt convention
    # that is 0.8 x 0.75 of the track, no growth; against the detector's own box the tracker's box is 1.67x
    # its object (over reinit_max_framing_ratio, 1.5). One such answer could be a partial box: the track
    # stays, and that box teaches the conversion nothing; the same on the next keyframe re-frames it.
    object_box = Box.from_center(track.cx, track.cy, track.w * 0.6, track.h * 0.6)
    assert fe.apply_candidates(20, [Detection(object_box, 0.8)]) is None
    assert fe.stats.decisions == {"confirm": 2}
    converted = fe.to_tracker_convention(tight)
    assert converted.w == pytest.approx(first.w) and converted.h == pytest.approx(first.h)  # as learnt at 10
    for frame in frames[20:25]:
        fe.feed(frame)
    track = fe.box_at(25)
    assert track is not None
    object_box = Box.from_center(track.cx, track.cy, track.w * 0.6, track.h * 0.6)
    chosen = fe.apply_candidates(25, [Detection(object_box, 0.8)])
    assert chosen is not None and chosen.box == object_box
    assert fe.stats.decisions == {"confirm": 2, "reinit": 1}
    reframed = fe.feed(frames[25]).box
    assert reframed is not None and reframed.w < 0.9 * track.w and reframed.h < 0.9 * track.h
    assert iou(reframed, fe.to_tracker_convention(object_box)) > 0.5


def test_an_answer_about_a_keyframe_the_catch_up_passed_judges_the_new_track(
    models_dir: Path, crossing
) -> None:  # type: ignore[no-untyped-def]
    """A search's answers keep arriving after the track started (a hosted VLM answers 2 s late): one about
    a keyframe between the start and the take-over is evidence about the new track there. Judged against
    "no track" instead, any "yes" beat it and two re-initialised it on a raw detector box (person12_1)."""
    seq, frames = crossing
    fe = _frontend(models_dir, policy="verified")
    for frame in frames[:12]:
        fe.feed(frame)  # searching: nothing tracked while the answer is on its way
    assert fe.box_at(6) is None
    assert fe.start(2, seq.ground_truth[1])  # the answer about keyframe 2 arrives at frame 12
    while fe.catching_up:
        fe.feed(frames[fe.ring.newest.frame_id])  # type: ignore[union-attr]
    on_track = fe.box_at(6)
    assert on_track is not None and iou(on_track, seq.ground_truth[5]) > 0.5  # the new track's box there
    truth = seq.ground_truth[5]
    same_person = Detection(Box(truth.x - 2, truth.y - 2, truth.w + 4, truth.h + 4), 0.8, verdict=Verdict.YES)
    decision = fe.judge_candidates(6, [same_person])
    assert decision is not None and decision.action is ReinitAction.CONFIRM, decision
    assert fe.stats.reinits == 1


@pytest.mark.parametrize("policy", ["verified", "c_box"])
def test_an_answer_about_a_keyframe_before_the_target_was_started_is_ignored(
    models_dir: Path,
    crossing,  # type: ignore[no-untyped-def]
    policy: str,
) -> None:
    """A search answer still in flight when a track starts (four requests out, a 2 s VLM) refers to a
    keyframe the track never saw: it moves nothing, whatever it says."""
    seq, frames = crossing
    fe = _frontend(models_dir, policy=policy)
    for frame in frames[:12]:
        fe.feed(frame)
    assert fe.start(10, seq.ground_truth[9])
    fe.feed(frames[12])
    truth = seq.ground_truth[5]
    elsewhere = Detection(Box(truth.x + 3 * truth.w, truth.y, truth.w, truth.h), 0.99, verdict=Verdict.YES)
    assert fe.apply_candidates(6, [elsewhere]) is None
    assert fe.judge_candidates(6, [elsewhere]) is None
    assert fe.stats.reinits == 1 and sum(fe.stats.decisions.values()) == 0


def _tenth_second_frames(frames: list[Frame]) -> list[Frame]:
    """The same images ten a second: 45 frames span 4.4 s of answers one a second."""
    return [Frame(f.frame_id, (f.frame_id - 1) * 0.1, f.image) for f in frames]


def test_a_trusted_track_the_detector_no_longer_finds_is_untrusted_as_not_detected(
    models_dir: Path, crossing
) -> None:  # type: ignore[no-untyped-def]
    """A box no loss signal doubts (here: the tracker on the real person) on which the answers found the
    person six times, then nothing: a 29 px person is proposed about 87 % of the time (the shipped curve),
    and this one every time so far; after four misses over 2 s "not_detected", until a candidate on the
    track confirms it."""
    seq, frames = crossing
    frames = _tenth_second_frames(frames)
    fe = _frontend(models_dir, policy="verified")
    fe.feed(frames[0])
    assert fe.start(1, seq.ground_truth[0], "person")
    results = {}
    for frame in frames[1:41]:
        results[frame.frame_id] = fe.feed(frame)
        if frame.frame_id % 3 == 0:  # an answer about the frame: the person on the track, then nothing
            box = fe.box_at(frame.frame_id)
            assert box is not None
            fe.apply_candidates(frame.frame_id, [Detection(box, 0.7)] if frame.frame_id <= 18 else [])
    lost = [k for k in range(2, 41) if not results[k].trusted]
    assert lost == [40] and results[40].lost_reason == "not_detected", [
        r.lost_reason for r in results.values()
    ]
    assert fe.stats.not_detected == 1 and fe.stats.loss_events == 1
    on_track = fe.box_at(40)
    assert on_track is not None
    assert fe.apply_candidates(40, [Detection(on_track, 0.7)]) is None  # confirmed, not re-initialised
    assert fe.feed(frames[41]).trusted and fe.stats.confirmations == 1


def test_a_candidate_on_the_track_or_a_class_without_a_curve_keeps_it_trusted(
    models_dir: Path, crossing
) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    frames = _tenth_second_frames(frames)
    for kind, found_at in (("person", {26}), ("boat", set()), ("", set())):
        fe = _frontend(models_dir, policy="verified")
        fe.feed(frames[0])
        assert fe.start(1, seq.ground_truth[0], kind)
        for frame in frames[1:45]:
            assert fe.feed(frame).trusted, (kind, frame.frame_id, fe.lost_reason)
            if frame.frame_id in (6, 16, 26, 36, 44):
                box = fe.box_at(frame.frame_id)
                assert box is not None
                fe.apply_candidates(
                    frame.frame_id, [Detection(box, 0.7)] if frame.frame_id in found_at else []
                )
        assert fe.stats.not_detected == 0, kind


def test_the_detector_miss_test_is_off_at_zero(models_dir: Path, crossing) -> None:  # type: ignore[no-untyped-def]
    seq, frames = crossing
    frames = _tenth_second_frames(frames)
    fe = TrackingFrontend.from_config(
        TrackerConfig(unsupported_miss_chance=0.0), models_dir, tracker_name="nano", policy="verified"
    )
    fe.feed(frames[0])
    assert fe.start(1, seq.ground_truth[0], "person")
    for frame in frames[1:45]:
        assert fe.feed(frame).trusted
        if frame.frame_id % 5 == 1:
            fe.apply_candidates(frame.frame_id, [])
    assert fe.stats.not_detected == 0

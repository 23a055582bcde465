"""Loss signals weighed over time (behaviors.loss_evidence), table-tested: `pytest -k loss_evidence`."""

from __future__ import annotations

import pytest

from behaviors.loss_evidence import LossEvidence, LossEvidenceSettings, judge_frame

WEAK = frozenset({"score", "collapsed", "appearance"})
ONE_S = LossEvidenceSettings(persistence_s=1.0, weak_signals=WEAK)


def run(frames: list[tuple[str, ...]], fps: float = 10.0, settings: LossEvidenceSettings = ONE_S) -> str:
    """The reasons frame by frame ('.' trusted, else the first letter of the reason)."""
    state = LossEvidence(time_s=0.0)
    out = ""
    for i, fired in enumerate(frames, start=1):
        state = judge_frame(state, i / fps, list(fired), settings)
        out += state.reason[:1] if state.reason else "."
    return out


A, S, C, J, L = ("appearance",), ("score",), ("collapsed",), ("jump",), ("left_frame",)
Q: tuple[str, ...] = ()


@pytest.mark.parametrize(
    ("name", "frames", "fps", "expected"),
    [
        ("quiet stays trusted", [Q] * 5, 10.0, "....."),
        ("a weak signal alone for a few frames is not a loss", [A, A, A, Q, Q, A, Q], 10.0, "......."),
        ("flickering weak signal never adds up", [A, Q] * 10, 10.0, "." * 20),
        # 1 s of alarm: the 10th frame at 10 fps untrusts; the same second at 30 fps takes 30 frames.
        ("a weak signal that persists 1 s untrusts", [S] * 12, 10.0, "." * 9 + "sss"),
        ("persistence is in seconds, not frames", [S] * 32, 30.0, "." * 29 + "sss"),
        ("two weak signals together untrust at once", [("score", "appearance"), Q], 10.0, "ss"),
        ("a strong signal untrusts at once", [J, Q, Q], 10.0, "jjj"),
        ("the strong signal names the box's fault", [("score", "left_frame")], 10.0, "l"),
        # After a loss the track is trusted again only after 1 s without an alarm (no flicker).
        ("recovery needs 1 s quiet", [L] + [Q] * 11, 10.0, "l" * 10 + ".."),
        # Lost at 1.0 s of evidence; 5 quiet frames leave 0.5 s, 3 alarms bring it to 0.8 s, 8 quiet frames
        # empty it.
        (
            "a weak alarm while lost keeps it lost",
            [L] + [Q] * 5 + [A] * 3 + [Q] * 12,
            10.0,
            "l" * 6 + "a" * 10 + "." * 5,
        ),
    ],
)
def test_loss_evidence_table(name: str, frames: list[tuple[str, ...]], fps: float, expected: str) -> None:
    assert run(frames, fps) == expected, name


def test_weak_signals_are_no_evidence_for_a_target_they_were_not_measured_on() -> None:
    """`weigh_weak` False (a car, a bird, a ball: `[tracker] loss_model_classes`): weak signals, alone or
    together and however long, untrust nothing; a geometric one still does."""
    objects = LossEvidenceSettings(persistence_s=1.0, weak_signals=WEAK, weigh_weak=False)
    assert run([S] * 30, settings=objects) == "." * 30
    assert run([("score", "appearance")] * 3, settings=objects) == "..."
    assert run([J, Q], settings=objects) == "jj"
    assert run([("jump", "score")], settings=objects) == "j"  # the geometric one names it
    # While lost a weak alarm no longer holds the account up: 1 s after the loss it is trusted again.
    assert run([L] + [A] * 11, settings=objects) == "l" * 10 + ".."


def test_loss_evidence_zero_persistence_is_per_frame() -> None:
    per_frame = LossEvidenceSettings(persistence_s=0.0, weak_signals=WEAK)
    assert run([A, Q, C, Q, J, Q], settings=per_frame) == "a.c.j."


def test_loss_evidence_rejects_negative_persistence_and_irregular_frames_count_time() -> None:
    with pytest.raises(ValueError, match="persistence_s"):
        LossEvidenceSettings(persistence_s=-1.0)
    # Frames arriving late: the time between them counts, not the number of frames.
    state = judge_frame(LossEvidence(time_s=0.0), 0.6, ["score"], ONE_S)
    assert state.trusted
    state = judge_frame(state, 1.2, ["score"], ONE_S)
    assert state.reason == "score"


def test_unknown_weak_loss_signal_is_refused_by_name() -> None:
    from companion.config import TrackerConfig
    from companion.vision.tracking_frontend import loss_evidence_settings

    with pytest.raises(ValueError, match=r"weak_loss_signals: unknown signal\(s\) \['apperance'\]"):
        loss_evidence_settings(TrackerConfig(weak_loss_signals=["score", "apperance"]))
    assert loss_evidence_settings(TrackerConfig()).weak_signals == frozenset(
        {"score", "collapsed", "appearance"}
    )

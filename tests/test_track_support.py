"""The detector's misses on a trusted track (behaviors.track_support), table-tested: `pytest -k track_support`."""

from __future__ import annotations

import pytest

from behaviors.track_support import SupportSettings, found_chance, judge_answer, started

SETTINGS = SupportSettings(max_miss_chance=0.001, min_unsupported_s=2.0, prior_looks=2.0)
HIT, MISS = True, False


def run(answers: list[tuple[bool, float]]) -> str:
    """Answers one a second about keyframes 1, 2, ... (`found`, the curve's POD): '.' supported, 'u' not."""
    state, out = started(0, 0.0), ""
    for second, (found, pod) in enumerate(answers, start=1):
        state = judge_answer(state, second, float(second), found, pod, SETTINGS)
        out += "u" if state.unsupported(float(second), SETTINGS) else "."
    return out


@pytest.mark.parametrize(
    ("name", "answers", "expected"),
    [
        ("found every time", [(HIT, 0.9)] * 6, "......"),
        # The track's own record decides how much a miss says: found on its last ten answers, three misses
        # of a person the curve finds 88 % of the time are a chance of 2e-4 (not 0.12^3: this one is found
        # more often than the average).
        ("a target found ten times, then missed: the third miss", [(HIT, 0.88)] * 10 + [(MISS, 0.88)] * 4, "." * 12 + "uu"),
        ("found three times: the fifth miss", [(HIT, 0.9)] * 3 + [(MISS, 0.9)] * 6, "." * 7 + "uu"),
        # With no record, the curve counts as two looks: a person in spray or shade is missed far more often
        # than the curve's average, so misses alone add up slowly (24 of them).
        ("no record: the curve alone is weak evidence", [(MISS, 0.88)] * 24, "." * 23 + "u"),
        ("a target rarely found says little by being missed", [(HIT, 0.5)] * 2 + [(MISS, 0.45)] * 12, "." * 14),
        ("one find of a large target: the third miss", [(HIT, 0.99)] + [(MISS, 0.99)] * 3, "...u"),
        ("a size the curve claims nothing for, no record: no evidence", [(MISS, 0.0)] * 30, "." * 30),
        ("a find ends the run", [(HIT, 0.88)] * 10 + [(MISS, 0.88)] * 2 + [(HIT, 0.88)] + [(MISS, 0.88)] * 2, "." * 15),
        ("a find ends an unsupported run", [(HIT, 0.88)] * 10 + [(MISS, 0.88)] * 3 + [(HIT, 0.88)], "." * 12 + "u."),
    ],
)  # fmt: skip
def test_track_support(name: str, answers: list[tuple[bool, float]], expected: str) -> None:
    assert run(answers) == expected, name


def test_track_support_counts_each_keyframe_once() -> None:
    # An early and a final answer about one keyframe, or a late answer about an older one: one look.
    state = started(0, 0.0)
    for keyframe in range(1, 11):
        state = judge_answer(state, keyframe, float(keyframe), HIT, 0.9, SETTINGS)
    for keyframe in (11, 11, 12, 10, 12, 13):
        state = judge_answer(state, keyframe, float(keyframe), MISS, 0.9, SETTINGS)
    assert (state.hits, state.misses, state.run) == (10, 3, 3) and state.unsupported(13.0, SETTINGS)


def test_a_track_started_on_a_detection_has_that_find_on_its_record() -> None:
    # A candidate's box is a look that found the target: misses of a 0.9 person then add up in eight answers,
    # not the twenty a track from an operator's box (no record) needs.
    for found, expected in ((True, 8), (False, 20)):
        state, misses = started(0, 0.0, found=found), 0
        while not state.unsupported(float(misses), SETTINGS):
            misses += 1
            state = judge_answer(state, misses, float(misses), MISS, 0.9, SETTINGS)
        assert misses == expected, found


def test_track_support_learns_the_targets_own_rate() -> None:
    state = started(0, 0.0)
    assert found_chance(state, 0.9, SETTINGS) == pytest.approx(0.9)  # no record: the curve
    for keyframe in range(1, 9):
        state = judge_answer(state, keyframe, float(keyframe), keyframe % 2 == 0, 0.9, SETTINGS)
    # Found 4 of 8: (2 * 0.9 + 4) / (2 + 8) = 0.58, nearer this target's own rate than the curve's.
    assert found_chance(state, 0.9, SETTINGS) == pytest.approx(0.58)


@pytest.mark.parametrize(
    "bad",
    [{"max_miss_chance": 0.0}, {"max_miss_chance": 1.0}, {"min_unsupported_s": -1.0}, {"prior_looks": 0.0}],
)
def test_track_support_settings_are_checked(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        SupportSettings(**bad)

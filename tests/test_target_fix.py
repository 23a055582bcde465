"""The estimate a track reports for its find (`behaviors.target_fix`), table-tested."""

from __future__ import annotations

import math

import pytest

from behaviors.geolocation import GeoEstimate, offset_to_latlon
from behaviors.target_fix import FRESHER_WITHIN, KeptFix, kept_fix


def at(north_m: float, sigma_m: float, clipped: bool = False) -> GeoEstimate:
    lat, lon = offset_to_latlon(47.0, 8.0, north_m, 0.0)
    return GeoEstimate(lat, lon, north_m, 0.0, abs(north_m), 20.0, sigma_m, clipped)


@pytest.mark.parametrize(
    ("sigmas", "reported", "why"),
    [
        ((2.0,), 0, "the first estimate"),
        ((1.0, 0.5), 1, "more precise"),
        ((0.6, 0.8), 1, "within 1.5 x the best: as good, and fresher"),
        ((0.5, 0.75), 1, "exactly 1.5 x the best"),
        ((0.6, 0.91), 0, "worse than 1.5 x the best: the view's far edge"),
        ((0.6, 3.0, 2.0, 0.85), 3, "good again after poor ones"),
        ((0.6, 0.8, 0.95, 1.2), 1, "no creeping: each later one against the best, not the one kept"),
        ((0.6, math.inf), 0, "an estimate with no bound says nothing"),
    ],
)
def test_the_freshest_estimate_nearly_as_good_as_the_best(
    sigmas: tuple[float, ...], reported: int, why: str
) -> None:
    kept = KeptFix()
    estimates = [at(float(i), s) for i, s in enumerate(sigmas)]
    for i, estimate in enumerate(estimates):
        kept = kept_fix(kept, estimate, 100.0 + i)
    assert kept.estimate == estimates[reported], why
    assert kept.time_s == 100.0 + reported, "the kept estimate's own time goes with it"
    assert kept.best_sigma_m == min(sigmas)


def test_a_followed_walking_person_is_reported_where_they_are() -> None:
    """Followed at the standoff (sigma 0.6-0.75 m, the best 0.5 m from the drone's closest look) while they
    walk 1.5 m/s for 10 s: the find is the last estimate, not the one 15 m back."""
    kept = kept_fix(KeptFix(), at(0.0, 0.5), 0.0)
    for step in range(1, 101):
        kept = kept_fix(kept, at(0.15 * step, 0.75 if step % 2 else 0.6), 0.1 * step)
    assert kept.estimate is not None and kept.estimate.north_m == pytest.approx(15.0)
    assert kept.time_s == pytest.approx(10.0)
    assert FRESHER_WITHIN * 0.5 >= 0.75


def test_a_survey_flying_away_keeps_the_good_estimate_and_its_age() -> None:
    """Seen well at t = 5 s, then only at the view's far edge as the survey flies on: the find stays the
    good estimate, and says it is from t = 5 s, not from the last frame."""
    kept = kept_fix(KeptFix(), at(0.0, 0.5), 5.0)
    for step in range(1, 30):
        kept = kept_fix(kept, at(0.5 * step, 0.5 + 0.2 * step), 5.0 + 0.1 * step)
    assert kept.estimate is not None and kept.estimate.north_m == pytest.approx(0.5)
    assert kept.time_s == pytest.approx(5.1)


@pytest.mark.parametrize(
    ("seen", "reported", "best", "why"),
    [
        (((3.7, False), (3.1, True)), 0, 3.7, "a clipped one, sharper, does not replace a whole box's"),
        (((3.7, False), (4.1, True)), 0, 3.7, "a clipped one within 1.5 x the best does not either"),
        (((3.4, True),), 0, math.inf, "a clipped one when there is nothing else"),
        (((3.4, True), (4.1, True)), 0, math.inf, "the first clipped one stays (nearest the judged view)"),
        (((3.4, True), (4.5, False)), 1, 4.5, "a whole box's replaces a clipped one, however sharp"),
        (((3.7, False), (3.1, True), (4.5, False)), 2, 3.7, "held to the whole boxes' best (1.5 x 3.7)"),
        (((3.7, False), (3.1, True), (5.6, False)), 0, 3.7, "worse than 1.5 x the whole boxes' best"),
    ],
)
def test_a_clipped_estimate_stands_only_where_the_track_has_no_other(
    seen: tuple[tuple[float, bool], ...], reported: int, best: float, why: str
) -> None:
    kept = KeptFix()
    estimates = [at(float(i), sigma, clipped) for i, (sigma, clipped) in enumerate(seen)]
    for i, estimate in enumerate(estimates):
        kept = kept_fix(kept, estimate, 100.0 + i)
    assert kept.estimate == estimates[reported], why
    assert kept.time_s == 100.0 + reported, why
    assert kept.best_sigma_m == best, why


def test_a_survey_passing_a_person_at_the_side_of_the_view_keeps_where_they_stood() -> None:
    """drone-1's first lane in a real-ArduCopter fleet run (ac3, frames 426-451): the person seen whole at the
    left of the view (sigma 3.76-3.70 m, 0.7-1.0 m off), then crossing the left edge, then gone while the
    tracker's box stayed against the edge on the ground, its estimates sliding north with the drone (8-11 m
    off at the confirmation, sigma 4.1-4.5, within 1.5 x the clipped boxes' best of 3.13). The find stays
    the last whole box's estimate (it was placed 7.9 m off)."""
    whole = [(0.91, 3.76), (0.72, 3.73), (0.97, 3.70), (1.01, 3.70)]
    crossing = [(0.70, 3.59), (0.30, 3.52), (0.73, 3.53), (0.33, 3.38), (0.26, 3.33)]
    crossing += [(0.98, 3.19), (1.42, 3.13)]
    gone = [(0.66, 3.22), (1.47, 3.35), (3.89, 3.72), (6.54, 3.97), (7.09, 4.06), (7.92, 4.11), (9.29, 4.25)]
    kept = KeptFix()
    t = 0.0
    for error_m, sigma in whole:
        kept = kept_fix(kept, at(error_m, sigma), t)
        t += 0.05
    for error_m, sigma in crossing + gone:
        kept = kept_fix(kept, at(error_m, sigma, clipped=True), t)
        t += 0.05
    assert kept.estimate is not None and kept.estimate.north_m == pytest.approx(1.01)
    assert kept.estimate.sigma_m == pytest.approx(3.70) and not kept.estimate.clipped
    assert kept.time_s == pytest.approx(0.15)

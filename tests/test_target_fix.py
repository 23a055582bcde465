"""The estimate a track reports for its find (`behaviors.target_fix`), table-tested."""

from __future__ import annotations

import math

import pytest

from behaviors.geolocation import GeoEstimate, offset_to_latlon
from behaviors.target_fix import FRESHER_WITHIN, KeptFix, kept_fix


def at(north_m: float, sigma_m: float) -> GeoEstimate:
    lat, lon = offset_to_latlon(47.0, 8.0, north_m, 0.0)
    return GeoEstimate(lat, lon, north_m, 0.0, abs(north_m), 20.0, sigma_m)


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

"""`bench --capacity`'s search for the most vehicles served (backend_tools/capacity_bench.py): doubling
from one vehicle until a fleet is not served, then bisecting the last gap; a trial is served only with
its p95 within the bound and at most 1 % of the keyframes due lost."""

from __future__ import annotations

import pytest

from backend_tools.capacity_bench import CapacitySettings, Trial, find_capacity, hardware_limit

SETTINGS = CapacitySettings(max_vehicles=64)


def _fleet_served_up_to(capacity: int) -> tuple[list[int], int]:
    tried: list[int] = []

    def trial(n: int) -> Trial:
        tried.append(n)
        served = n <= capacity
        return Trial(vehicles=n, due=100, answered=100, p95_s=0.5 if served else 2.0)

    best, trials = find_capacity(trial, SETTINGS, lambda _: None)
    assert [t.vehicles for t in trials] == sorted(tried)
    return tried, best


@pytest.mark.parametrize(
    ("capacity", "tried"),
    [
        (0, [1]),
        (1, [1, 2]),
        (4, [1, 2, 4, 8, 6, 5]),
        (5, [1, 2, 4, 8, 6, 5]),
        (7, [1, 2, 4, 8, 6, 7]),
        (40, [1, 2, 4, 8, 16, 32, 64, 48, 40, 44, 42, 41]),
        (64, [1, 2, 4, 8, 16, 32, 64]),
    ],
)
def test_capacity_search_table(capacity: int, tried: list[int]) -> None:
    assert _fleet_served_up_to(capacity) == (tried, capacity)


@pytest.mark.parametrize(
    ("trial", "served"),
    [
        (Trial(vehicles=4, due=100, answered=100, p95_s=1.0), True),
        (Trial(vehicles=4, due=100, answered=100, p95_s=1.01), False),
        (Trial(vehicles=4, due=100, answered=99, refused=1, p95_s=0.5), True),
        (Trial(vehicles=4, due=100, answered=98, refused=1, skipped=1, p95_s=0.5), False),
        (Trial(vehicles=4, due=100, answered=0, refused=0, p95_s=0.5), False),
    ],
)
def test_a_trial_is_served_within_the_p95_bound_and_losing_at_most_one_percent(
    trial: Trial, served: bool
) -> None:
    assert trial.served(SETTINGS) is served


@pytest.mark.parametrize(
    ("first", "last", "limit"), [(13.6, 26.4, 26.4), (26.4, 25.0, 26.4), (20.0, 20.0, 20.0)]
)
def test_the_hardware_limit_is_the_faster_raw_measurement(first: float, last: float, limit: float) -> None:
    """Other work on a shared machine only slows the raw detector down: the limit is the faster of the
    measurements before and after the fleets, and both are reported."""
    found = hardware_limit({"cores": 2, "keyframes_per_s": first}, {"cores": 2, "keyframes_per_s": last})
    assert found["keyframes_per_s"] == limit
    assert found["measured_keyframes_per_s"] == [first, last]

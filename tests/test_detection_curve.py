"""The detection curve's arithmetic (behaviors/detection_curve.py): the Wilson interval, the probability of
a size with thin bins, leave-one-sequence-out, and curve files refused with one line."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from behaviors.detection_curve import (
    MIN_SAMPLES,
    SIZE_EDGES_PX,
    CurveBin,
    CurveError,
    DetectionCurve,
    bin_centre,
    bin_index,
    curve_from_sequences,
    curves_document,
    curves_from_document,
    empty_bins,
    wilson_interval,
)


@pytest.mark.parametrize(
    ("successes", "trials", "low", "high"),
    [
        (0, 0, None, None),  # no trials: no interval
        (5, 10, 0.2366, 0.7634),  # symmetric around 1/2
        (0, 10, 0.0, 0.2775),  # none found still leaves room above
        (10, 10, 0.7225, 1.0),
        (80, 100, 0.7112, 0.8666),
    ],
)
def test_wilson_interval(successes: int, trials: int, low: float | None, high: float | None) -> None:
    interval = wilson_interval(successes, trials)
    if low is None:
        assert interval is None
        return
    assert interval is not None
    assert interval == pytest.approx((low, high), abs=1e-4)
    assert interval[0] <= successes / trials <= interval[1]


def test_size_edges_are_half_octaves_from_8_px() -> None:
    assert SIZE_EDGES_PX[0] == 0 and math.isinf(SIZE_EDGES_PX[-1])
    assert SIZE_EDGES_PX[1] == 8 and SIZE_EDGES_PX[3] == 16 and SIZE_EDGES_PX[-2] == 128
    inner = SIZE_EDGES_PX[1:-1]
    assert all(b / a == pytest.approx(math.sqrt(2)) for a, b in zip(inner, inner[1:], strict=False))


@pytest.mark.parametrize(
    ("size", "index"),
    [
        (0.0, 0),
        (7.99, 0),
        (8.0, 1),
        (16.0, 3),
        (127.9, 8),
        (128.0, 9),
        (1e6, 9),
        (-1.0, None),
        (math.nan, None),
    ],
)
def test_bin_index(size: float, index: int | None) -> None:
    assert bin_index(empty_bins(), size) == index


def _curve(counts: dict[int, tuple[int, int, int, int]], name: str = "person") -> DetectionCurve:
    """A curve with [samples, proposed, yes, uncertain] in the bins given by index, the rest empty."""
    bins = tuple(
        CurveBin(b.lo_px, b.hi_px, *counts[i]) if i in counts else b for i, b in enumerate(empty_bins())
    )
    return DetectionCurve(name, bins)


CURVE = _curve({2: (20, 10, 4, 2), 3: (5, 5, 5, 0), 4: (40, 36, 30, 4), 6: (12, 12, 12, 0)})


def _logistic(size: float, size50: float, slope: float) -> float:
    return 1.0 / (1.0 + (size50 / size) ** slope)


def _from_truth(size50: float, slope: float, frames: int = 100_000) -> DetectionCurve:
    """A curve whose bins hold `frames` frames each, found as often as the true curve says at their centre."""
    return _curve(
        {
            i: (frames, frames, round(frames * _logistic(bin_centre(b), size50, slope)), 0)
            for i, b in enumerate(empty_bins())
            if 1 <= i <= 8
        }
    )


@pytest.mark.parametrize(("size50", "slope"), [(18.0, 2.0), (30.0, 4.0), (12.0, 1.2)])
def test_the_fit_finds_the_curve_the_frames_came_from(size50: float, slope: float) -> None:
    """Johnson's target transfer function, (N/N50)^E / (1 + (N/N50)^E), comes back from its own counts."""
    curve = _from_truth(size50, slope)
    fit = curve.fit()
    assert fit is not None and fit.size50_px == pytest.approx(size50, rel=0.01)
    assert fit.slope == pytest.approx(slope, rel=0.01)
    for size in (9.0, 14.0, 25.0, 60.0, 300.0):
        assert curve.probability(size) == pytest.approx(_logistic(size, size50, slope), abs=0.01)


@pytest.mark.parametrize(
    ("size", "accept_uncertain", "expected"),
    [
        (4.0, False, 0.0),  # below the smallest bin of MIN_SAMPLES frames: the curve claims nothing
        (math.nan, False, 0.0),
        (12.0, False, 0.21),
        (12.0, True, 0.28),  # the uncertain ones counted too: higher everywhere
        (30.0, False, 0.82),
        (30.0, True, 0.89),
        (70.0, False, 0.985),  # a bigger target is never harder to find
        (1000.0, False, 1.0),
    ],
)
def test_probability_is_the_fit_through_every_bin(
    size: float, accept_uncertain: bool, expected: float
) -> None:
    assert CURVE.probability(size, accept_uncertain) == pytest.approx(expected, abs=0.01)


def test_a_thin_bin_counts_in_the_fit_but_claims_nothing_below_the_first_full_one() -> None:
    thin_first = _curve({2: (MIN_SAMPLES - 1, 9, 9, 0), 3: (MIN_SAMPLES, 5, 5, 0)})
    assert thin_first.probability(12.0) == 0.0  # one frame short of speaking for its own sizes
    assert thin_first.probability(20.0) > 0.5  # its 9 of 9 lift the fit above the 5 of 10 there
    assert _curve({2: (MIN_SAMPLES - 1, 9, 9, 0)}).fit() is None


@pytest.mark.parametrize(
    ("counts", "found"),
    [
        ({2: (40, 40, 36, 0), 4: (40, 40, 4, 0)}, 40 / 80),  # found less as they grow: flat at the share
        ({2: (40, 40, 40, 0), 4: (40, 40, 40, 0)}, 1.0),  # all found: near 1, never off to infinity
        ({2: (40, 0, 0, 0), 4: (40, 0, 0, 0)}, 0.0),  # none found
    ],
)
def test_the_fit_is_never_falling_nor_infinite(
    counts: dict[int, tuple[int, int, int, int]], found: float
) -> None:
    curve = _curve(counts)
    fit = curve.fit()
    assert fit is not None and fit.slope >= 0 and math.isfinite(fit.intercept)
    assert curve.probability(20.0) == pytest.approx(found, abs=0.03)


def test_table_and_share() -> None:
    assert CURVE.table() == [CURVE.probability(bin_centre(b)) for b in CURVE.bins]
    assert CURVE.samples == 77
    assert CURVE.share() == pytest.approx(51 / 77)
    assert CURVE.share(True) == pytest.approx(57 / 77)
    assert DetectionCurve("person", empty_bins()).share() == 0.0
    assert DetectionCurve("person", empty_bins()).probability(30.0) == 0.0


def test_counting_one_frame() -> None:
    b = CurveBin(8.0, 16.0)
    b = b.counting(False, None).counting(True, "no").counting(True, "yes").counting(True, "uncertain")
    assert (b.samples, b.proposed, b.yes, b.uncertain) == (4, 3, 1, 1)


def test_curve_from_sequences_and_without() -> None:
    a = _curve({4: (30, 30, 30, 0)}).bins
    b = _curve({2: (20, 4, 2, 1), 4: (10, 2, 0, 1)}).bins
    curve = curve_from_sequences("person", {"a": a, "b": b}, {"tiles": "2"})
    assert curve.bins[4].samples == 40 and curve.bins[4].yes == 30 and curve.bins[4].uncertain == 1
    assert dict(curve.configuration) == {"tiles": "2"}
    without_a = curve.without("a")
    assert without_a.bins == b and [name for name, _ in without_a.sequences] == ["b"]
    assert without_a.probability(30.0) == DetectionCurve("person", b).probability(30.0)
    assert without_a.probability(30.0) < 0.1 < curve.probability(30.0)  # b's own frames found little
    assert curve.without("a").without("b").samples == 0
    assert curve.without("unknown") is curve
    with pytest.raises(CurveError, match="at least one sequence"):
        curve_from_sequences("person", {})


def test_round_trip_through_a_document() -> None:
    a = _curve({4: (30, 30, 28, 1)}).bins
    b = _curve({2: (20, 4, 2, 1)}).bins
    curve = curve_from_sequences("person", {"a": a, "b": b}, {"detector": "yolox"})
    document = json.loads(json.dumps(curves_document({"person": curve}, note="x")))
    again = curves_from_document(document)["person"]
    assert again.configuration == curve.configuration
    assert [(x.samples, x.proposed, x.yes, x.uncertain) for x in again.bins] == [
        (x.samples, x.proposed, x.yes, x.uncertain) for x in curve.bins
    ]
    assert [x.lo_px for x in again.bins] == pytest.approx([x.lo_px for x in curve.bins], abs=1e-3)
    assert math.isinf(again.bins[-1].hi_px)
    assert again.without("a").probability(14.0) == curve.without("a").probability(14.0)
    assert again.table() == pytest.approx(curve.table(), abs=1e-4)  # edges kept to 1e-3 px


def _good() -> dict[str, Any]:
    return curve_from_sequences("person", {"a": _curve({4: (30, 30, 28, 1)}).bins}).to_dict()


def _bad(change: Any) -> dict[str, Any]:
    data = _good()
    change(data)
    return data


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ([], "a curve must be an object"),
        (_bad(lambda d: d.update(target_class="")), "target_class must be a name"),
        (_bad(lambda d: d.update(bins=[])), "bins must be a list of 1-"),
        (_bad(lambda d: d.update(bins="x")), "bins must be a list"),
        (_bad(lambda d: d["bins"].__setitem__(0, 3)), "a bin must be an object"),
        (_bad(lambda d: d["bins"][0].update(lo_px="0")), "lo_px must be a finite number"),
        (_bad(lambda d: d["bins"][1].update(lo_px=9.0)), "bins must follow each other"),
        (_bad(lambda d: d["bins"][0].update(hi_px=0.0)), "0 <= lo_px < hi_px"),
        (_bad(lambda d: d["bins"][0].update(samples=-1)), "samples must be a count"),
        (_bad(lambda d: d["bins"][0].update(samples=1.5)), "samples must be a count"),
        (_bad(lambda d: d["bins"][0].update(samples=True)), "samples must be a count"),
        (_bad(lambda d: d["bins"][4].update(yes=31)), "yes \\+ uncertain <= proposed <= samples"),
        (_bad(lambda d: d.update(configuration=[1])), "configuration must be an object"),
        (_bad(lambda d: d.update(sequences=[])), "sequences must be an object"),
        (_bad(lambda d: d["sequences"].update(a=[[0, 0, 0, 0]])), "one row of counts per bin"),
        (_bad(lambda d: d["sequences"]["a"].__setitem__(4, [30, 30])), "counts are \\[samples"),
        (_bad(lambda d: d["sequences"]["a"].__setitem__(4, [40, 30, 28, 1])), "do not add up"),
        (_bad(lambda d: d["sequences"].update(b=d["sequences"]["a"])), "do not add up"),
    ],
)
def test_from_dict_refuses_with_one_line(data: Any, message: str) -> None:
    with pytest.raises(CurveError, match=message) as info:
        DetectionCurve.from_dict(data)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("document", "message"),
    [
        ({"format": "other", "curves": {}}, "not a detection curve file"),
        ({"format": "cloudtrack-detection-curve/1", "curves": {}}, "curves must be an object"),
        ({"format": "cloudtrack-detection-curve/1", "curves": {"car": _good()}}, "names class 'person'"),
        ([], "not a detection curve file"),
    ],
)
def test_document_refusals(document: Any, message: str) -> None:
    with pytest.raises(CurveError, match=message) as info:
        curves_from_document(document)
    assert "\n" not in str(info.value)

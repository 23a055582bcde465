"""The detection curve: how likely the search is to find the described target, by its size in the keyframe.

Measured on real footage with ground truth (`cloudtrack-backend pod-curve`): for every frame where the
target is visible, its size (sqrt(w * h) of its box in keyframe pixels, the frame downscaled as the
companion downscales keyframes) and what the back-end made of it: not proposed, or proposed as a
candidate with the verifier's verdict. A bin counts those frames; the probability of detection (POD) at a
size is the share of its bin's frames where the target was proposed and judged the way the mission acts
on: "yes", or also "uncertain" where the mission accepts it (`[behavior] accept_uncertain`). "yes" counts
what the mission acts on by default (`candidate_selection.may_start`): a "yes", and an "uncertain" it
starts on anyway (nothing in the description the verifier could judge, or singled out by its rank).

Bins are half octaves of size from 8 px (a rule fixed before any data was seen, so a new data set falls
into the same bins); they count frames and print the table. The POD at a size is not a bin's own share:
a bin holds the frames of one or two sequences as often as of many, so its share is one target's luck.
It is the curve fitted through all of them in the form target acquisition models give detection by size
(the target transfer probability function of Johnson's criteria and NVThermIP, P = (N/N50)^E /
(1 + (N/N50)^E), N the cycles across the target: here its size in pixels), a logistic in log size, fitted
by maximum likelihood on the bins' counts at their centres with half a frame found and half missed added
to each bin (so a bin of all found or none does not run the fit off to infinity) and a slope never below 0
(a bigger target is never harder to find). Below the smallest bin with `MIN_SAMPLES` frames the curve
claims nothing (0). The per-sequence counts are kept so a sequence can be predicted from a curve fitted
without it (`without`: leave-one-sequence-out).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

FORMAT = "cloudtrack-detection-curve/1"
# Half octaves from 8 px: 8, 11.3, 16, 22.6, 32, 45.3, 64, 90.5, 128 px, open-ended at both ends.
SIZE_EDGES_PX: tuple[float, ...] = (0.0, *(8.0 * 2.0 ** (k / 2) for k in range(9)), math.inf)
MIN_SAMPLES = 10  # frames a bin needs before its share is used
MAX_BINS = 64
MAX_SEQUENCES = 1000
MAX_CONFIG_ITEMS = 64


class CurveError(ValueError):
    """A curve file that is not one: one line saying what is wrong."""


@dataclass(frozen=True)
class CurveBin:
    """Frames whose target size fell in [lo_px, hi_px): how many, and what became of the target in them."""

    lo_px: float
    hi_px: float
    samples: int = 0  # frames with the target visible
    proposed: int = 0  # ... where a candidate was the target (any verdict)
    yes: int = 0  # ... acted on by default (judged "yes", or an "uncertain" the mission starts on anyway)
    uncertain: int = 0  # ... judged "uncertain", acted on only with accept_uncertain

    def found(self, accept_uncertain: bool = False) -> int:
        return self.yes + (self.uncertain if accept_uncertain else 0)

    def probability(self, accept_uncertain: bool = False) -> float | None:
        """The bin's share of frames found; None without frames."""
        return self.found(accept_uncertain) / self.samples if self.samples else None

    def interval(self, accept_uncertain: bool = False, z: float = 1.96) -> tuple[float, float] | None:
        """Wilson score interval of the share (95 % by default); None without frames."""
        return wilson_interval(self.found(accept_uncertain), self.samples, z)

    def counting(self, proposed: bool, verdict: str | None) -> CurveBin:
        """This bin with one more frame: the target proposed or not, and the verifier's verdict on it
        ("yes", "no", "uncertain"; None when not proposed)."""
        return replace(
            self,
            samples=self.samples + 1,
            proposed=self.proposed + proposed,
            yes=self.yes + (proposed and verdict == "yes"),
            uncertain=self.uncertain + (proposed and verdict == "uncertain"),
        )

    def plus(self, other: CurveBin, sign: int = 1) -> CurveBin:
        return replace(
            self,
            samples=self.samples + sign * other.samples,
            proposed=self.proposed + sign * other.proposed,
            yes=self.yes + sign * other.yes,
            uncertain=self.uncertain + sign * other.uncertain,
        )


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float] | None:
    """The Wilson score interval of a binomial share; None for no trials."""
    if trials <= 0:
        return None
    p = successes / trials
    denominator = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denominator
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


@dataclass(frozen=True)
class CurveFit:
    """P(size) = 1 / (1 + exp(-(intercept + slope * ln size))), claimed from `min_size_px` up; with a
    slope, the same as (size / size50)^slope / (1 + (size / size50)^slope)."""

    intercept: float
    slope: float
    min_size_px: float

    def probability(self, size_px: float) -> float:
        z = self.intercept + self.slope * math.log(max(size_px, 1e-9))
        return 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0

    @property
    def size50_px(self) -> float | None:
        """The size found half the time (N50); None for a flat curve."""
        return math.exp(-self.intercept / self.slope) if self.slope > 0 else None


def bin_centre(b: CurveBin) -> float:
    """Where a bin's frames stand on the size axis: the geometric middle of its edges (the open-ended first
    and last bins: half an octave inside their one edge)."""
    if b.lo_px <= 0:
        return b.hi_px / math.sqrt(2.0)
    if math.isinf(b.hi_px):
        return b.lo_px * math.sqrt(2.0)
    return math.sqrt(b.lo_px * b.hi_px)


def fit_curve(bins: Sequence[CurveBin], accept_uncertain: bool = False) -> CurveFit | None:
    """The maximum-likelihood logistic in log size through the bins' counts (module doc), by Newton's
    method on the two parameters, the slope held at 0 or above; None without a bin of MIN_SAMPLES frames."""
    measured = [b for b in bins if b.samples >= MIN_SAMPLES]
    if not measured:
        return None
    rows = [
        (math.log(bin_centre(b)), b.found(accept_uncertain) + 0.5, b.samples + 1.0) for b in bins if b.samples
    ]
    share = sum(k for _, k, _ in rows) / sum(n for _, _, n in rows)
    intercept, slope = math.log(share / (1 - share)), 0.0
    for _ in range(100):
        g0 = g1 = h00 = h01 = h11 = 0.0
        for x, k, n in rows:
            p = 1.0 / (1.0 + math.exp(-(intercept + slope * x)))
            w = n * p * (1 - p)
            g0 += k - n * p
            g1 += (k - n * p) * x
            h00, h01, h11 = h00 + w, h01 + w * x, h11 + w * x * x
        det = h00 * h11 - h01 * h01
        if det <= 1e-12:
            break
        step0, step1 = (h11 * g0 - h01 * g1) / det, (h00 * g1 - h01 * g0) / det
        intercept, slope = intercept + step0, slope + step1
        if slope < 0:  # the best monotone curve is flat: the share of all frames
            intercept, slope = math.log(share / (1 - share)), 0.0
            break
        if abs(step0) + abs(step1) < 1e-10:
            break
    return CurveFit(intercept, slope, min(b.lo_px for b in measured))


def empty_bins(edges: Sequence[float] = SIZE_EDGES_PX) -> tuple[CurveBin, ...]:
    return tuple(CurveBin(lo, hi) for lo, hi in zip(edges, edges[1:], strict=False))


def bin_index(bins: Sequence[CurveBin], size_px: float) -> int | None:
    """The bin a size falls in; None for a size that is not a finite non-negative number."""
    if not math.isfinite(size_px) or size_px < 0:
        return None
    for i, b in enumerate(bins):
        if b.lo_px <= size_px < b.hi_px:
            return i
    return None


@dataclass(frozen=True)
class DetectionCurve:
    """One target class's curve and the configuration it was measured for (detector, tiling, score
    threshold, keyframe width, verifier): a different configuration is a different curve."""

    target_class: str
    bins: tuple[CurveBin, ...]
    configuration: tuple[tuple[str, str], ...] = ()
    sequences: tuple[tuple[str, tuple[CurveBin, ...]], ...] = ()

    def probability(self, size_px: float, accept_uncertain: bool = False) -> float:
        """POD of one look at a target of `size_px` keyframe pixels: the fitted curve (module doc)."""
        fit = self.fit(accept_uncertain)
        if fit is None or not math.isfinite(size_px) or size_px < fit.min_size_px:
            return 0.0
        return fit.probability(size_px)

    def fit(self, accept_uncertain: bool = False) -> CurveFit | None:
        """The curve through the bins (None without a bin of `MIN_SAMPLES` frames)."""
        return self._fits[1 if accept_uncertain else 0]

    @cached_property
    def _fits(self) -> tuple[CurveFit | None, CurveFit | None]:
        return fit_curve(self.bins, False), fit_curve(self.bins, True)

    def table(self, accept_uncertain: bool = False) -> list[float]:
        """`probability` at each bin's centre."""
        return [self.probability(bin_centre(b), accept_uncertain) for b in self.bins]

    def without(self, sequence: str) -> DetectionCurve:
        """The curve fitted without one sequence's frames (itself when it holds none of them)."""
        theirs = dict(self.sequences).get(sequence)
        if theirs is None:
            return self
        bins = tuple(mine.plus(other, -1) for mine, other in zip(self.bins, theirs, strict=True))
        return replace(self, bins=bins, sequences=tuple(s for s in self.sequences if s[0] != sequence))

    @property
    def samples(self) -> int:
        return sum(b.samples for b in self.bins)

    def share(self, accept_uncertain: bool = False) -> float:
        """The share of all frames found, whatever their size (the size-blind figure); 0 without frames."""
        found = sum(b.found(accept_uncertain) for b in self.bins)
        return found / self.samples if self.samples else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "target_class": self.target_class,
            "configuration": dict(self.configuration),
            "bins": [_bin_dict(b) for b in self.bins],
            "sequences": {name: [_counts(b) for b in bins] for name, bins in self.sequences},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DetectionCurve:
        """A curve from `to_dict`'s shape; CurveError naming the first thing wrong."""
        if not isinstance(data, Mapping):
            raise CurveError("a curve must be an object")
        name = data.get("target_class")
        if not isinstance(name, str) or not 0 < len(name) <= 64:
            raise CurveError("target_class must be a name of 1-64 characters")
        raw_bins = data.get("bins")
        if not isinstance(raw_bins, list) or not 0 < len(raw_bins) <= MAX_BINS:
            raise CurveError(f"{name}: bins must be a list of 1-{MAX_BINS} bins")
        bins = tuple(_bin(name, raw) for raw in raw_bins)
        for a, b in zip(bins, bins[1:], strict=False):
            if a.hi_px != b.lo_px:
                raise CurveError(f"{name}: bins must follow each other ({a.hi_px} then {b.lo_px})")
        config = data.get("configuration", {})
        if not isinstance(config, Mapping) or len(config) > MAX_CONFIG_ITEMS:
            raise CurveError(f"{name}: configuration must be an object of at most {MAX_CONFIG_ITEMS} items")
        raw_sequences = data.get("sequences", {})
        if not isinstance(raw_sequences, Mapping) or len(raw_sequences) > MAX_SEQUENCES:
            raise CurveError(f"{name}: sequences must be an object of at most {MAX_SEQUENCES} sequences")
        sequences = []
        for seq, rows in raw_sequences.items():
            if not isinstance(rows, list) or len(rows) != len(bins):
                raise CurveError(f"{name}: sequence {str(seq)[:60]!r} needs one row of counts per bin")
            sequences.append(
                (str(seq), tuple(_with_counts(name, b, row) for b, row in zip(bins, rows, strict=True)))
            )
        if sequences:
            # `without` subtracts a sequence's counts: counts that do not add up would turn negative there.
            summed = _summed(bins, [rows for _, rows in sequences])
            if [_counts(b) for b in summed] != [_counts(b) for b in bins]:
                raise CurveError(f"{name}: the sequences' counts do not add up to the bins' counts")
        return cls(
            name,
            bins,
            tuple((str(k), str(v)) for k, v in config.items()),
            tuple(sequences),
        )


def curve_from_sequences(
    target_class: str,
    per_sequence: Mapping[str, Sequence[CurveBin]],
    configuration: Mapping[str, str] | None = None,
) -> DetectionCurve:
    """One class's curve from its sequences' bins (all with the same edges): the bins are their sums."""
    rows = list(per_sequence.values())
    if not rows:
        raise CurveError(f"{target_class}: a curve needs at least one sequence")
    bins = _summed(tuple(replace(b, samples=0, proposed=0, yes=0, uncertain=0) for b in rows[0]), rows)
    return DetectionCurve(
        target_class,
        bins,
        tuple((str(k), str(v)) for k, v in (configuration or {}).items()),
        tuple((name, tuple(b)) for name, b in per_sequence.items()),
    )


def _summed(bins: Sequence[CurveBin], rows: Sequence[Sequence[CurveBin]]) -> tuple[CurveBin, ...]:
    """The bins' edges with the rows' counts added up."""
    total = [replace(b, samples=0, proposed=0, yes=0, uncertain=0) for b in bins]
    for row in rows:
        total = [t.plus(b) for t, b in zip(total, row, strict=True)]
    return tuple(total)


def _counts(b: CurveBin) -> list[int]:
    return [b.samples, b.proposed, b.yes, b.uncertain]


def _bin_dict(b: CurveBin) -> dict[str, Any]:
    return {
        "lo_px": round(b.lo_px, 3),
        "hi_px": None if math.isinf(b.hi_px) else round(b.hi_px, 3),
        "samples": b.samples,
        "proposed": b.proposed,
        "yes": b.yes,
        "uncertain": b.uncertain,
    }


def _number(name: str, value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CurveError(f"{name}: {what} must be a finite number")
    return float(value)


def _count(name: str, value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 10**9:
        raise CurveError(f"{name}: {what} must be a count (a whole number >= 0)")
    return value


def _bin(name: str, raw: Any) -> CurveBin:
    if not isinstance(raw, Mapping):
        raise CurveError(f"{name}: a bin must be an object")
    lo = _number(name, raw.get("lo_px"), "lo_px")
    hi_raw = raw.get("hi_px")
    hi = math.inf if hi_raw is None else _number(name, hi_raw, "hi_px")
    if not 0 <= lo < hi:
        raise CurveError(f"{name}: a bin needs 0 <= lo_px < hi_px")
    return _with_counts(
        name, CurveBin(lo, hi), [raw.get(k) for k in ("samples", "proposed", "yes", "uncertain")]
    )


def _with_counts(name: str, b: CurveBin, row: Any) -> CurveBin:
    if not isinstance(row, list) or len(row) != 4:
        raise CurveError(f"{name}: counts are [samples, proposed, yes, uncertain]")
    samples, proposed, yes, uncertain = (
        _count(name, v, k) for v, k in zip(row, ("samples", "proposed", "yes", "uncertain"), strict=True)
    )
    if not yes + uncertain <= proposed <= samples:
        raise CurveError(f"{name}: counts need yes + uncertain <= proposed <= samples")
    return replace(b, samples=samples, proposed=proposed, yes=yes, uncertain=uncertain)


def curves_from_document(data: Any) -> dict[str, DetectionCurve]:
    """Every class's curve in a curve file's document (`{"format", "curves": {class: curve}}`)."""
    if not isinstance(data, Mapping) or data.get("format") != FORMAT:
        raise CurveError(f"not a detection curve file (format must be {FORMAT!r})")
    curves = data.get("curves")
    if not isinstance(curves, Mapping) or not curves:
        raise CurveError("curves must be an object of class -> curve")
    out = {}
    for key, raw in curves.items():
        curve = DetectionCurve.from_dict(raw)
        if curve.target_class != key:
            raise CurveError(f"curve {str(key)[:60]!r} names class {curve.target_class!r}")
        out[curve.target_class] = curve
    return out


def curves_document(curves: Mapping[str, DetectionCurve], **extra: Any) -> dict[str, Any]:
    return {"format": FORMAT, **extra, "curves": {name: c.to_dict() for name, c in curves.items()}}

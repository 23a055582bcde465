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
into the same bins). A bin with fewer than `MIN_SAMPLES` frames says nothing on its own: it takes the
value of the nearest smaller bin that does (a smaller target is never easier to find), and below the
smallest such bin the curve claims nothing (0). The per-sequence counts are kept so a sequence can be
predicted from a curve fitted without it (`without`: leave-one-sequence-out).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
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
        """POD of one look at a target of `size_px` keyframe pixels (see the module doc for thin bins)."""
        i = bin_index(self.bins, size_px)
        if i is None:
            return 0.0
        for b in reversed(self.bins[: i + 1]):
            if b.samples >= MIN_SAMPLES:
                return b.found(accept_uncertain) / b.samples
        return 0.0

    def table(self, accept_uncertain: bool = False) -> list[float]:
        """`probability` at each bin (what a lookup returns for a size in that bin)."""
        return [self.probability(b.lo_px, accept_uncertain) for b in self.bins]

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

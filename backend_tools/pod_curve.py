"""The detection curve (`behaviors.detection_curve`) measured on sequences with ground truth, and checked
on sequences it was not fitted on (the command: `backend_tools.pod_curve_command`).

Every frame where the ground truth shows the target goes through what a keyframe goes through: the
companion's downscaling and JPEG (`cloudtrack.api_client.encode_keyframe`), the back-end's decoding and its
own pipeline as configured (`[detector]`, `[verifier]`, `[crops]`: detection of the prompt's superset,
margin crops, verification against the sequence's `referring.txt`), as `/v1/detect` runs it.

A candidate is the target (`is_target`) when it overlaps the ground-truth box by IoU >= 0.5 (as
`detector_recall`), or when the ground-truth box holds it (90 % of it inside) and it spans a quarter of
that box: tracking ground truth boxes a target with what it rides or carries (a cyclist with the bicycle,
a surfer with the board), the detector boxes the person alone (uav123_bike1 close up: the rider's box
96-100 % inside, IoU 0.3-0.5). The target is found where the mission acts on one of its candidates
(`behaviors.candidate_selection.may_start`): counted as "yes" when it does so by default (a "yes", or an
"uncertain" nothing in the description could judge, or one the description's rank singles out), as
"uncertain" when only `[behavior] accept_uncertain` would.

Frames of one sequence are one target under one description: they are not independent samples, and the
look-dependence figure (`look_dependence`) says how far from it they are.

A keyframe too dark for the curve (`behaviors.scene_light`: mean luma two stops under mid-grey, measured on
the keyframe as the companion measures it, `cloudtrack.keyframe_light`) is measured but kept apart: it is
in no bin, no fit and no check, and is reported on its own (`low_light`), because the companion's map
claims nothing for such a keyframe either.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from backend.config import BackendConfig
from backend.detectors.factory import CLOSED_SET_WEIGHTS, build_detector, closed_set_weights
from backend.images import decode_image
from backend.pipeline import Pipeline
from backend.supersets import superset_from_prompt
from backend.verifiers.factory import build_verifier
from behaviors.candidate_selection import may_start
from behaviors.detection import Verdict
from behaviors.detection_curve import (
    MIN_SAMPLES,
    CurveBin,
    DetectionCurve,
    bin_index,
    curve_from_sequences,
    empty_bins,
)
from behaviors.geometry import Box, iou
from behaviors.scene_light import MIN_MEAN_LUMA, too_dark
from cloudtrack.api_client import encode_keyframe
from cloudtrack.keyframe_light import mean_luma

MATCH_IOU = 0.5
HELD_INSIDE = 0.9  # share of a candidate's box inside the ground truth's, for a target boxed with its ride
HELD_SPAN = 0.25  # ... and the least share of the ground truth's area it then spans
DEFAULT_FPS = 30.0  # a sequence whose source.json names no frame rate
LOOK_GAP_S = 0.5  # looks this far apart at the same target: what one pass over a place gives
MAX_GROUNDTRUTH_BYTES = 10_000_000
MAX_TEXT_BYTES = 100_000  # referring.txt, source.json


class SequenceError(ValueError):
    """A sequence folder that cannot be measured: one line naming the file and what is wrong."""


@dataclass(frozen=True)
class Look:
    """One frame with the target in view: its size in keyframe pixels and what the back-end made of it."""

    frame: int  # index in the sequence
    size_px: float  # sqrt(w * h) of the ground-truth box in the keyframe's pixels
    proposed: bool  # a candidate was the target
    verdict: str | None  # "yes": the mission acts on it by default; "uncertain": only when accepting
    # uncertain ones; "no": judged no; None: not proposed
    verifier_yes: bool = False  # the verifier itself said "yes" (the rest of "yes" is uncertain, acted on)
    verifier_failed: bool = False  # a verdict on it came from a timeout or a failed verifier
    mean_luma: float = 255.0  # the keyframe's (cloudtrack.keyframe_light)

    def found(self, accept_uncertain: bool) -> bool:
        return self.verdict == "yes" or (accept_uncertain and self.verdict == "uncertain")


@dataclass(frozen=True)
class SequenceLooks:
    name: str
    superset: str
    fps: float
    step: int
    looks: tuple[Look, ...]  # lit well enough for the curve: the frames it is fitted and checked on
    dark: tuple[Look, ...] = ()  # too dark for it (module doc)

    def summary(self) -> dict[str, Any]:
        """Its frames, and how many the verifier itself said "yes" to (beside the curve's "yes", which also
        counts the "uncertain" ones the mission acts on); the low-light frames apart."""
        return {
            "class": self.superset,
            "fps": self.fps,
            "frames": len(self.looks),
            "proposed": sum(look.proposed for look in self.looks),
            "found": sum(look.verdict == "yes" for look in self.looks),
            "verifier_yes": sum(look.verifier_yes for look in self.looks),
            "low_light": low_light(self.dark),
        }

    def bins(self) -> tuple[CurveBin, ...]:
        bins = list(empty_bins())
        for look in self.looks:
            i = bin_index(bins, look.size_px)
            if i is not None:
                bins[i] = bins[i].counting(look.proposed, look.verdict)
        return tuple(bins)


@dataclass(frozen=True)
class SequenceSource:
    path: Path
    prompt: str
    superset: str
    fps: float
    boxes: tuple[Box | None, ...]
    frames: tuple[Path, ...]


def _read_text(path: Path, limit: int) -> str:
    try:
        with open(path, "rb") as f:
            raw = f.read(limit + 1)
    except OSError as exc:
        raise SequenceError(f"{path}: {exc.strerror or exc}") from None
    if len(raw) > limit:
        raise SequenceError(f"{path}: larger than {limit} bytes")
    try:
        return raw.decode()
    except UnicodeDecodeError:
        raise SequenceError(f"{path}: not UTF-8 text") from None


def _groundtruth(path: Path) -> tuple[Box | None, ...]:
    """x,y,w,h per frame (commas or tabs); nan, or a box without area, where the target is not in view."""
    boxes: list[Box | None] = []
    for number, line in enumerate(_read_text(path, MAX_GROUNDTRUTH_BYTES).splitlines(), 1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in re.split(r"[,\t ]+", line.strip())[:4]]
        except ValueError:
            values = []
        if len(values) != 4:
            raise SequenceError(f"{path} line {number}: expected x,y,w,h (nan where the target is absent)")
        visible = all(math.isfinite(v) for v in values) and values[2] > 0 and values[3] > 0
        boxes.append(Box(*values) if visible else None)
    return tuple(boxes)


def _fps(path: Path) -> float:
    """The sequence's frame rate: source.json's `fps`, else an "N fps" in its `dataset` line (UAV123's
    10 fps subset says so there), else DEFAULT_FPS."""
    if not path.is_file():
        return DEFAULT_FPS
    try:
        source = json.loads(_read_text(path, MAX_TEXT_BYTES))
    except ValueError:
        raise SequenceError(f"{path}: not JSON") from None
    if not isinstance(source, dict):
        return DEFAULT_FPS
    fps = source.get("fps")
    if isinstance(fps, (int, float)) and not isinstance(fps, bool) and 0 < fps <= 1000:
        return float(fps)
    said = re.search(r"(\d+(?:\.\d+)?)\s*fps", str(source.get("dataset", "")))
    return float(said.group(1)) if said and 0 < float(said.group(1)) <= 1000 else DEFAULT_FPS


def read_sequence(path: Path) -> SequenceSource:
    """A sequence folder: frames/*.jpg, groundtruth.txt, referring.txt (the prompt), source.json (optional)."""
    if not path.is_dir():
        raise SequenceError(f"{path}: not a sequence folder")
    prompt = " ".join(_read_text(path / "referring.txt", MAX_TEXT_BYTES).split())
    superset = superset_from_prompt(prompt) if prompt else None
    if not superset:
        raise SequenceError(f"{path / 'referring.txt'}: names no class the detector knows")
    frames = tuple(sorted((path / "frames").glob("*.jpg")))
    if not frames:
        raise SequenceError(f"{path / 'frames'}: no .jpg frames")
    return SequenceSource(
        path, prompt, superset, _fps(path / "source.json"), _groundtruth(path / "groundtruth.txt"), frames
    )


def build_pipeline(config: BackendConfig, pool: ThreadPoolExecutor) -> Pipeline:
    """The back-end's pipeline as `backend.app.create_app` builds it from the configuration."""
    return Pipeline.configured(
        config, build_detector(config.detector), build_verifier(config.verifier, config.vlm), pool
    )


def configuration(config: BackendConfig, keyframe_width: int, jpeg_quality: int) -> dict[str, str]:
    """What a curve was measured for: another detector, tiling, threshold, keyframe or verifier is another
    curve."""
    d = config.detector
    out: dict[str, str] = {"detector": d.kind}
    if d.kind in CLOSED_SET_WEIGHTS:
        weights = closed_set_weights(d)
        out["model_file"] = f"{weights.parent.name}/{weights.name}"
        out["model_sha256"] = hashlib.sha256(weights.read_bytes()).hexdigest()
        if d.open_vocabulary:
            out["open_vocabulary"] = f"{d.open_vocabulary} {d.hf_model}".strip()
    else:
        out["model_file"] = d.hf_model
    out |= {
        "tiles": str(d.tiles),
        "tile_overlap": str(d.tile_overlap),
        "score_threshold": str(d.score_threshold),
        "nms_threshold": str(d.nms_threshold),
        "max_candidates": str(d.max_candidates),
        "keyframe_width": str(keyframe_width),
        "jpeg_quality": str(jpeg_quality),
        "verifier": config.verifier.kind,
        "crop_margin_px": str(config.crops.margin_px),
        "uncertain_policy": config.verifier.uncertain_policy,
        "target": f"a candidate with IoU >= {MATCH_IOU} with the ground-truth box, or {HELD_INSIDE:.0%} inside "
        f"it spanning {HELD_SPAN:.0%} of it; found: the mission acts on it (candidate_selection.may_start)",
        "size": "sqrt(w * h) of the ground-truth box in keyframe pixels",
    }
    return out


FAILED = ("verification timed out", "verifier failed")


def measure(
    source: SequenceSource,
    pipeline: Pipeline,
    keyframe_width: int,
    jpeg_quality: int,
    max_pixels: int,
    step: int = 1,
) -> SequenceLooks:
    """Every `step`-th frame with the target in view, as a keyframe through the pipeline."""
    looks = []
    for index, box in enumerate(source.boxes):
        if box is None or index % step or index >= len(source.frames):
            continue
        image = cv2.imread(str(source.frames[index]))
        if image is None:
            raise SequenceError(f"{source.frames[index]}: not an image")
        jpeg, scale = encode_keyframe(image, keyframe_width, jpeg_quality)
        keyframe = decode_image(jpeg, max_pixels)
        truth = box.scaled(keyframe.shape[1] / image.shape[1], keyframe.shape[0] / image.shape[0])
        luma = mean_luma(keyframe)
        result = pipeline.run(keyframe, source.prompt, source.superset, frame_id=index)
        detections = [c.detection for c in result.candidates]
        target = [d for d in detections if is_target(d.box, truth)]
        verdict = None
        if target:
            verdict = "no"
            if any(d in target for d in may_start(detections, accept_uncertain=True)):
                verdict = "uncertain"
            if any(d in target for d in may_start(detections, accept_uncertain=False)):
                verdict = "yes"
        looks.append(
            Look(
                index,
                math.sqrt(truth.w * truth.h),
                bool(target),
                verdict,
                any(d.verdict is Verdict.YES for d in target),
                any(d.justification.startswith(FAILED) for d in target),
                round(luma, 1),
            )
        )
    lit = tuple(look for look in looks if not too_dark(look.mean_luma))
    dark = tuple(look for look in looks if too_dark(look.mean_luma))
    return SequenceLooks(source.path.name, source.superset, source.fps, step, lit, dark)


def low_light(dark: Sequence[Look]) -> dict[str, Any]:
    """What the back-end made of frames too dark for the curve (reported, never fitted or checked)."""
    return {
        "frames": len(dark),
        "proposed": sum(look.proposed for look in dark),
        "found": sum(look.verdict == "yes" for look in dark),
        "mean_luma": round(sum(look.mean_luma for look in dark) / len(dark), 1) if dark else None,
        "below": MIN_MEAN_LUMA,
    }


def is_target(candidate: Box, truth: Box) -> bool:
    """The candidate is the ground truth's target (see the module doc)."""
    if iou(candidate, truth) >= MATCH_IOU:
        return True
    if not (candidate.is_valid() and truth.is_valid()):
        return False
    w = max(0.0, min(candidate.x2, truth.x2) - max(candidate.x, truth.x))
    h = max(0.0, min(candidate.y2, truth.y2) - max(candidate.y, truth.y))
    return w * h >= HELD_INSIDE * candidate.area and w * h >= HELD_SPAN * truth.area


def fit_curves(
    measured: Sequence[SequenceLooks], config: Mapping[str, str], min_sequences: int
) -> tuple[dict[str, DetectionCurve], dict[str, str]]:
    """One curve per class with at least `min_sequences` sequences and a bin of MIN_SAMPLES frames; and
    why each other class has none."""
    by_class: dict[str, dict[str, tuple[CurveBin, ...]]] = {}
    for seq in measured:
        if seq.looks:  # a sequence all in low light is no sequence of the curve (reported apart)
            by_class.setdefault(seq.superset, {})[seq.name] = seq.bins()
    curves, left_out = {}, {}
    for name, sequences in sorted(by_class.items()):
        curve = curve_from_sequences(name, sequences, config)
        if len(sequences) < min_sequences:
            left_out[name] = (
                f"{len(sequences)} sequence(s), fewer than {min_sequences}: one target's curve is that "
                "target's, and a curve is checked by predicting each sequence from the others"
            )
        elif not any(b.samples >= MIN_SAMPLES for b in curve.bins):
            left_out[name] = f"no size bin with {MIN_SAMPLES} frames"
        else:
            curves[name] = curve
    return curves, left_out


def _predictor(curve: DetectionCurve, sequence: str) -> tuple[DetectionCurve, bool]:
    """The curve to predict a sequence with: fitted without it when it was fitted on it."""
    held_out = sequence in dict(curve.sequences)
    return (curve.without(sequence) if held_out else curve), held_out


def _gap_frames(seq: SequenceLooks) -> int:
    """LOOK_GAP_S in the sequence's frames, in whole steps (at least one: --step can only lengthen it)."""
    return seq.step * max(1, round(LOOK_GAP_S * seq.fps / seq.step))


def look_dependence(
    measured: Sequence[SequenceLooks], curves: Mapping[str, DetectionCurve], accept_uncertain: bool
) -> dict[str, Any]:
    """How alike two looks LOOK_GAP_S apart at the same target are: P(found at t+k | missed at t) beside
    P(found at t+k), and what the size alone (the curve, fitted without the sequence) predicts for the
    looks after a miss. Independent looks would have the first two equal."""
    groups: dict[str, dict[str, Any]] = {}
    for seq in measured:
        k = _gap_frames(seq)
        by_frame = {look.frame: look for look in seq.looks}
        curve = curves.get(seq.superset)
        predictor = _predictor(curve, seq.name)[0] if curve is not None else None
        for key in ("all", seq.superset):
            g = groups.setdefault(key, {"pairs": 0, "found": 0, "missed_before": 0, "found_after_miss": 0,
                                        "found_before": 0, "found_after_found": 0, "size_predicts": 0.0,
                                        "predicted": 0, "gap_frames": {}})  # fmt: skip
            g["gap_frames"][seq.name] = k
            for t, first in by_frame.items():
                second = by_frame.get(t + k)
                if second is None:
                    continue
                found = second.found(accept_uncertain)
                g["pairs"] += 1
                g["found"] += found
                if first.found(accept_uncertain):
                    g["found_before"] += 1
                    g["found_after_found"] += found
                else:
                    g["missed_before"] += 1
                    g["found_after_miss"] += found
                    if predictor is not None:
                        g["size_predicts"] += predictor.probability(second.size_px, accept_uncertain)
                        g["predicted"] += 1
    out: dict[str, Any] = {
        "gap_s": LOOK_GAP_S,
        "gap_s_by_sequence": {seq.name: round(_gap_frames(seq) / seq.fps, 3) for seq in measured},
        "accept_uncertain": accept_uncertain,
        "classes": {},
    }
    for key, g in groups.items():
        out["classes"][key] = {
            "pairs": g["pairs"],
            "p_found": _share(g["found"], g["pairs"]),
            "missed_before": g["missed_before"],
            "p_found_after_miss": _share(g["found_after_miss"], g["missed_before"]),
            "p_found_after_miss_by_size": _share(g["size_predicts"], g["predicted"]),
            "found_before": g["found_before"],
            "p_found_after_found": _share(g["found_after_found"], g["found_before"]),
            "gap_frames": g["gap_frames"],
        }
    return out


def _share(part: float, whole: int) -> float | None:
    return round(part / whole, 4) if whole else None


def check(
    measured: Sequence[SequenceLooks], curves: Mapping[str, DetectionCurve], accept_uncertain: bool
) -> tuple[dict[str, Any], list[str]]:
    """Each frame predicted by its class's curve at its size (fitted without its sequence when fitted on
    it) and by the size-blind baseline (that same curve's overall share), beside what was observed, per
    bin; and the sequences left out (no curve for their class)."""
    classes: dict[str, Any] = {}
    skipped = []
    for seq in measured:
        if not seq.looks:  # all in low light: reported apart
            continue
        curve = curves.get(seq.superset)
        if curve is None:
            skipped.append(f"{seq.name} ({seq.superset}: the curve file has no curve for it)")
            continue
        predictor, held_out = _predictor(curve, seq.name)
        baseline = predictor.share(accept_uncertain)
        c = classes.setdefault(seq.superset, {"bins": [_check_row(b) for b in curve.bins], "sequences": {}})
        s = c["sequences"][seq.name] = {"held_out": held_out, "samples": 0, "predicted": 0.0,
                                         "observed": 0, "baseline": round(baseline, 4)}  # fmt: skip
        for look in seq.looks:
            i = bin_index(curve.bins, look.size_px)
            if i is None:
                continue
            p = predictor.probability(look.size_px, accept_uncertain)
            row = c["bins"][i]
            row["samples"] += 1
            row["predicted"] += p
            row["baseline"] += baseline
            row["observed"] += look.found(accept_uncertain)
            s["samples"] += 1
            s["predicted"] += p
            s["observed"] += look.found(accept_uncertain)
    for c in classes.values():
        for row in c["bins"]:
            n = row["samples"]
            row["observed"] = row["observed"] / n if n else None
            row["predicted"] = row["predicted"] / n if n else None
            row["baseline"] = row["baseline"] / n if n else None
            row["error"] = row["predicted"] - row["observed"] if n else None
            row["baseline_error"] = row["baseline"] - row["observed"] if n else None
            for key in ("observed", "predicted", "baseline", "error", "baseline_error"):
                row[key] = None if row[key] is None else round(row[key], 4)
        for s in c["sequences"].values():
            n = s["samples"]
            s["predicted"] = round(s["predicted"] / n, 4) if n else None
            s["observed"] = round(s["observed"] / n, 4) if n else None
    return classes, skipped


def _check_row(b: CurveBin) -> dict[str, Any]:
    return {"lo_px": round(b.lo_px, 3), "hi_px": None if math.isinf(b.hi_px) else round(b.hi_px, 3),
            "samples": 0, "predicted": 0.0, "observed": 0, "baseline": 0.0}  # fmt: skip


def worst_error(rows: Iterable[Mapping[str, Any]], key: str, min_samples: int) -> float | None:
    errors = [abs(r[key]) for r in rows if r["samples"] >= min_samples and r[key] is not None]
    return max(errors) if errors else None

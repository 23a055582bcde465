"""Detector recall on the described targets by class and box size, and time per keyframe, for several
detectors and set-ups at once.

    python -m backend_tools.detector_recall ../shared/data/sequences/* --model-dir ../shared/models \
        --variants yolox,yolox+tiles2,atto,atto+tiles2,femto,femto+tiles2 --step 2

A variant is a model (`yolox` or `fp32`: YOLOX-nano; `int8`: its quantised weights; `atto`, `femto`:
DEIMv2), optionally `+tilesN` (`[detector] tiles`) and `+scoreX` (`[detector] score_threshold`, default the
back-end's); `A/B` runs B only on keyframes where A finds nothing of the target's class (a fallback). A
target counts as found in a frame when a detection of its class (the sequence's `referring.txt` mapped by
`backend.supersets`) overlaps its ground-truth box by IoU >= 0.5. Size = sqrt(w*h) of the ground-truth box
in the keyframe's pixels, binned < 16, 16-32, 32-96, > 96 px. Classes: people, vehicles, boats, other (the
bag). Variants run interleaved on every frame (each frame through every model in turn, each model once per
frame however many variants use it), so a busy machine slows them alike; timings are the detector call per
keyframe (pre-processing, inference, decoding, tiling and merging; a fallback's includes its second model
where it ran). "False candidates" are boxes of the target's class that are not the target: what the
verifier must reject. `--speed-runs N` adds the 640x480 speed test of the back-end bench: N interleaved
rounds on one frame of uav123_person12_1.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from backend.config import DetectorConfig
from backend.detectors.interface import SupersetDetector
from backend.supersets import superset_from_prompt
from behaviors.detection import Detection
from behaviors.geometry import Box, iou

SIZE_BINS = (
    ("<16", 0.0, 16.0),
    ("16-32", 16.0, 32.0),
    ("32-96", 32.0, 96.0),
    (">96", 96.0, float("inf")),
)
CLASSES = ("people", "vehicles", "boats", "other")
_CLASS_OF = {"person": "people", "boat": "boats"} | dict.fromkeys(
    ("vehicle", "car", "truck", "bus", "motorbike", "bicycle"), "vehicles"
)
# Model name in a variant -> (model store name, weight file); fp32 is the name the int8 study used.
MODELS = {
    "yolox": ("yolox", "yolox_nano.onnx"),
    "fp32": ("yolox", "yolox_nano.onnx"),
    "atto": ("deimv2_atto", "deimv2_hgnetv2_atto_coco.onnx"),
    "femto": ("deimv2_femto", "deimv2_hgnetv2_femto_coco.onnx"),
}


def target_class(superset: str) -> str:
    """The table's class of a sequence's superset: people, vehicles, boats or other."""
    return _CLASS_OF.get(superset, "other")


def size_bin(size: float) -> str:
    return next(b for b, lo, hi in SIZE_BINS if lo <= size < hi)


@dataclass
class Tally:
    found: dict[tuple[str, str], int] = field(default_factory=dict)  # (class, size bin) -> frames found
    total: dict[tuple[str, str], int] = field(default_factory=dict)
    per_sequence: dict[str, list[int]] = field(default_factory=dict)  # name -> [found, total]
    times: list[float] = field(default_factory=list)
    others: list[int] = field(default_factory=list)  # boxes of the class that are not the target, per frame

    def add(
        self, sequence: str, size: float, hit: bool, seconds: float, others: int = 0, kind: str = "people"
    ) -> None:
        key = (kind, size_bin(size))
        self.found[key] = self.found.get(key, 0) + hit
        self.total[key] = self.total.get(key, 0) + 1
        counts = self.per_sequence.setdefault(sequence, [0, 0])
        counts[0] += hit
        counts[1] += 1
        self.times.append(seconds)
        self.others.append(others)

    def recall(self, classes: Sequence[str] = CLASSES, bins: Sequence[str] = ()) -> tuple[float | None, int]:
        """(recall, frames) over the given classes and size bins (no bins: every size)."""
        keys = [k for k in self.total if k[0] in classes and (not bins or k[1] in bins)]
        total = sum(self.total[k] for k in keys)
        return (sum(self.found[k] for k in keys) / total if total else None), total

    def summary(self) -> dict[str, object]:
        def cell(classes: Sequence[str] = CLASSES, bins: Sequence[str] = ()) -> dict[str, object]:
            recall, frames = self.recall(classes, bins)
            return {"recall": recall, "frames": frames}

        objects = [c for c in CLASSES if c != "people"]
        return {
            "recall": self.recall()[0],
            "frames": self.recall()[1],
            "by_size": {b: cell(bins=[b]) for b, _, _ in SIZE_BINS},
            "by_class": {c: cell([c]) for c in CLASSES},
            "people_by_size": {b: cell(["people"], [b]) for b, _, _ in SIZE_BINS},
            "objects_by_size": {b: cell(objects, [b]) for b, _, _ in SIZE_BINS},
            "per_sequence": {name: f / t for name, (f, t) in self.per_sequence.items()},
            "median_ms": 1000 * float(np.median(self.times)) if self.times else float("nan"),
            "mean_ms": 1000 * float(np.mean(self.times)) if self.times else float("nan"),
            "others_per_frame": float(np.mean(self.others)) if self.others else float("nan"),
        }


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def build_variant(spec: str, model_dir: Path, int8_model: Path | None, threads: int) -> SupersetDetector:
    """'yolox', 'atto+tiles2', 'femto+tiles2+score0.3', 'int8' ... -> the detector (tiles as in `[detector]
    tiles`, the score threshold as `[detector] score_threshold`, default the back-end's)."""
    from backend.detectors.deimv2 import Deimv2Detector
    from backend.detectors.tiling import TiledDetector
    from backend.detectors.yolox import YoloxDetector
    from cloudtrack.model_store import require

    model, *options = spec.split("+")
    tiling = next((o for o in options if o.startswith("tiles")), "")
    score = next((o for o in options if o.startswith("score")), f"score{DetectorConfig().score_threshold}")
    if any(not o.startswith(("tiles", "score")) for o in options) or not _number(score[5:]):
        raise ValueError(f"variant {spec!r}: expected a model, then +tilesN and/or +scoreX")
    if tiling and not tiling[5:].isdigit():
        raise ValueError(f"variant {spec!r}: expected +tilesN")
    if model not in (*MODELS, "int8"):
        raise ValueError(f"variant {spec!r}: the model must be one of {', '.join((*MODELS, 'int8'))}")
    store_name, file_name = MODELS.get(model, MODELS["yolox"])
    path = require(store_name, model_dir)[file_name]
    if model == "int8":
        path = int8_model or path.with_name("yolox_nano_int8.onnx")
        if not path.is_file():
            raise ValueError(
                f"{path} is missing; make it with `python -m backend_tools.quantize SEQUENCES --out {path}`"
            )
    inner: YoloxDetector | Deimv2Detector
    if store_name == "yolox":
        inner = YoloxDetector(path, score_threshold=float(score[5:]), threads=threads)
    else:
        inner = Deimv2Detector(path, score_threshold=float(score[5:]), threads=threads)
    if tiling:
        return TiledDetector(inner, int(tiling[5:]), min_side=inner.input_size)
    return inner


def build_variants(
    specs: Sequence[str], model_dir: Path, int8_model: Path | None, threads: int
) -> tuple[dict[str, SupersetDetector], dict[str, list[str]]]:
    """The detectors every variant needs, each once, and each variant's detectors in order (two for a
    fallback `A/B`)."""
    detectors: dict[str, SupersetDetector] = {}
    variants: dict[str, list[str]] = {}
    for spec in specs:
        parts = spec.split("/")
        if len(parts) > 2 or not all(parts):
            raise ValueError(f"variant {spec!r}: expected one detector or a fallback A/B")
        for part in parts:
            if part not in detectors:
                detectors[part] = build_variant(part, model_dir, int8_model, threads)
        variants[spec] = parts
    return detectors, variants


def _groundtruth(seq: Path) -> list[Box | None]:
    rows = []
    for line in (seq / "groundtruth.txt").read_text().split():
        values = [float(v) for v in line.replace("\t", ",").split(",")]
        rows.append(None if any(np.isnan(values)) or values[2] <= 0 or values[3] <= 0 else Box(*values[:4]))
    return rows


def measure_recall(
    sequences: Sequence[Path],
    variants: dict[str, SupersetDetector],
    step: int,
    max_width: int = 0,
    fallbacks: dict[str, list[str]] | None = None,
) -> dict[str, Tally]:
    """Every `step`-th frame with a target, downscaled to `max_width` like keyframes (0: native).

    `variants` are the detectors; `fallbacks` (default: each detector alone) names what is tallied: a
    list of one detector, or two where the second runs only when the first finds nothing."""
    tallies_of = fallbacks or {name: [name] for name in variants}
    tallies = {name: Tally() for name in tallies_of}
    for seq in sequences:
        referring = seq / "referring.txt"
        superset = (superset_from_prompt(referring.read_text()) if referring.is_file() else None) or "person"
        frames = sorted((seq / "frames").glob("*.jpg"))
        for index, box in enumerate(_groundtruth(seq)):
            if box is None or index % step or index >= len(frames):
                continue
            image = cv2.imread(str(frames[index]))
            if image is None:
                raise ValueError(f"cannot read {frames[index]}")
            if max_width and image.shape[1] > max_width:
                scale = max_width / image.shape[1]
                image = cv2.resize(
                    image, (max_width, round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA
                )
                box = box.scaled(scale, scale)
            size = float(np.sqrt(box.w * box.h))
            runs: dict[str, tuple[list[Detection], float]] = {}
            for name, detector in variants.items():
                start = time.perf_counter()
                found = detector.detect(image, [superset])
                runs[name] = (found, time.perf_counter() - start)
            for name, parts in tallies_of.items():
                found, seconds = runs[parts[0]]
                if not found and len(parts) > 1:
                    found, more = runs[parts[1]]
                    seconds += more
                hits = [iou(box, d.box) >= 0.5 for d in found]
                tallies[name].add(
                    seq.name, size, any(hits), seconds, len(hits) - sum(hits), target_class(superset)
                )
    return tallies


def measure_speed(
    frame: np.ndarray, variants: dict[str, SupersetDetector], runs: int
) -> dict[str, dict[str, float]]:
    """Interleaved rounds on one frame: each round runs every variant once, in turn."""
    times: dict[str, list[float]] = {name: [] for name in variants}
    for detector in variants.values():
        for _ in range(5):
            detector.detect(frame, ["person"])
    for _ in range(runs):
        for name, detector in variants.items():
            start = time.perf_counter()
            detector.detect(frame, ["person"])
            times[name].append(time.perf_counter() - start)
    return {name: {"median_ms": 1000 * float(np.median(t)), "p10_ms": 1000 * float(np.percentile(t, 10)),
                   "p90_ms": 1000 * float(np.percentile(t, 90))} for name, t in times.items()}  # fmt: skip


def _fmt(value: object) -> str:
    return "-" if value is None else f"{value:.2f}" if isinstance(value, float) else str(value)


def _cells(groups: object) -> list[str]:
    assert isinstance(groups, dict)
    return [f"{_fmt(g['recall'])} ({g['frames']})" for g in groups.values()]


def print_tables(tallies: dict[str, Tally], load: float, max_width: int) -> None:
    """The side-by-side tables: people by size (a search's first need), classes, objects by size, cost."""
    summaries = {name: t.summary() for name, t in tallies.items()}
    base = next(iter(summaries.values()))
    width = f"keyframes at most {max_width} px wide" if max_width else "native frames"
    print(f"load average {load:.1f}; {width}; recall at IoU >= 0.5 (frames); the first row is the baseline")
    bins = " | ".join(f"{b} px" for b, _, _ in SIZE_BINS)
    print(
        f"\n| variant | people {bins} | people | vehicles | boats | other | all | "
        "false candidates per keyframe | median ms per keyframe | mean ms | time ratio |"
    )
    print("|---|" + "---|" * (len(SIZE_BINS) + 9))
    for name, s in summaries.items():
        ratio = float(s["median_ms"]) / float(base["median_ms"])  # type: ignore[arg-type]
        print(
            f"| {name} | {' | '.join(_cells(s['people_by_size']))} | {' | '.join(_cells(s['by_class']))} | "
            f"{_fmt(s['recall'])} ({s['frames']}) | {_fmt(s['others_per_frame'])} | {_fmt(s['median_ms'])} | "
            f"{_fmt(s['mean_ms'])} | {ratio:.2f} |"
        )
    print(f"\n| variant | all targets {bins} | objects (not people) {bins} |")
    print("|---|" + "---|" * 2 * len(SIZE_BINS))
    for name, s in summaries.items():
        print(f"| {name} | {' | '.join(_cells(s['by_size']))} | {' | '.join(_cells(s['objects_by_size']))} |")
    names = list(next(iter(tallies.values())).per_sequence)
    print("\n| variant | " + " | ".join(names) + " |\n|---|" + "---|" * len(names))
    for name, s in summaries.items():
        per = s["per_sequence"]
        assert isinstance(per, dict)
        print(f"| {name} | " + " | ".join(_fmt(per[n]) for n in names) + " |")


def main(argv: list[str] | None = None) -> int:
    from cloudtrack.model_store import ModelError, resolve_model_dir

    parser = argparse.ArgumentParser(
        prog="python -m backend_tools.detector_recall",
        description="Superset detector recall on each sequence's described target by class and box size, "
        "false candidates and time per keyframe, for several detectors side by side (interleaved on every "
        "frame).",
        epilog="variants: yolox (or fp32), int8, atto, femto, each optionally +tilesN and +scoreX; A/B: B only "
        "where A finds nothing of the class\n"
        "examples:\n"
        "  python -m backend_tools.detector_recall ../shared/data/sequences/* --model-dir ../shared/models "
        "--variants yolox,yolox+tiles2,atto,atto+tiles2,femto,femto+tiles2,yolox+tiles2/atto+tiles2\n"
        "  python -m backend_tools.detector_recall ../shared/data/sequences/uav123_person12_1 "
        "--model-dir ../shared/models "
        "--variants fp32,int8 --int8-model /tmp/yolox_nano_int8.onnx --step 1 --speed-runs 300 --threads 0",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "sequences", nargs="+", type=Path, help="folders with frames/, groundtruth.txt, referring.txt"
    )
    parser.add_argument("--model-dir", help="weights folder (default: $CLOUDTRACK_MODEL_DIR, then the cache)")
    parser.add_argument(
        "--variants",
        default="yolox",
        help="comma-separated: yolox (fp32), int8, atto, femto, each optionally +tilesN and +scoreX, or A/B "
        "(B where A finds nothing); the first is the baseline (default yolox; score: the back-end's "
        "[detector] score_threshold)",
    )
    parser.add_argument(
        "--int8-model", type=Path, help="int8 model (default: <model-dir>/yolox_nano/yolox_nano_int8.onnx)"
    )
    parser.add_argument(
        "--threads", type=int, default=1, help="onnxruntime threads per detector, 0 = all cores (default 1)"
    )
    parser.add_argument("--step", type=int, default=1, help="use every STEP-th frame (default 1)")
    parser.add_argument(
        "--max-width",
        type=int,
        default=640,
        help="downscale wider frames to this width, as the companion's keyframes "
        "([backend] max_keyframe_width, default 640); 0 = native size; size bins are in these pixels",
    )
    parser.add_argument(
        "--speed-runs", type=int, default=0, help="also time N interleaved rounds on a 640x480 frame"
    )
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the figures as JSON")
    args = parser.parse_args(argv)
    try:
        model_dir = resolve_model_dir(args.model_dir)
        detectors, fallbacks = build_variants(
            [v for v in args.variants.split(",") if v], model_dir, args.int8_model, args.threads
        )
        tallies = measure_recall(args.sequences, detectors, max(1, args.step), args.max_width, fallbacks)
    except (ModelError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    load = os.getloadavg()[0]
    result: dict[str, object] = {
        "load_average_1min": load,
        "threads": args.threads,
        "step": args.step,
        "max_width": args.max_width,
        "variants": {name: t.summary() for name, t in tallies.items()},
    }
    print_tables(tallies, load, args.max_width)
    if args.speed_runs:
        seq = next((s for s in args.sequences if s.name == "uav123_person12_1"), args.sequences[0])
        first_frame = cv2.imread(str(sorted((seq / "frames").glob("*.jpg"))[0]))
        if first_frame is None:
            print(f"error: cannot read the first frame of {seq}", file=sys.stderr)
            return 2
        speed = measure_speed(cv2.resize(first_frame, (640, 480)), detectors, args.speed_runs)
        result["speed_640x480"] = speed
        first = next(iter(speed.values()))["median_ms"]
        print(f"\n640x480 frame of {seq.name}, {args.speed_runs} interleaved rounds, threads {args.threads}:")
        for name, figures in speed.items():
            print(
                f"  {name}: median {figures['median_ms']:.2f} ms (p10 {figures['p10_ms']:.2f}, "
                f"p90 {figures['p90_ms']:.2f}), x{figures['median_ms'] / first:.2f}"
            )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Detector recall on the described targets by box size, and time per keyframe, for several set-ups at once.

    python -m backend_tools.detector_recall ../shared/data/sequences/* --model-dir ../shared/models \
        --variants fp32,fp32+tiles2,fp32+tiles3 --step 2

A target counts as found in a frame when a detection of its class (the sequence's `referring.txt` mapped
by `backend.supersets`) overlaps its ground-truth box by IoU >= 0.5. Size bins follow COCO: sqrt(w*h) of
the ground-truth box < 32 px, 32-96, > 96, in the frame's own pixels. Variants run interleaved on every
frame (each frame through every variant in turn), so a busy machine slows them alike; timings are the
detector call per keyframe (pre-processing, inference, decoding, tiling and merging). `--speed-runs N`
adds the 640x480 speed test of the back-end bench: N interleaved rounds on one frame of uav123_person12_1.
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
from behaviors.geometry import Box, iou

SIZE_BINS = (("<32", 0.0, 32.0), ("32-96", 32.0, 96.0), (">96", 96.0, float("inf")))


@dataclass
class Tally:
    found: dict[str, int] = field(default_factory=lambda: {b: 0 for b, _, _ in SIZE_BINS})
    total: dict[str, int] = field(default_factory=lambda: {b: 0 for b, _, _ in SIZE_BINS})
    per_sequence: dict[str, list[int]] = field(default_factory=dict)  # name -> [found, total]
    times: list[float] = field(default_factory=list)
    others: list[int] = field(default_factory=list)  # boxes of the class that are not the target, per frame

    def add(self, sequence: str, size: float, hit: bool, seconds: float, others: int = 0) -> None:
        label = next(b for b, lo, hi in SIZE_BINS if lo <= size < hi)
        self.found[label] += hit
        self.total[label] += 1
        counts = self.per_sequence.setdefault(sequence, [0, 0])
        counts[0] += hit
        counts[1] += 1
        self.times.append(seconds)
        self.others.append(others)

    def summary(self) -> dict[str, object]:
        found, total = sum(self.found.values()), sum(self.total.values())
        return {
            "recall": found / total if total else float("nan"),
            "frames": total,
            "by_size": {
                b: {
                    "recall": self.found[b] / self.total[b] if self.total[b] else None,
                    "frames": self.total[b],
                }
                for b, _, _ in SIZE_BINS
            },
            "per_sequence": {name: f / t for name, (f, t) in self.per_sequence.items()},
            "median_ms": 1000 * float(np.median(self.times)) if self.times else float("nan"),
            "others_per_frame": float(np.mean(self.others)) if self.others else float("nan"),
        }


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def build_variant(spec: str, model_dir: Path, int8_model: Path | None, threads: int) -> SupersetDetector:
    """'fp32', 'int8', 'fp32+tiles3', 'fp32+tiles2+score0.2' ... -> the detector (tiles as in `[detector]
    tiles`, the score threshold as `[detector] score_threshold`, default the back-end's)."""
    from backend.detectors.tiling import TiledDetector
    from backend.detectors.yolox import YoloxDetector
    from cloudtrack.model_store import require

    precision, *options = spec.split("+")
    tiling = next((o for o in options if o.startswith("tiles")), "")
    score = next((o for o in options if o.startswith("score")), f"score{DetectorConfig().score_threshold}")
    if any(not o.startswith(("tiles", "score")) for o in options) or not _number(score[5:]):
        raise ValueError(f"variant {spec!r}: expected fp32 or int8, then +tilesN and/or +scoreX")
    fp32 = require("yolox", model_dir)["yolox_nano.onnx"]
    if precision not in ("fp32", "int8"):
        raise ValueError(f"variant {spec!r}: precision must be fp32 or int8")
    path = fp32 if precision == "fp32" else (int8_model or fp32.with_name("yolox_nano_int8.onnx"))
    if not path.is_file():
        raise ValueError(
            f"{path} is missing; make it with `python -m backend_tools.quantize SEQUENCES --out {path}`"
        )
    yolox = YoloxDetector(path, score_threshold=float(score[5:]), threads=threads)
    detector: SupersetDetector = yolox
    if tiling:
        if not tiling.startswith("tiles") or not tiling[5:].isdigit():
            raise ValueError(f"variant {spec!r}: expected +tilesN")
        detector = TiledDetector(yolox, int(tiling[5:]), min_side=yolox.input_size)
    return detector


def _groundtruth(seq: Path) -> list[Box | None]:
    rows = []
    for line in (seq / "groundtruth.txt").read_text().split():
        values = [float(v) for v in line.replace("\t", ",").split(",")]
        rows.append(None if any(np.isnan(values)) or values[2] <= 0 or values[3] <= 0 else Box(*values[:4]))
    return rows


def measure_recall(
    sequences: Sequence[Path], variants: dict[str, SupersetDetector], step: int, max_width: int = 0
) -> dict[str, Tally]:
    """Every `step`-th frame with a target, downscaled to `max_width` like keyframes (0: native)."""
    tallies = {name: Tally() for name in variants}
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
            for name, detector in variants.items():
                start = time.perf_counter()
                found = detector.detect(image, [superset])
                seconds = time.perf_counter() - start
                hits = [iou(box, d.box) >= 0.5 for d in found]
                tallies[name].add(seq.name, size, any(hits), seconds, len(hits) - sum(hits))
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


def main(argv: list[str] | None = None) -> int:
    from cloudtrack.model_store import ModelError, resolve_model_dir

    parser = argparse.ArgumentParser(
        prog="python -m backend_tools.detector_recall",
        description="YOLOX recall on each sequence's described target by box size, and detector time per "
        "keyframe, for several variants side by side (interleaved on every frame).",
        epilog="examples:\n"
        "  python -m backend_tools.detector_recall ../shared/data/sequences/* --model-dir ../shared/models "
        "--variants fp32,fp32+tiles2,fp32+tiles3\n"
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
        default="fp32",
        help="comma-separated: fp32, int8, each optionally +tilesN and +scoreX (default fp32; score: the "
        "back-end's [detector] score_threshold)",
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
        variants = {
            v: build_variant(v, model_dir, args.int8_model, args.threads)
            for v in args.variants.split(",")
            if v
        }
        tallies = measure_recall(args.sequences, variants, max(1, args.step), args.max_width)
    except (ModelError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result: dict[str, object] = {
        "load_average_1min": os.getloadavg()[0],
        "threads": args.threads,
        "step": args.step,
        "max_width": args.max_width,
        "variants": {name: t.summary() for name, t in tallies.items()},
    }
    base = next(iter(tallies.values())).summary()
    width = f"frames at most {args.max_width} px wide" if args.max_width else "native frames"
    print(
        f"load average {os.getloadavg()[0]:.1f}; {width}; recall at IoU >= 0.5 (frames); "
        "time per keyframe (x first)"
    )
    print("| variant | <32 px | 32-96 px | >96 px | all | other boxes per frame | median ms | time ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for name, tally in tallies.items():
        s = tally.summary()
        bins = s["by_size"]
        assert isinstance(bins, dict)
        cells = [f"{_fmt(bins[b]['recall'])} ({bins[b]['frames']})" for b, _, _ in SIZE_BINS]
        ratio = float(s["median_ms"]) / float(base["median_ms"])  # type: ignore[arg-type]
        print(
            f"| {name} | {' | '.join(cells)} | {_fmt(s['recall'])} ({s['frames']}) | "
            f"{_fmt(s['others_per_frame'])} | {_fmt(s['median_ms'])} | {ratio:.2f} |"
        )
    names = list(next(iter(tallies.values())).per_sequence)
    print("\n| variant | " + " | ".join(names) + " |\n|---|" + "---|" * len(names))
    for name, tally in tallies.items():
        per = tally.summary()["per_sequence"]
        assert isinstance(per, dict)
        print(f"| {name} | " + " | ".join(_fmt(per[n]) for n in names) + " |")
    if args.speed_runs:
        seq = next((s for s in args.sequences if s.name == "uav123_person12_1"), args.sequences[0])
        first_frame = cv2.imread(str(sorted((seq / "frames").glob("*.jpg"))[0]))
        if first_frame is None:
            print(f"error: cannot read the first frame of {seq}", file=sys.stderr)
            return 2
        speed = measure_speed(cv2.resize(first_frame, (640, 480)), variants, args.speed_runs)
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

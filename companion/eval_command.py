"""`cloudtrack-companion eval`: tracking accuracy and speed on annotated sequences (see tracking_eval)."""

from __future__ import annotations

import argparse
import functools
import json
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from behaviors.detection import Detection
from cloudtrack.config_files import ConfigError
from cloudtrack.model_store import ModelError, require, resolve_model_dir
from companion.config_command import add_config_flags, load_from_args
from companion.loss_detection import parse_signals
from companion.models_command import add_model_dir_flag
from companion.trackers import TrackerUnavailableError, available_trackers
from companion.tracking_eval import (
    DetectFn,
    DetectionCache,
    EvalSettings,
    SequenceData,
    SequenceResult,
    evaluate_sequence,
    load_sequence,
    overall,
    parse_size,
    parse_sweep,
    result_dict,
    signal_table,
)

log = logging.getLogger(__name__)

EPILOG = """\
examples:
  cloudtrack-companion eval ../shared/data/sequences/* --tracker nano --json out/eval.json
  cloudtrack-companion eval ../shared/data/sequences/* --tracker nano,vit,csrt,kcf,mil
  cloudtrack-companion eval ../shared/data/sequences/* --tracker nano --size 640x480
  cloudtrack-companion eval ../shared/data/sequences/* --tracker nano,vit --sweep 0.3:0.95:0.05 --plot out/sweep.png
  cloudtrack-companion eval ../shared/data/sequences/* --policy both --occlude --delay-s 1
  cloudtrack-companion eval ../shared/data/sequences/* --signal-table --occlude --tracker nano,vit,csrt
  CLOUDTRACK_BACKEND__TOKEN=... cloudtrack-companion eval ../shared/data/sequences/uav123_person12_1 --backend http://127.0.0.1:8080

Re-initialisation candidates come from the back-end with --backend URL (first acquisition too, from
referring.txt), else from the YOLOX-nano detector in-process (--detector none: no re-initialisation).
FPS counts the whole onboard loop except the detector (it runs on the back-end); edge FPS counts the
tracker's update() alone.
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "eval",
        help="mIoU, FPS and re-initialisations of the trackers on annotated sequences",
        description="Evaluate the onboard tracking front-end on sequences in the layout of "
        "../shared/data/sequences (frames/, groundtruth.txt, referring.txt).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("sequences", nargs="+", type=Path, metavar="SEQUENCE_DIR")
    parser.add_argument("--tracker", default=None, help="tracker name(s), comma separated (default: [tracker] name)")
    parser.add_argument("--threshold", type=float, help="t_c for scored trackers (default: [tracker] score_threshold)")
    parser.add_argument("--sweep", help="START:STOP:STEP of t_c, e.g. 0.3:0.95:0.05 (scored trackers only)")
    parser.add_argument("--policy", choices=("c_box", "score", "both"), default="c_box",
                        help="re-init candidate choice: C_box to the last trusted box, highest detector score, or both")
    parser.add_argument("--signals", default=None,
                        help="loss signals in use: all, none or a list such as score,jump (default: [tracker] loss_signals)")
    parser.add_argument("--size", help="resize frames to WIDTHxHEIGHT, e.g. 640x480 (default: native)")
    parser.add_argument("--detector", choices=("yolox", "none"), default="yolox",
                        help="in-process detector for re-initialisation when no --backend is given")
    parser.add_argument("--backend", metavar="URL", help="ask this CloudTrack back-end for candidates instead")
    parser.add_argument("--delay-s", type=float, default=0.0,
                        help="simulated back-end latency in seconds of sequence time (default 0)")
    parser.add_argument("--no-compensation", action="store_true", help="apply late answers without fast-forwarding")
    parser.add_argument("--reverify-s", type=float, default=0.0,
                        help="also re-initialise from candidates every S seconds while tracking (default 0: off)")
    parser.add_argument("--occlude", action="store_true",
                        help="stress test: hide the target for 1.5 s from a third of each sequence (ground truth nan there)")
    parser.add_argument("--signal-table", action="store_true",
                        help="instead of mIoU: score every loss signal against the frames really off target")
    parser.add_argument("--max-frames", type=int, help="use only the first N frames of each sequence")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write every result as JSON")
    parser.add_argument("--plot", type=Path, metavar="OUT.png",
                        help="IoU per frame per sequence, or with --sweep the mIoU/FPS-versus-t_c curves")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_model_dir_flag(parser)
    add_config_flags(parser)
    parser.set_defaults(func=run)


@functools.lru_cache(maxsize=2)
def _yolox(path: Path) -> Any:
    from backend.detectors.yolox import YoloxDetector

    return YoloxDetector(path)


def _detector(args: argparse.Namespace, model_dir: Path, seq: SequenceData) -> DetectFn | None:
    if args.backend:
        from cloudtrack.api_client import BackendClient, BackendError

        backend = args.backend_config
        client = BackendClient(args.backend, backend.token, backend.timeout_s, backend.jpeg_quality,
                               backend.max_keyframe_width, vehicle_id=args.vehicle_id,
                               mission_id=f"eval-{seq.name}")
        prompt = seq.referring or "a person"

        def ask_backend(image: np.ndarray, frame_id: int) -> list[Detection]:
            try:
                return client.detect(image, prompt, frame_id=frame_id)
            except BackendError as exc:  # a failed request is an empty answer, as in flight
                log.warning("%s frame %d: back-end request failed: %s", seq.name, frame_id, exc)
                return []

        return ask_backend
    if args.detector == "none":
        return None
    from backend.supersets import UnknownSupersetError, coco_classes_for, superset_from_prompt

    yolox = _yolox(require("yolox", model_dir)["yolox_nano.onnx"])
    superset = superset_from_prompt(seq.referring) or "person"
    try:
        coco_classes_for(superset)
    except UnknownSupersetError:
        log.warning("%s: no detector class for %r; no re-initialisation on this sequence", seq.name, superset)
        return None

    def detect(image: np.ndarray, frame_id: int) -> list[Detection]:
        return list(yolox.detect(image, [superset], frame_id=frame_id))

    return detect


def _fmt(value: float, digits: int = 3) -> str:
    return "nan" if not math.isfinite(value) else f"{value:.{digits}f}"


def _print_table(label: str, results: Sequence[SequenceResult]) -> dict[str, Any]:
    print(f"\n{label}")
    print(f"{'sequence':<22} {'frames':>6} {'mIoU':>6} {'any box':>7} {'FPS':>7} {'edge FPS':>8} {'re-inits':>8} "
          f"{'losses':>6}  lost frames by reason")
    for r in results:
        reasons = ", ".join(f"{k}:{v}" for k, v in sorted(r.loss_reasons.items())) or "-"
        print(f"{r.sequence:<22} {r.frames:>6} {_fmt(r.miou):>6} {_fmt(r.miou_any_box):>7} {_fmt(r.fps, 1):>7} "
              f"{_fmt(r.edge_fps, 1):>8} {r.reinits:>8} {r.loss_events:>6}  {reasons}")
    total = overall(results)
    print(f"{'overall':<22} {total['frames']:>6} {_fmt(total['miou']):>6} {_fmt(total['miou_any_box']):>7} "
          f"{_fmt(total['fps'], 1):>7} {_fmt(total['edge_fps'], 1):>8} {total['reinits']:>8} {total['loss_events']:>6}")
    return total


def run(args: argparse.Namespace) -> int:
    try:
        config = load_from_args(args)
        model_dir = resolve_model_dir(args.model_dir or config.tracker.model_dir or None)
        trackers = [t.strip() for t in (args.tracker or config.tracker.name).split(",") if t.strip()]
        for name in trackers:
            if name not in available_trackers():
                raise TrackerUnavailableError(
                    f"tracker {name!r} is not provided by this OpenCV build; available: {', '.join(available_trackers())}"
                )
        signals = parse_signals(args.signals) if args.signals is not None else frozenset(config.tracker.loss_signals)
        size = parse_size(args.size) if args.size else None
        sweep = parse_sweep(args.sweep) if args.sweep else None
        if args.threshold is not None and not 0 <= args.threshold <= 1:
            raise ValueError(f"--threshold {args.threshold}: must be between 0 and 1")
        if args.max_frames is not None and args.max_frames < 2:
            raise ValueError("--max-frames must be at least 2")
        seqs = [load_sequence(p) for p in args.sequences]
        args.backend_config = config.backend
        args.vehicle_id = config.vehicle.id
    except (ConfigError, ModelError, TrackerUnavailableError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    from tqdm.contrib.logging import logging_redirect_tqdm

    policies = ["c_box", "score"] if args.policy == "both" else [args.policy]
    try:
        detectors = {s.name: _detector(args, model_dir, s) for s in seqs}
    except ModelError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    caches = {name: DetectionCache(fn) if fn is not None else None for name, fn in detectors.items()}
    output: dict[str, Any] = {"command": sys.argv[1:], "runs": []}

    if args.signal_table:
        for name in trackers:
            report = signal_table(seqs, config.tracker, model_dir, name, size, args.max_frames, args.occlude)
            _print_signal_table(report)
            output["runs"].append({"signal_table": _signal_dict(report)})
        _write_json(args.json, output)
        return 0

    if sweep:
        skipped = [t for t in trackers if t not in config.tracker.score_threshold]
        if skipped:
            print(f"--sweep: {', '.join(skipped)} ha(s) no score and no t_c; not swept", file=sys.stderr)
        trackers = [t for t in trackers if t in config.tracker.score_threshold]
    thresholds: list[float | None] = list(sweep) if sweep else [args.threshold]
    total_frames = sum(
        min(len(s.ground_truth), args.max_frames or len(s.ground_truth)) for s in seqs
    ) * len(trackers) * len(policies) * len(thresholds)
    with logging_redirect_tqdm():
        return _run_evals(args, config, model_dir, trackers, seqs, policies, thresholds, sweep, signals, size,
                          caches, output, total_frames)


def _run_evals(
    args: argparse.Namespace,
    config: Any,
    model_dir: Path,
    trackers: list[str],
    seqs: list[SequenceData],
    policies: list[str],
    thresholds: list[float | None],
    sweep: list[float] | None,
    signals: frozenset[str],
    size: tuple[int, int] | None,
    caches: dict[str, DetectionCache | None],
    output: dict[str, Any],
    total_frames: int,
) -> int:
    from tqdm import tqdm

    bar = tqdm(total=total_frames, unit="frame", disable=args.no_progress, file=sys.stderr)
    sweep_points: dict[str, list[tuple[float, float, float]]] = {}
    last_results: list[SequenceResult] = []
    for name in trackers:
        for threshold in thresholds:
            for policy in policies:
                settings = EvalSettings(
                    tracker=name,
                    threshold=threshold,
                    signals=signals,
                    policy=policy,  # type: ignore[arg-type]
                    size=size,
                    compensate=not args.no_compensation,
                    max_frames=args.max_frames,
                    occlude=args.occlude,
                )
                results = []
                for seq in seqs:
                    delay = round(args.delay_s * seq.fps)
                    seq_settings = EvalSettings(**{
                        **settings.__dict__,
                        "delay_frames": delay,
                        "keyframe_interval": max(1, round(0.5 * seq.fps)),
                        "reverify_interval": round(args.reverify_s * seq.fps),
                    })
                    results.append(evaluate_sequence(
                        seq, config.tracker, model_dir, seq_settings, caches[seq.name],
                        init_from_detector=bool(args.backend), progress=bar.update,
                    ))
                bar.clear()
                t_label = f"t_c={threshold}" if threshold is not None else f"t_c={config.tracker.score_threshold.get(name, '-')}"
                total = _print_table(f"tracker {name}, {t_label}, policy {policy}, size {args.size or 'native'}", results)
                output["runs"].append({
                    "tracker": name, "threshold": threshold, "policy": policy, "size": args.size,
                    "overall": total, "sequences": [result_dict(r) for r in results],
                })
                if sweep and threshold is not None:
                    sweep_points.setdefault(name, []).append((threshold, total["miou"], total["fps"]))
                last_results = results
    bar.close()
    _write_json(args.json, output)
    if args.plot:
        if sweep:
            _plot_sweep(sweep_points, args.plot)
        else:
            _plot_ious(last_results, args.plot)
        print(f"plot written to {args.plot}")
    return 0


def _write_json(path: Path | None, data: dict[str, Any]) -> None:
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, default=str))
    print(f"results written to {path}")


def _signal_dict(report: Any) -> dict[str, Any]:
    return {
        "tracker": report.tracker,
        "frames": report.frames,
        "lost_frames": report.lost_frames,
        "signals": {k: vars(v) for k, v in report.counts.items()},
        "combinations": {k: vars(v) for k, v in report.combos.items()},
    }


def _print_signal_table(report: Any) -> None:
    print(f"\ntracker {report.tracker}: {report.frames} frames, {report.lost_frames} off target (IoU < 0.1 or target hidden)")
    print(f"{'signal':<28} {'fired':>6} {'precision':>9} {'recall':>7}")
    for name, c in [*report.counts.items(), *report.combos.items()]:
        precision = c.fired_lost / c.fired if c.fired else float("nan")
        recall = c.fired_lost / report.lost_frames if report.lost_frames else float("nan")
        print(f"{name:<28} {c.fired:>6} {_fmt(precision, 2):>9} {_fmt(recall, 2):>7}")


def _plot_sweep(points: dict[str, list[tuple[float, float, float]]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_iou, ax_fps) = plt.subplots(1, 2, figsize=(10, 4))
    for name, values in points.items():
        t = [v[0] for v in values]
        ax_iou.plot(t, [v[1] for v in values], marker="o", label=name)
        ax_fps.plot(t, [v[2] for v in values], marker="o", label=name)
    ax_iou.set(xlabel="re-initialisation threshold t_c", ylabel="mIoU", title="mIoU versus t_c")
    ax_fps.set(xlabel="re-initialisation threshold t_c", ylabel="FPS (onboard loop)", title="FPS versus t_c")
    for ax in (ax_iou, ax_fps):
        ax.grid(True, alpha=0.3)
        ax.legend()
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)


def _plot_ious(results: Sequence[SequenceResult], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4))
    for r in results:
        ax.plot([np.nan if v is None else v for v in r.ious], label=f"{r.sequence} ({_fmt(r.miou)})")
    ax.set(xlabel="frame", ylabel="IoU with ground truth", title=f"{results[0].tracker if results else ''} IoU per frame")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)

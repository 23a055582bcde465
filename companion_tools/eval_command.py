"""`cloudtrack-companion eval`: tracking accuracy and speed on annotated sequences (see tracking_eval)."""

from __future__ import annotations

import argparse
import functools
import json
import logging
import math
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from behaviors.detection import Detection
from behaviors.geometry import Box
from behaviors.tracking_metrics import pooled_miou
from cloudtrack.api_client import encode_keyframe
from cloudtrack.config_files import ConfigError
from cloudtrack.model_store import ModelError, resolve_model_dir
from companion.config_command import add_config_flags, load_from_args
from companion.models_command import add_model_dir_flag
from companion.vision.loss_detection import parse_signals
from companion.vision.trackers import TrackerUnavailableError, available_trackers
from companion.vision.tracking_frontend import POLICIES
from companion_tools.tracking_eval import (
    OFF_TARGET_IOU,
    ON_TARGET_IOU,
    DetectFn,
    DetectionCache,
    EvalSettings,
    SequenceData,
    SequenceResult,
    acquisition_ceiling,
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
  cloudtrack-companion eval ../shared/data/sequences/* --policy all --occlude --delay-s 1
  cloudtrack-companion eval ../shared/data/sequences/* --init prompt --model-dir ../shared/models
  cloudtrack-companion eval ../shared/data/sequences/* --init prompt --delay-s 0.3 --tracker nano
  cloudtrack-companion eval ../shared/data/sequences/* --signal-table --tracker nano,vit,csrt
  CLOUDTRACK_BACKEND__TOKEN=... cloudtrack-companion eval ../shared/data/sequences/uav123_person12_1 \
      --backend http://127.0.0.1:8080 --init prompt

Every table prints the bare tracker beside the configuration, from the same run on the same frames:
"bare" starts on the first ground-truth box with no loss signals and no re-initialisation (what
--signals none --detector none gives). "overall" pools frames (longer sequences weigh more), "mean" is
the mean of the sequences' mIoU; "diff" is the configuration minus bare.

Columns: "mIoU" counts only boxes the front-end trusted (a box flagged lost counts 0: the drone follows
nothing then); "any box" counts every box the tracker gave, trusted or flagged lost (the paper's view of
the tracker alone). "moved off" counts re-initialisations that moved the box from the target (IoU >= 0.5
with ground truth on the keyframe) to something else; "confirms" counts latched losses withdrawn because
a candidate on the track supported it (policy verified).

Candidates come from the back-end with --backend URL, else from the back-end pipeline in-process on what
flight sends: the keyframe downscaled to [backend] max_keyframe_width and JPEG-encoded as the companion's
client does, the back-end's configured detector (`[detector]`: YOLOX-nano, tiled) and the verifier named
by --verifier (the factory's names: none, local, ... ; default the back-end's [verifier] kind). A query
looks where flight's does (behaviors.query_region): the whole frame while the track is trusted or nothing
is tracked; after a loss the last trusted box grown [behavior] redetect_roi_scale times, to the whole
frame by redetect_full_frame_s (a tiny value: always the whole frame). --detector none: no candidates, no
re-initialisation. --init prompt: the first box is the back-end's answer to the sequence's referring.txt,
asked every --search-s ([backend] search_interval_s) of sequence time and applied --delay-s later
(default 2 s, a hosted VLM) while the sequence runs on, latency-compensated as in flight. As the mission
with [backend] early_answer, a search's fast-stage answer comes first, --early-s (0.3 s) after its
keyframe, and starts a provisional track the --delay-s answer keeps, moves or ends (--no-early: searches
wait for the --delay-s answer; in-process the configured verifier stands in for both stages). As the
companion's back-end worker, at most [backend] max_requests_in_flight requests are out at once and a
keyframe asked for meanwhile waits for an answer (a newer one replaces it); a start needs a "yes" (or
"uncertain" with [behavior] accept_uncertain). Its table prints the ratio to the ground-truth-initialised run and the "ceiling": that
run's IoU from the frame the first answer can arrive over all frames, the most a perfect acquirer reaches
with this delay; and the measured time of the back-end's answers (in-process: the local verifier's real
latency, to try as --delay-s). FPS counts the whole onboard loop except the detector (it runs on the
back-end); edge FPS counts the tracker's update() alone.
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
    parser.add_argument(
        "--tracker", default=None, help="tracker name(s), comma separated (default: [tracker] name)"
    )
    parser.add_argument(
        "--threshold", type=float, help="t_c for scored trackers (default: [tracker] score_threshold)"
    )
    parser.add_argument("--sweep", help="START:STOP:STEP of t_c, e.g. 0.3:0.95:0.05 (scored trackers only)")
    parser.add_argument(
        "--policy",
        choices=(*POLICIES, "both", "all"),
        default=None,
        help="what a re-detection answer may do: verified (move only on evidence, twice in a "
        "row; else wait), c_box (the paper: nearest to the last trusted box), score (highest "
        "detector score), both (c_box and score) or all (default: [tracker] reinit_policy)",
    )
    parser.add_argument(
        "--init",
        choices=("gt", "prompt"),
        default="gt",
        help="first box: the first ground-truth box (gt, default) or the back-end's answer "
        "to the sequence's referring.txt (prompt)",
    )
    parser.add_argument(
        "--verifier",
        default=None,
        help="in-process pipeline's verifier by factory name, e.g. none or local "
        "(default: the back-end's [verifier] kind)",
    )
    parser.add_argument(
        "--keyframe-s",
        type=float,
        default=None,
        help="seconds of sequence time between back-end requests (default: [backend] keyframe_interval_s)",
    )
    parser.add_argument(
        "--search-s",
        type=float,
        default=None,
        help="... while nothing is tracked or the track is lost, as the mission's search and re-detection "
        "(default: [backend] search_interval_s)",
    )
    parser.add_argument(
        "--signals",
        default=None,
        help="loss signals in use: all, none or a list such as score,jump (default: [tracker] loss_signals)",
    )
    parser.add_argument("--size", help="resize frames to WIDTHxHEIGHT, e.g. 640x480 (default: native)")
    parser.add_argument(
        "--detector",
        choices=("yolox", "none"),
        default="yolox",
        help="in-process detector for re-initialisation when no --backend is given",
    )
    parser.add_argument(
        "--backend", metavar="URL", help="ask this CloudTrack back-end for candidates instead"
    )
    parser.add_argument(
        "--delay-s",
        type=float,
        default=None,
        help="simulated back-end latency in seconds of sequence time "
        "(default 0 with --init gt, 2 with --init prompt)",
    )
    parser.add_argument(
        "--early-s",
        type=float,
        default=0.3,
        help="--init prompt with [backend] early_answer: seconds until a search's fast-stage answer "
        "(the local verifier's), which starts a provisional track the --delay-s answer confirms, moves or "
        "ends (default 0.3, the local stage's p90 answer time measured here)",
    )
    parser.add_argument(
        "--no-early",
        action="store_true",
        help="searches wait for the --delay-s answer (as with [backend] early_answer = false)",
    )
    parser.add_argument(
        "--no-compensation", action="store_true", help="apply late answers without fast-forwarding"
    )
    parser.add_argument(
        "--reverify-s",
        type=float,
        default=0.0,
        help="also re-initialise from candidates every S seconds while tracking (default 0: off)",
    )
    parser.add_argument(
        "--occlude",
        action="store_true",
        help="stress test: hide the target for 1.5 s from a third of each sequence (ground truth nan there)",
    )
    parser.add_argument(
        "--signal-table",
        action="store_true",
        help="instead of mIoU: score every loss signal against the frames really off target "
        "(and its false alarms on target), and detector box extent against the ground truth",
    )
    parser.add_argument("--max-frames", type=int, help="use only the first N frames of each sequence")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write every result as JSON")
    parser.add_argument(
        "--plot",
        type=Path,
        metavar="OUT.png",
        help="IoU per frame per sequence, or with --sweep the mIoU/FPS-versus-t_c curves",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_model_dir_flag(parser)
    add_config_flags(parser)
    parser.set_defaults(func=run)


def _detector(
    args: argparse.Namespace, model_dir: Path, seq: SequenceData, stage: str = "final"
) -> DetectFn | None:
    """The back-end's answers for `seq`; with `stage` "early" its fast stage's (in-process: None when the
    verifier has no slower stage, its answers being final already)."""
    prompt = seq.referring or "a person"
    if args.backend:
        from cloudtrack.api_client import BackendClient, BackendError

        backend = args.backend_config
        client = BackendClient(
            args.backend,
            backend.token,
            backend.timeout_s,
            backend.jpeg_quality,
            backend.max_keyframe_width,
            vehicle_id=args.vehicle_id,
            mission_id=f"eval-{seq.name}",
        )

        def ask_backend(image: np.ndarray, frame_id: int, region: Box | None) -> list[Detection]:
            try:
                return client.detect_reply(
                    image, prompt, frame_id=frame_id, roi=region, stage=stage
                ).detections
            except BackendError as exc:  # a failed request is an empty answer, as in flight
                log.warning("%s frame %d: back-end request failed: %s", seq.name, frame_id, exc)
                return []

        return ask_backend
    if args.detector == "none":
        return None
    from backend.supersets import UnknownSupersetError, coco_classes_for, superset_from_prompt

    superset = superset_from_prompt(seq.referring) or "person"
    try:
        coco_classes_for(superset)
    except UnknownSupersetError:
        log.warning("%s: no detector class for %r; no re-initialisation on this sequence", seq.name, superset)
        return None
    pipeline = _pipeline(model_dir, args.verifier_kind)
    if stage == "early":
        pipeline = pipeline.early_stage()
        if pipeline is None:
            return None
    keyframes = args.backend_config

    def detect(image: np.ndarray, frame_id: int, region: Box | None) -> list[Detection]:
        # What flight sends (the keyframe downscaled and JPEG-encoded as the companion's client does), then
        # the back-end's own path: its configured detector, margin crops, the verifier's verdicts.
        jpeg, scale = encode_keyframe(image, keyframes.max_keyframe_width, keyframes.jpeg_quality)
        sent = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        roi = region.scaled(scale, scale) if region is not None else None
        found = pipeline.run(sent, prompt, superset, roi=roi, frame_id=frame_id)
        return [_unscaled(c.detection, scale) for c in found.candidates]

    return detect


def _target_kind(seq: SequenceData) -> str:
    """The class the sequence's description names (its superset), as a ground-truth start knows it."""
    from backend.supersets import superset_from_prompt

    return superset_from_prompt(seq.referring) or "person" if seq.referring else ""


def _unscaled(detection: Detection, scale: float) -> Detection:
    body = detection.body_box
    return replace(
        detection,
        box=detection.box.scaled(1 / scale, 1 / scale),
        body_box=body.scaled(1 / scale, 1 / scale) if body is not None else None,
    )


@functools.lru_cache(maxsize=4)
def _pipeline(model_dir: Path, verifier_kind: str) -> Any:
    """The back-end's pipeline as its configuration builds it (`[detector]`: YOLOX-nano with the
    configured tiles), on the weights in `model_dir`, with the verifier named `verifier_kind`."""
    from concurrent.futures import ThreadPoolExecutor

    from backend.config import VerifierConfig, VlmConfig, load_backend_config
    from backend.detectors.factory import build_detector
    from backend.pipeline import Pipeline
    from backend.verifiers.factory import build_verifier

    detector_config = load_backend_config().detector.model_copy(update={"model_dir": str(model_dir)})
    verifier = build_verifier(VerifierConfig(kind=verifier_kind), VlmConfig())
    pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="eval-verify")
    return Pipeline(build_detector(detector_config), verifier, pool)


def _fmt(value: float, digits: int = 3) -> str:
    return "nan" if not math.isfinite(value) else f"{value:.{digits}f}"


def _print_table(
    label: str, results: Sequence[SequenceResult], bare: Sequence[SequenceResult], framing_bound: float
) -> dict[str, Any]:
    """The configuration beside the bare tracker, sequence by sequence, from the same run."""
    print(f"\n{label}")
    print(
        f"{'sequence':<22} {'frames':>6} {'bare':>6} {'mIoU':>6} {'diff':>7} {'any box':>7} {'FPS':>7} "
        f"{'edge FPS':>8} {'re-inits':>8} {'moved off':>9} {'confirms':>8} {'losses':>6}  "
        "lost frames by reason"
    )
    for r, b in zip(results, bare, strict=True):
        reasons = ", ".join(f"{k}:{v}" for k, v in sorted(r.loss_reasons.items())) or "-"
        moved_off = r.reinit_outcomes.get("target->other", 0)
        print(
            f"{r.sequence:<22} {r.frames:>6} {_fmt(b.miou):>6} {_fmt(r.miou):>6} "
            f"{_signed(r.miou - b.miou):>7} {_fmt(r.miou_any_box):>7} {_fmt(r.fps, 1):>7} "
            f"{_fmt(r.edge_fps, 1):>8} {r.reinits:>8} {moved_off:>9} {r.confirmations:>8} "
            f"{r.loss_events:>6}  {reasons}"
        )
    total, base = overall(results), overall(bare)
    moved = total["reinit_outcomes"].get("target->other", 0)
    print(
        f"{'overall (frames)':<22} {total['frames']:>6} {_fmt(base['miou']):>6} {_fmt(total['miou']):>6} "
        f"{_signed(total['miou'] - base['miou']):>7} {_fmt(total['miou_any_box']):>7} "
        f"{_fmt(total['fps'], 1):>7} "
        f"{_fmt(total['edge_fps'], 1):>8} {total['reinits']:>8} {moved:>9} {total['confirmations']:>8} "
        f"{total['loss_events']:>6}"
    )
    print(
        f"{'mean (sequences)':<22} {'':>6} {_fmt(base['mean_miou']):>6} {_fmt(total['mean_miou']):>6} "
        f"{_signed(total['mean_miou'] - base['mean_miou']):>7}"
    )
    outcomes = ", ".join(f"{k}:{v}" for k, v in sorted(total["reinit_outcomes"].items())) or "none"
    print(f"re-initialisations by where the box was -> went (IoU >= 0.5 with ground truth): {outcomes}")
    _print_framing(total["framing"], results, framing_bound)
    print(
        "bare: first ground-truth box, no loss signals, no re-initialisation; mIoU: trusted boxes only; "
        "any box: every tracker box, trusted or flagged lost"
    )
    return total


def _print_framing(
    summary: dict[str, dict[str, float]], results: Sequence[SequenceResult], bound: float
) -> None:
    """How tracks framed the object the detector found on them, on target and off it ("verified" only)."""
    on, off = summary["on_target"], summary["off_target"]
    if not on["n"] and not off["n"]:
        return
    above = sum(ratio > bound for r in results for overlap, ratio in r.framing if overlap >= ON_TARGET_IOU)
    print(
        f"framing (track / the detector's box on it, larger of w and h) when the track's own candidate "
        f"decided an answer: on target (IoU >= {ON_TARGET_IOU}) n={on['n']:.0f} median {_fmt(on['median'], 2)} "
        f"p95 {_fmt(on['p95'], 2)} max {_fmt(on['max'], 2)}, {above} above the re-framing bound {bound:g}; "
        f"off target (IoU < {OFF_TARGET_IOU}) n={off['n']:.0f} median {_fmt(off['median'], 2)}"
    )


def _signed(value: float) -> str:
    return "nan" if not math.isfinite(value) else f"{value:+.3f}"


def _print_acquisition(
    results: Sequence[SequenceResult],
    reference: Sequence[SequenceResult],
    delays: dict[str, int],
    delay_s: float,
) -> dict[str, Any]:
    """--init prompt: time to the first box, mIoU beside the ground-truth start and beside the ceiling a
    perfect acquirer reaches with answers `delay_s` late, and every answer while looking (was the chosen
    candidate the described target?)."""
    print(
        f"\n{'sequence':<22} {'first box s':>11} {'1st verified':>12} {'prompt mIoU':>11} "
        f"{'gt-init mIoU':>12} {'ratio':>6} {'ceiling':>7} {'ceil ratio':>10}  "
        "answers while acquiring (keyframe:candidates/yes, T target among them, =target/=OTHER chosen; "
        "e: the fast stage's early answer)"
    )
    ceilings = []
    for r, g in zip(results, reference, strict=True):
        answers = (
            " ".join(
                f"{'' if a.final else 'e'}{a.frame_id}:{a.candidates}/{a.confirmed}"
                f"{'T' if a.target_found else '-'}"
                f"{'' if a.chosen_iou is None else ('=target' if a.chosen_iou >= 0.5 else '=OTHER')}"
                for a in r.acquisition
            )
            or "-"
        )
        first = "never" if r.first_box_s is None else f"{r.first_box_s:.1f}"
        chosen = next((a.chosen_iou for a in r.acquisition if a.chosen_iou is not None and a.final), None)
        verdict = "-" if chosen is None else ("target" if chosen >= 0.5 else "OTHER")
        ratio = r.miou / g.miou if g.miou > 0 else float("nan")
        ceiling = acquisition_ceiling(g, delays[r.sequence])
        ceilings.append(ceiling)
        print(
            f"{r.sequence:<22} {first:>11} {verdict:>12} {_fmt(r.miou):>11} {_fmt(g.miou):>12} "
            f"{_fmt(ratio, 2):>6} {_fmt(ceiling.miou):>7} "
            f"{_fmt(ceiling.miou / g.miou if g.miou > 0 else float('nan'), 2):>10}  {answers}"
        )
    total, ref = overall(results), overall(reference)
    ratio = total["miou"] / ref["miou"] if ref["miou"] > 0 else float("nan")
    ceiling_miou = pooled_miou(ceilings)
    ceiling_ratio = ceiling_miou / ref["miou"] if ref["miou"] > 0 else float("nan")
    print(
        f"{'overall (frames)':<22} {'':>11} {'':>12} {_fmt(total['miou']):>11} {_fmt(ref['miou']):>12} "
        f"{_fmt(ratio, 2):>6} {_fmt(ceiling_miou):>7} {_fmt(ceiling_ratio, 2):>10}"
    )
    for final, what in ((True, "verified boxes"), (False, "early starts")):
        chosen_all = [
            a for r in results for a in r.acquisition if a.chosen_iou is not None and a.final is final
        ]
        right = sum(a.chosen_iou is not None and a.chosen_iou >= 0.5 for a in chosen_all)
        if final or chosen_all:
            print(f"first {what} on the described target: {right} of {len(chosen_all)}")
    print(
        "the first verified choice per sequence: verdict and what was judged; how many others fit as well "
        "(the detector's score chose); then what nothing judged"
    )
    for r in results:
        picked = next((a for a in r.acquisition if a.chosen_iou is not None and a.final), None)
        if picked is None:
            print(f"  {r.sequence}: none chosen")
            continue
        where = {True: "fits", False: "does not fit", None: "not judged"}[picked.placement]
        on_target = (picked.chosen_iou or 0.0) >= 0.5
        print(
            f"  {r.sequence} (keyframe {picked.frame_id}, {'target' if on_target else 'OTHER'}): "
            f"{picked.verdict or '-'}, placement {where}: {picked.justification or '-'}; "
            f"{picked.alike} others alike; not judged: {'; '.join(picked.unjudged) or '-'}"
        )
    print(
        f"ceiling: the ground-truth-initialised run's IoU from the frame the first answer can arrive "
        f"({delay_s:g} s after the first frame) over all frames: what a perfect acquirer could reach "
        f"with this delay; ceil ratio = ceiling / gt-init (the most the ratio can be)"
    )
    return {"ratio": ratio, "ceiling_miou": ceiling_miou, "ceiling_ratio": ceiling_ratio}


def _print_answer_time(caches: dict[str, DetectionCache | None], source: str) -> dict[str, float] | None:
    """The measured time of the back-end's answers in this run (each keyframe's detection and
    verification, wall clock): the delay to try with --delay-s for an in-process (local) verifier."""
    seconds = sorted(t for c in caches.values() if c is not None for t in c.seconds)
    if not seconds:
        return None
    figures = {
        "answers": float(len(seconds)),
        "median_s": float(np.median(seconds)),
        "p90_s": float(np.percentile(seconds, 90)),
        "max_s": seconds[-1],
    }
    print(
        f"answer time of {source} in this run: {len(seconds)} keyframes, median "
        f"{figures['median_s']:.2f} s, p90 {figures['p90_s']:.2f} s, max {figures['max_s']:.2f} s "
        "(wall clock per keyframe, detection + verification)"
    )
    return figures


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
        signals = (
            parse_signals(args.signals)
            if args.signals is not None
            else frozenset(config.tracker.loss_signals)
        )
        size = parse_size(args.size) if args.size else None
        sweep = parse_sweep(args.sweep) if args.sweep else None
        if args.threshold is not None and not 0 <= args.threshold <= 1:
            raise ValueError(f"--threshold {args.threshold}: must be between 0 and 1")
        if args.max_frames is not None and args.max_frames < 2:
            raise ValueError("--max-frames must be at least 2")
        seqs = [load_sequence(p) for p in args.sequences]
        if args.keyframe_s is None:
            args.keyframe_s = config.backend.keyframe_interval_s
        if args.search_s is None:
            args.search_s = config.backend.search_interval_s
        if args.keyframe_s <= 0 or args.search_s <= 0:
            raise ValueError("--keyframe-s and --search-s must be positive")
        args.backend_config = config.backend
        args.vehicle_id = config.vehicle.id
        args.early = config.backend.early_answer and not args.no_early
        if args.early and args.early_s < 0:
            raise ValueError("--early-s must not be negative")
    except (ConfigError, ModelError, TrackerUnavailableError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    from tqdm.contrib.logging import logging_redirect_tqdm

    policies: list[str]
    if args.policy in ("both", "all"):
        policies = ["c_box", "score"] if args.policy == "both" else list(POLICIES)
    else:
        policies = [args.policy or config.tracker.reinit_policy]
    try:
        from backend.config import load_backend_config

        args.verifier_kind = args.verifier or load_backend_config().verifier.kind
        if not args.backend and args.detector != "none":
            _pipeline(model_dir, args.verifier_kind)
        detectors = {s.name: _detector(args, model_dir, s) for s in seqs}
    except (ModelError, ConfigError, ValueError) as exc:  # pydantic's ValidationError is a ValueError
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.init == "prompt" and not any(detectors.values()):
        print("error: --init prompt needs candidates (the in-process pipeline or --backend)", file=sys.stderr)
        return 2
    caches = {name: DetectionCache(fn) if fn is not None else None for name, fn in detectors.items()}
    early_caches: dict[str, DetectionCache | None] = {name: None for name in caches}
    if args.init == "prompt" and args.early:
        for seq in seqs:
            fn = _detector(args, model_dir, seq, "early") if caches[seq.name] is not None else None
            early_caches[seq.name] = DetectionCache(fn) if fn is not None else None
    output: dict[str, Any] = {"command": sys.argv[1:], "runs": []}

    if args.signal_table:
        for name in trackers:
            report = signal_table(
                seqs,
                config.tracker,
                model_dir,
                name,
                size,
                args.max_frames,
                args.occlude,
                caches,
                keyframe_s=args.keyframe_s,
                kinds={s.name: _target_kind(s) for s in seqs},
            )
            _print_signal_table(report, config.tracker.loss_persistence_s)
            output["runs"].append({"signal_table": _signal_dict(report)})
        _write_json(args.json, output)
        return 0

    if sweep:
        skipped = [t for t in trackers if t not in config.tracker.score_threshold]
        if skipped:
            print(f"--sweep: {', '.join(skipped)} ha(s) no score and no t_c; not swept", file=sys.stderr)
        trackers = [t for t in trackers if t in config.tracker.score_threshold]
    thresholds: list[float | None] = list(sweep) if sweep else [args.threshold]
    runs = len(policies) * len(thresholds) * (2 if args.init == "prompt" else 1) + 1  # + the bare tracker
    total_frames = (
        sum(min(len(s.ground_truth), args.max_frames or len(s.ground_truth)) for s in seqs)
        * len(trackers)
        * runs
    )
    with logging_redirect_tqdm():
        return _run_evals(
            args,
            config,
            model_dir,
            trackers,
            seqs,
            policies,
            thresholds,
            sweep,
            signals,
            size,
            caches,
            early_caches,
            output,
            total_frames,
        )


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
    early_caches: dict[str, DetectionCache | None],
    output: dict[str, Any],
    total_frames: int,
) -> int:
    from tqdm import tqdm

    bar = tqdm(total=total_frames, unit="frame", disable=args.no_progress, file=sys.stderr)
    sweep_points: dict[str, list[tuple[float, float, float]]] = {}
    last_results: list[SequenceResult] = []
    delay_s = args.delay_s if args.delay_s is not None else (2.0 if args.init == "prompt" else 0.0)
    has_candidates = any(c is not None for c in caches.values())
    early = args.early and args.init == "prompt"
    source = (
        f"back-end {args.backend}" if args.backend else (f"in-process YOLOX + verifier {args.verifier_kind}")
    )

    def run_all(settings: EvalSettings, with_candidates: bool = True) -> list[SequenceResult]:
        results = []
        for seq in seqs:
            seq_settings = replace(
                settings,
                delay_frames=round(delay_s * seq.fps),
                keyframe_interval=max(1, round(args.keyframe_s * seq.fps)),
                search_interval=max(1, round(args.search_s * seq.fps)),
                max_in_flight=args.backend_config.max_requests_in_flight,
                reverify_interval=round(args.reverify_s * seq.fps),
                early_frames=round(args.early_s * seq.fps) if args.early else None,
                target_kind=_target_kind(seq),
            )
            results.append(
                evaluate_sequence(
                    seq,
                    config.tracker,
                    model_dir,
                    seq_settings,
                    caches[seq.name] if with_candidates else None,
                    progress=bar.update,
                    early_detections=early_caches[seq.name] if with_candidates else None,
                )
            )
        bar.clear()
        return results

    bound = config.tracker.reinit_max_framing_ratio
    for name in trackers:
        # The baseline every configuration must beat, on the same frames and size in this same run.
        bare = run_all(
            EvalSettings(
                tracker=name, signals=frozenset(), size=size, max_frames=args.max_frames, occlude=args.occlude
            ),
            with_candidates=False,
        )
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
                    accept_uncertain=config.behavior.accept_uncertain,
                    region_scale=config.behavior.redetect_roi_scale,
                    region_full_frame_s=config.behavior.redetect_full_frame_s,
                )
                results = run_all(settings)
                t_c = threshold if threshold is not None else config.tracker.score_threshold.get(name, "-")
                label = (
                    f"tracker {name}, t_c={t_c}, policy {policy}, size {args.size or 'native'}, "
                    f"candidates: {source if has_candidates else 'none'}, "
                    f"keyframe every {args.keyframe_s:g} s (searching every {args.search_s:g} s), "
                    f"delay {delay_s:g} s"
                    + (f", searches start on the fast stage's answer at {args.early_s:g} s" if early else "")
                )
                run: dict[str, Any] = {
                    "tracker": name,
                    "threshold": threshold,
                    "policy": policy,
                    "size": args.size,
                    "init": args.init,
                    "delay_s": delay_s,
                    "early_s": args.early_s if early else None,
                    "keyframe_s": args.keyframe_s,
                    "search_s": args.search_s,
                }
                if args.init == "prompt":
                    prompted = run_all(replace(settings, init="prompt"))
                    _print_table(f"{label}, first box from the ground truth", results, bare, bound)
                    total = _print_table(
                        f"{label}, first box from the prompt (--init prompt)", prompted, bare, bound
                    )
                    first_answer_s = args.early_s if early else delay_s
                    run["acquisition"] = _print_acquisition(
                        prompted,
                        results,
                        {q.name: round(first_answer_s * q.fps) for q in seqs},
                        first_answer_s,
                    )
                    run["gt_init"] = {
                        "overall": overall(results),
                        "sequences": [result_dict(r) for r in results],
                    }
                    results = prompted
                else:
                    total = _print_table(label, results, bare, bound)
                run.update(
                    {
                        "overall": total,
                        "sequences": [result_dict(r) for r in results],
                        "bare": {"overall": overall(bare), "sequences": [result_dict(r) for r in bare]},
                    }
                )
                output["runs"].append(run)
                if sweep and threshold is not None:
                    sweep_points.setdefault(name, []).append((threshold, total["miou"], total["fps"]))
                last_results = results
    bar.close()
    if args.init == "prompt":
        output["answer_time"] = _print_answer_time(caches, source)
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
        "on_target_frames": report.on_target_frames,
        "signals": {k: vars(v) for k, v in report.counts.items()},
        "combinations": {k: vars(v) for k, v in report.combos.items()},
        "keyframes": report.keyframes,
        "target_detected": report.target_detected,
        "detector_extent": report.detector_extent,
        "tracker_extent": report.tracker_extent,
        "decided": vars(report.decided),
        "detection_delays_s": report.detection_delays_s,
        "episodes_missed": report.episodes_missed,
    }


def _print_signal_table(report: Any, persistence_s: float) -> None:
    print(
        f"\ntracker {report.tracker}: {report.frames} frames, {report.lost_frames} off target "
        "(IoU < 0.1 or "
        f"target hidden), {report.on_target_frames} on target (IoU >= 0.5); tracked from the first box, "
        "never re-initialised"
    )
    print(f"{'signal':<28} {'fired':>6} {'off target':>10} {'on target':>9} {'precision':>9} {'recall':>7}")
    for name, c in [*report.counts.items(), *report.combos.items()]:
        precision = c.fired_lost / c.fired if c.fired else float("nan")
        recall = c.fired_lost / report.lost_frames if report.lost_frames else float("nan")
        print(
            f"{name:<28} {c.fired:>6} {c.fired_lost:>10} {c.fired_on_target:>9} {_fmt(precision, 2):>9} "
            f"{_fmt(recall, 2):>7}"
        )
    d = report.decided
    precision = d.fired_lost / d.fired if d.fired else float("nan")
    recall = d.fired_lost / report.lost_frames if report.lost_frames else float("nan")
    label = f"untrusted (persistence {persistence_s:g} s)"
    print(
        f"{label:<28} {d.fired:>6} {d.fired_lost:>10} {d.fired_on_target:>9} {_fmt(precision, 2):>9} "
        f"{_fmt(recall, 2):>7}"
    )
    print("(off target: hits; on target: false alarms, each a frame the drone stops following a right track)")
    delays = report.detection_delays_s
    episodes = len(delays) + report.episodes_missed
    if episodes:
        median = f"{float(np.median(delays)):.2f} s" if delays else "-"
        worst = f"{max(delays):.2f} s" if delays else "-"
        print(
            f"runs off target: {episodes}; untrusted in {len(delays)} (delay median {median}, max {worst}), "
            f"never in {report.episodes_missed}"
        )
    if report.keyframes:
        print(
            f"detector on {report.keyframes} keyframes: the target detected (IoU >= 0.5) on "
            f"{report.target_detected}"
        )
        extents = (("detector", report.detector_extent), ("tracker on target", report.tracker_extent))
        for label, ratios in extents:
            if ratios:
                w = np.median([r[0] for r in ratios])
                h = np.median([r[1] for r in ratios])
                print(
                    f"  {label:<18} box / ground truth, median width {w:.2f}, height {h:.2f} "
                    f"({len(ratios)} boxes)"
                )


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
    ax.set(
        xlabel="frame",
        ylabel="IoU with ground truth",
        title=f"{results[0].tracker if results else ''} IoU per frame",
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
